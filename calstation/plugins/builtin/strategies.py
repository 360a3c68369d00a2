"""Registers the built-in fine-tuning strategies (``periodicity``, ``shape``) through the same
hook third-party plugins use."""

from __future__ import annotations

from calstation import hookimpl
from calstation.plugins.hookspecs import RegisterStrategy


@hookimpl
def calstation_register_cost_strategies(register: RegisterStrategy) -> None:
    """Register ``periodicity`` and ``shape`` (imported when a strategy is first looked up, not
    when the CLI starts)."""
    from calstation.plugins.cost_strategies import BUILTIN_STRATEGIES

    for strategy in BUILTIN_STRATEGIES:
        register(strategy)
