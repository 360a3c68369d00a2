"""The paper bench on harder simulated stations: 2 mm range noise, and no background.

    .venv/bin/python benchmarks/paper_variants.py [--variants noise-2mm,no-background]
        [--starts 5] [--workers 2] [--report-root docs/bench-variants]

Each variant is recipes/sim-periodicity.yaml with one simulation setting changed, written to
``out/bench-<variant>/recipe.yaml``; ``calstation bench paper`` then runs on it (the nine
scenarios, the initial calibration and ``--starts`` set-A and set-B starts per scenario and
method, no cost landscapes, and the ablations from the initial calibration only) and writes
``<report-root>/<variant>/results.md``.
``default`` is the recipe unchanged.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]

VARIANTS = {
    "default": {},
    "noise-2mm": {"lidar": {"range_noise": 0.002}},
    "no-background": {"background": {"enabled": False}},
}
"""Per variant, the keys of the recipe's ``simulation`` section it changes."""


def variant_recipe(name: str, out: Path) -> Path:
    """Write the variant's recipe into ``out``; its path."""
    data = yaml.safe_load((REPO / "recipes/sim-periodicity.yaml").read_text())
    for key, value in VARIANTS[name].items():
        if isinstance(value, dict) and isinstance(data["simulation"].get(key), dict):
            data["simulation"][key].update(value)
        else:
            data["simulation"][key] = value
    out.mkdir(parents=True, exist_ok=True)
    path = out / "recipe.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variants", default="noise-2mm,no-background",
                        help=f"comma-separated, of {', '.join(VARIANTS)}")
    parser.add_argument("--starts", type=int, default=5, help="set-A and set-B starts")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--report-root", type=Path, default=REPO / "out" / "bench-variants")
    args = parser.parse_args()
    for name in args.variants.split(","):
        if name not in VARIANTS:
            parser.error(f"--variants: unknown variant {name!r} (known: {', '.join(VARIANTS)})")
        out = REPO / "out" / f"bench-{name}"
        recipe = variant_recipe(name, out)
        changed = ", ".join(f"simulation.{k}: {v}" for k, v in VARIANTS[name].items())
        label = (f"Variant **{name}** of the paper bench (`benchmarks/paper_variants.py`): "
                 f"recipes/sim-periodicity.yaml with {changed or 'nothing'} changed; "
                 f"{args.starts} set-A and {args.starts} set-B starts per scenario and method, "
                 "no cost landscapes, and the ablations from the initial calibration only.")
        command = [
            str(Path(sys.executable).parent / "calstation"), "bench", "paper",
            "--recipe", str(recipe),
            "--out", str(out), "--report-dir", str(args.report_root / name),
            "--workers", str(args.workers), "--starts", str(args.starts),
            "--landscape-grid", "0", "--ablation-starts", "0", "--label", label,
        ]
        print(" ".join(command), flush=True)
        code = subprocess.call(command, cwd=REPO)
        if code:
            return code
    return 0


if __name__ == "__main__":
    sys.exit(main())
