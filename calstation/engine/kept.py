"""The last result of each named computation, kept with the key it was made for.

A least-squares solve evaluates its residuals and Jacobian many times, and a finite-difference
step changes only some of the parameters: what depends on the others is the same as at the last
evaluation. :class:`Kept` holds, per name, the last result and the bytes of the values it was
computed from, and computes again only when they differ.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar, cast

T = TypeVar("T")


class Kept:
    """Per name, the last result of a computation and the key it was made for."""

    def __init__(self) -> None:
        self._kept: dict[str, tuple[bytes, object]] = {}

    def get(self, name: str, key: bytes, compute: Callable[[], T]) -> T:
        """``compute()``, or what it gave at the last call of ``name`` when ``key`` is the
        same."""
        kept = self._kept.get(name)
        if kept is None or kept[0] != key:
            kept = (key, compute())
            self._kept[name] = kept
        return cast(T, kept[1])
