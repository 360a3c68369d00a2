"""The plugin manager and the small typed facade application code uses.

Built-in plugins are ordinary modules listed in :data:`DEFAULT_PLUGINS`; third-party plugins (and
the plugin packages shipped under ``plugins/``) come from the ``calstation`` entry-point group.

Environment variables:

- ``CALSTATION_BLOCK_PLUGINS``: comma-separated plugin names not to load (entry-point names or
  built-in module names).
- ``CALSTATION_TRACE_HOOKS``: when set to ``1``, every hook call and result is printed to stderr.
"""

from __future__ import annotations

import importlib
import os
import sys
import threading
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, overload

import pluggy

from calstation.errors import PluginError
from calstation.jsonvalue import JSONObject
from calstation.plugins import hookspecs
from calstation.plugins.hookspecs import (
    DriverFactory,
    EncoderFactory,
    LidarFactory,
    RunBrief,
    RunSummary,
    TurntableFactory,
)

if TYPE_CHECKING:
    import typer

    from calstation.drivers import DriverContext
    from calstation.plugins.cost_strategies import Strategy
    from calstation.plugins.simulation import Simulator

DEFAULT_PLUGINS: tuple[str, ...] = (
    "calstation.plugins.builtin.strategies",
    "calstation.plugins.builtin.replay",
)
"""Modules that register calstation's built-in strategies and drivers through the hooks."""

ENTRY_POINT_GROUP = "calstation"
DRIVER_KINDS = ("lidar", "turntable", "encoder")

_pm: pluggy.PluginManager | None = None
_loaded = False
_lock = threading.RLock()


def get_plugin_manager() -> pluggy.PluginManager:
    """The one plugin manager (hook specs added, nothing loaded yet)."""
    global _pm
    with _lock:
        if _pm is None:
            _pm = pluggy.PluginManager("calstation")
            _pm.add_hookspecs(hookspecs)
        return _pm


def blocked_plugins() -> set[str]:
    """Names in ``CALSTATION_BLOCK_PLUGINS``."""
    raw = os.environ.get("CALSTATION_BLOCK_PLUGINS", "")
    return {name.strip() for name in raw.split(",") if name.strip()}


def load_plugins() -> pluggy.PluginManager:
    """Load built-in and entry-point plugins once; later calls return the same manager.

    Raises :class:`PluginError` when a plugin cannot be imported or implements a hook that does not
    exist (``check_pending``), naming the plugin.
    """
    global _loaded
    pm = get_plugin_manager()
    with _lock:
        if _loaded:
            return pm
        blocked = blocked_plugins()
        for name in blocked:
            pm.set_blocked(name)
        for modname in DEFAULT_PLUGINS:
            if modname in blocked or pm.has_plugin(modname):
                continue
            try:
                module = importlib.import_module(modname)
            except ImportError as exc:
                raise PluginError(f"built-in plugin {modname} failed to import: {exc}") from exc
            pm.register(module, name=modname)
        try:
            pm.load_setuptools_entrypoints(ENTRY_POINT_GROUP)
        except Exception as exc:  # a broken third-party plugin must not hide behind a traceback
            raise PluginError(
                f"a plugin in entry-point group '{ENTRY_POINT_GROUP}' failed to load: {exc}"
            ) from exc
        try:
            pm.check_pending()
        except pluggy.PluginValidationError as exc:
            raise PluginError(f"plugin {exc.plugin!r} implements an unknown hook: {exc}") from exc
        if os.environ.get("CALSTATION_TRACE_HOOKS") == "1":
            _enable_tracing(pm)
        _loaded = True
        _registry_cache.clear()
        return pm


def _enable_tracing(pm: pluggy.PluginManager) -> None:
    def before(
        hook_name: str, hook_impls: Sequence[pluggy.HookImpl], kwargs: Mapping[str, object]
    ) -> None:
        names = ", ".join(impl.plugin_name for impl in hook_impls)
        print(f"[calstation hook] {hook_name}({', '.join(kwargs)}) → {names}", file=sys.stderr)

    def after(
        outcome: pluggy.Result[object], hook_name: str, hook_impls: Sequence[pluggy.HookImpl],
        kwargs: Mapping[str, object],
    ) -> None:
        print(f"[calstation hook] {hook_name} returned {outcome.get_result()!r}", file=sys.stderr)

    pm.add_hookcall_monitoring(before, after)


def _trace(message: str) -> None:
    """Print a hook-trace line when ``CALSTATION_TRACE_HOOKS=1``."""
    if os.environ.get("CALSTATION_TRACE_HOOKS") == "1":
        print(f"[calstation hook] {message}", file=sys.stderr)


def reset_for_tests() -> None:
    """Forget loaded plugins and registries (tests only)."""
    global _pm, _loaded
    with _lock:
        _pm = None
        _loaded = False
        _registry_cache.clear()


@contextmanager
def isolated(*plugins: object, builtins: bool = True) -> Iterator[pluggy.PluginManager]:
    """A plugin manager holding only ``plugins`` (and the built-ins), for tests.

    Entry-point plugins are not loaded, so a test sees exactly what it registers; the previous
    manager is restored on exit, whatever happens.
    """
    global _pm, _loaded
    with _lock:
        saved = (_pm, _loaded, _registry_cache.copy())
        pm = pluggy.PluginManager("calstation")
        pm.add_hookspecs(hookspecs)
        _pm, _loaded = pm, True
        _registry_cache.clear()
    try:
        if builtins:
            for modname in DEFAULT_PLUGINS:
                pm.register(importlib.import_module(modname), name=modname)
        for plugin in plugins:
            pm.register(plugin, name=getattr(plugin, "__name__", None))
        try:
            pm.check_pending()
        except pluggy.PluginValidationError as exc:
            raise PluginError(f"plugin {exc.plugin!r} implements an unknown hook: {exc}") from exc
        yield pm
    finally:
        with _lock:
            _pm, _loaded = saved[0], saved[1]
            _registry_cache.update(saved[2])


@dataclass(frozen=True)
class PluginInfo:
    """One loaded plugin: its name, where it comes from, and the hooks it implements."""

    name: str
    source: str
    version: str | None
    hooks: tuple[str, ...] = field(default_factory=tuple)


def plugin_report() -> list[PluginInfo]:
    """Every loaded plugin with the hooks it implements, built-ins first."""
    pm = load_plugins()
    dists = {id(plugin): dist for plugin, dist in pm.list_plugin_distinfo()}
    infos = []
    for name, plugin in pm.list_name_plugin():
        if plugin is None:  # blocked
            continue
        hooks = tuple(sorted(h.name for h in pm.get_hookcallers(plugin) or ()))
        dist = dists.get(id(plugin))
        if dist is not None:
            source = f"entry point of {dist.project_name}"
            version = str(dist.version)
        else:
            source = "built-in" if name in DEFAULT_PLUGINS else "registered"
            version = None
        infos.append(PluginInfo(name=name, source=source, version=version, hooks=hooks))
    infos.sort(key=lambda i: (i.source != "built-in", i.name))
    return infos


# --- registries ----------------------------------------------------------------------------
@dataclass(frozen=True)
class DriverEntry:
    """One registered driver factory."""

    kind: str
    name: str
    factory: DriverFactory
    plugin: str


@dataclass
class _Registries:
    """What the registration hooks gave, built once per plugin manager."""

    drivers: dict[tuple[str, str], DriverEntry] | None = None
    strategies: dict[str, Strategy] | None = None
    strategy_plugins: dict[str, str] = field(default_factory=dict)
    simulators: dict[str, Simulator] | None = None

    def clear(self) -> None:
        self.drivers = self.strategies = self.simulators = None
        self.strategy_plugins = {}

    def copy(self) -> _Registries:
        return _Registries(self.drivers, self.strategies, dict(self.strategy_plugins),
                           self.simulators)

    def update(self, other: _Registries) -> None:
        self.drivers, self.strategies = other.drivers, other.strategies
        self.strategy_plugins, self.simulators = other.strategy_plugins, other.simulators


_registry_cache = _Registries()


def drivers() -> dict[tuple[str, str], DriverEntry]:
    """Every registered driver, by (kind, name)."""
    with _lock:
        if _registry_cache.drivers is not None:
            return dict(_registry_cache.drivers)
        pm = load_plugins()
        found: dict[tuple[str, str], DriverEntry] = {}
        for impl in pm.hook.calstation_register_drivers.get_hookimpls():
            plugin = impl.plugin_name

            def register(
                kind: str, name: str, factory: DriverFactory, _plugin: str = plugin
            ) -> None:
                if kind not in DRIVER_KINDS:
                    raise PluginError(
                        f"plugin {_plugin} registered driver {name!r} of unknown kind {kind!r}; "
                        f"kinds are {', '.join(DRIVER_KINDS)}"
                    )
                if (kind, name) in found:
                    other = found[(kind, name)].plugin
                    raise PluginError(
                        f"{kind} driver {name!r} registered twice: by {other} and by {_plugin}"
                    )
                found[(kind, name)] = DriverEntry(kind, name, factory, _plugin)

            _trace(f"calstation_register_drivers(register) → {plugin}")
            impl.function(register=register)
        _registry_cache.drivers = found
        return dict(found)


@overload
def driver_factory(kind: Literal["lidar"], name: str) -> LidarFactory: ...


@overload
def driver_factory(kind: Literal["turntable"], name: str) -> TurntableFactory: ...


@overload
def driver_factory(kind: Literal["encoder"], name: str) -> EncoderFactory: ...


@overload
def driver_factory(kind: str, name: str) -> DriverFactory: ...


def driver_factory(kind: str, name: str) -> DriverFactory:
    """The factory of driver ``name`` of ``kind`` (registered under that kind, so typed by it);
    :class:`PluginError` lists the known ones."""
    entries = drivers()
    if (kind, name) not in entries:
        known = sorted(n for (k, n) in entries if k == kind)
        raise PluginError(
            f"no {kind} driver named {name!r}; installed: {', '.join(known) or 'none'}"
        )
    return entries[(kind, name)].factory


def strategies() -> dict[str, Strategy]:
    """Every registered fine-tuning strategy, by name."""
    with _lock:
        if _registry_cache.strategies is not None:
            return dict(_registry_cache.strategies)
        from calstation.plugins.cost_strategies import options_model_of

        pm = load_plugins()
        found: dict[str, Strategy] = {}
        owners: dict[str, str] = {}
        for impl in pm.hook.calstation_register_cost_strategies.get_hookimpls():
            plugin = impl.plugin_name

            def register(strategy: Strategy, _plugin: str = plugin) -> None:
                name = getattr(strategy, "name", None)
                if not isinstance(name, str) or not name:
                    raise PluginError(f"plugin {_plugin} registered a strategy without a name")
                if name in found:
                    raise PluginError(
                        f"strategy {name!r} registered twice: by {owners[name]} and by {_plugin}"
                    )
                try:
                    options_model_of(strategy)
                except PluginError as exc:
                    raise PluginError(f"plugin {_plugin}: {exc}") from None
                found[name] = strategy
                owners[name] = _plugin

            _trace(f"calstation_register_cost_strategies(register) → {plugin}")
            impl.function(register=register)
        _registry_cache.strategies = found
        _registry_cache.strategy_plugins = owners
        return dict(found)


def strategy_plugin(name: str) -> str:
    """The name of the plugin that registered strategy ``name`` (see :func:`strategies`)."""
    strategy(name)
    with _lock:
        return _registry_cache.strategy_plugins.get(name, "?")


def strategy(name: str) -> Strategy:
    """The strategy called ``name``; :class:`PluginError` lists the known ones."""
    found = strategies()
    if name not in found:
        raise PluginError(
            f"no fine-tuning strategy named {name!r}; installed: {', '.join(sorted(found))}"
        )
    return found[name]


def simulators() -> dict[str, Simulator]:
    """Every registered simulator, by name (see :mod:`calstation.plugins.simulation`)."""
    with _lock:
        if _registry_cache.simulators is not None:
            return dict(_registry_cache.simulators)
        pm = load_plugins()
        found: dict[str, Simulator] = {}
        owners: dict[str, str] = {}
        for impl in pm.hook.calstation_register_simulators.get_hookimpls():
            plugin = impl.plugin_name

            def register(simulator: Simulator, _plugin: str = plugin) -> None:
                name = getattr(simulator, "name", None)
                if not isinstance(name, str) or not name:
                    raise PluginError(f"plugin {_plugin} registered a simulator without a name")
                if name in found:
                    raise PluginError(
                        f"simulator {name!r} registered twice: by {owners[name]} and by {_plugin}"
                    )
                found[name] = simulator
                owners[name] = _plugin

            _trace(f"calstation_register_simulators(register) → {plugin}")
            impl.function(register=register)
        _registry_cache.simulators = found
        return dict(found)


def simulator(name: str | None = None) -> Simulator:
    """The simulator called ``name`` (default ``sim``, the calstation-sim plugin's);
    :class:`PluginError` says how to install it when there is none."""
    from calstation.plugins.simulation import DEFAULT_SIMULATOR

    wanted = name or DEFAULT_SIMULATOR
    found = simulators()
    if wanted not in found:
        hint = (" (the calstation-sim plugin: pip install 'calstation[sim]')"
                if wanted == DEFAULT_SIMULATOR else "")
        raise PluginError(
            f"no simulator named {wanted!r}{hint}; installed: {', '.join(sorted(found)) or 'none'}"
        )
    return found[wanted]


def fixture_placed(context: DriverContext, fixture: str, geometry: object) -> None:
    """Tell plugins that ``fixture`` is now on the platter."""
    hook = load_plugins().hook
    hook.calstation_fixture_placed(context=context, fixture=fixture, geometry=geometry)


def run_started(run: RunBrief) -> None:
    """Tell observers a run started (or was resumed)."""
    load_plugins().hook.calstation_run_started(run=run)


def step_finished(run: RunBrief, step: str, status: str, result: JSONObject) -> None:
    """Tell observers a step finished."""
    load_plugins().hook.calstation_step_finished(run=run, step=step, status=status, result=result)


def run_finished(run: RunBrief, status: str, summary: RunSummary) -> None:
    """Tell observers a run ended."""
    load_plugins().hook.calstation_run_finished(run=run, status=status, summary=summary)


def register_commands(cli: typer.Typer) -> None:
    """Let plugins add CLI commands."""
    load_plugins().hook.calstation_register_commands(cli=cli)
