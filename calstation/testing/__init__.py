"""calstation's kit for plugin authors: test a strategy or a driver without hardware.

- :mod:`calstation.testing.conformance`: checks a driver plugin runs against its own Lidar,
  Turntable and Encoder (functions taking driver factories, and a pytest base class).
- :mod:`calstation.testing.transports`: serve an emulated byte-stream device on TCP or a
  pseudo-terminal, and scripted request/reply devices (PyMeasure's ``expected_protocol`` style).
- :mod:`calstation.testing.canbus`: an emulated CANopen node on python-can to build device
  emulators on.
- :mod:`calstation.testing.fixtures`: pytest fixtures giving the recordings of a simulated run
  (through the ``calstation-sim`` plugin when installed) for a strategy test; import them into a
  ``conftest.py``.
- :mod:`calstation.testing.hostile`: hostile files made on purpose (decompression bombs, flipped
  bytes), for reliability tests.
- :func:`simulate_scans` and :func:`strategy_start` below: the same without pytest;
  :func:`lean_recipe`, the simulated recipe made quick for whole runs.

Nothing here is imported by calstation itself; only tests and emulators use it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from calstation.engine.frames import Extrinsics
from calstation.errors import PluginError
from calstation.recipes import SHIPPED_DIR, LoadedRecipe, load_recipe

SHIPPED_RECIPES = SHIPPED_DIR
"""The recipes shipped with calstation (the simulated station's among them;
:data:`calstation.recipes.SHIPPED_DIR`)."""


def lean_recipe(folder: Path) -> Path:
    """``recipes/sim-periodicity.yaml`` with fewer static lines and a quicker spin, written to
    ``folder/lean.yaml``: a whole simulated ``calstation run`` in a few seconds."""
    import yaml

    data = yaml.safe_load((SHIPPED_RECIPES / "sim-periodicity.yaml").read_text())
    data["name"] = "sim-periodicity-lean"
    data["steps"]["static_scan"]["lines"] = 60
    for scan in ("spin_scan", "cube_scan"):
        data["steps"][scan].update({"rpm": 30, "revolutions": 1.02, "settle_s": 0.2})
    path = folder / "lean.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@dataclass(frozen=True)
class SimulatedScans:
    """The recordings of one simulated run and what is known about them.

    ``static``, ``spin`` (the spin target), ``cube`` (the QA cube) are MCAP paths;
    ``truth`` the true H; ``recipe`` the recipe they were simulated with.
    """

    static: Path
    spin: Path
    cube: Path
    truth: Extrinsics
    recipe: LoadedRecipe

    def scan_of(self, fixture: str) -> Path:
        """The recording of ``fixture`` (a strategy's ``fixture``: spin_target or qa_cube)."""
        if fixture == "spin_target":
            return self.spin
        if fixture == "qa_cube":
            return self.cube
        raise PluginError(f"no simulated scan of fixture {fixture!r}; known: spin_target, qa_cube")


def simulate_scans(
    out_dir: Path,
    recipe: str | Path | LoadedRecipe = "sim-periodicity.yaml",
    *,
    seed: int = 1,
    range_m: float = 1.25,
    pitch_deg: float = 45.0,
) -> SimulatedScans:
    """Simulate a whole run (static, spin and cube scans) into ``out_dir``.

    ``recipe`` is a path, a recipe shipped with calstation by file name, or a loaded recipe.
    Needs a simulator (the calstation-sim plugin, ``pip install 'calstation[sim]'``);
    :class:`PluginError` says so when there is none.
    """
    from calstation import plugins

    simulator = plugins.simulator()
    if isinstance(recipe, LoadedRecipe):
        loaded = recipe
    else:
        path = Path(recipe)
        if not path.is_file() and (SHIPPED_RECIPES / path).is_file():
            path = SHIPPED_RECIPES / path
        loaded = load_recipe(path)
    files = simulator.simulate_run(
        loaded, Path(out_dir), seed=seed, range_m=range_m, pitch_deg=pitch_deg, progress=False
    )
    from calstation.recordings.reader import read_recording

    truth = read_recording(files["static"]).truth
    if truth is None:
        raise PluginError("the simulated recordings carry no ground truth")
    return SimulatedScans(Path(files["static"]), Path(files["spin"]), Path(files["cube"]),
                          truth, loaded)


def strategy_start(scans: SimulatedScans) -> Extrinsics:
    """The start a station gives a strategy: the initial calibration of the static scan."""
    from calstation.engine.initial import initial_calibration
    from calstation.recordings.reader import read_recording

    rc = scans.recipe.recipe
    return initial_calibration(
        read_recording(scans.static), rc.fixtures.static_target, rc.calibration.initial
    ).H


__all__ = ["SHIPPED_RECIPES", "SimulatedScans", "simulate_scans", "strategy_start"]
