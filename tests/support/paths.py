"""Where the tests find the repository's files."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
RECIPES = REPO / "recipes"
DATA = REPO / "tests" / "data"
