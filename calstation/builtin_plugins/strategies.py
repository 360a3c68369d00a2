"""Registers the built-in fine-tuning strategies."""

from __future__ import annotations
