"""Registers the simulated station's drivers and commands."""

from __future__ import annotations
