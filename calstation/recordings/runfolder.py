"""The recordings a run writes into its folder: the file stem (and artifact kind) of each scan
step's recordings.

Only the standard library, so that the station, the database's journal (loaded by every command
that opens the database), the re-processing and the simulator share one definition at no cost.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

RECORDING_OF: dict[str, str] = {"static_scan": "static", "spin_scan": "spin", "cube_scan": "cube"}
"""Scan step → the kind (and file stem) of its recording."""


def second_pass(kind: str) -> str:
    """The kind (and file stem) of the second pass of a ``kind`` scan
    (``steps.spin_scan.second_pass_rpm``, ``steps.cube_scan.second_pass_rpm``)."""
    return f"{kind}-pass2"


SCAN_RECORDINGS: dict[str, tuple[str, ...]] = {
    step: (kind,) if step == "static_scan" else (kind, second_pass(kind))
    for step, kind in RECORDING_OF.items()
}
"""Scan step → the kinds of its recordings, in the order the station writes them (a second
pass after the first)."""


def file_sha256(path: Path) -> str:
    """sha256 (hex) of a file's bytes: what a run's artifacts are stored and checked with."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
