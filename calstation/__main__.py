"""The ``calstation`` script and ``python -m calstation``."""

from __future__ import annotations

import gc


def main() -> None:
    """Run the command line. Python's cyclic garbage collector stays off while the command line's
    own modules load; :func:`calstation.cli.main` then decides, by the command, whether it stays
    off (``calstation.cli.QUICK_COMMANDS``)."""
    gc.disable()
    from calstation.cli import main as cli_main

    gc.enable()
    cli_main()


if __name__ == "__main__":
    main()
