"""Registers the replay drivers, which play a recording back as if it were hardware."""

from __future__ import annotations
