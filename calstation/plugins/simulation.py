"""The simulator interface: a whole station simulated from a recipe's ``simulation`` section.

calstation imports no simulator: the kit (:mod:`calstation.testing`), the paper bench and
``calstation plan`` reach one through the plugin manager (:func:`calstation.plugins.simulator`),
registered by the ``calstation_register_simulators`` hook. calstation's own, ray-cast one is the
``calstation-sim`` plugin, the ``sim`` extra: ``pip install 'calstation[sim]'``.
"""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    from calstation.engine.frames import Extrinsics
    from calstation.recipes import LoadedRecipe

DEFAULT_SIMULATOR = "sim"
"""The simulator calstation's kit, bench and plan use: the ``calstation-sim`` plugin's."""


@runtime_checkable
class Simulator(Protocol):
    """A simulated station.

    - ``name``: how :func:`calstation.plugins.simulator` finds it;
    - ``simulate_run``: a whole run of ``loaded`` written into ``out`` — ``static.mcap`` (not for
      a recipe that starts from the platter), ``spin.mcap``, ``cube.mcap``, each second pass a
      step asks for (``spin-pass2.mcap``, ``cube-pass2.mcap``) and ``truth.json`` — returned by
      name (``static``, ``spin``, ``cube``, ``truth``, …). ``seed``, ``range_m`` (m) and
      ``pitch_deg`` override the recipe's simulation; ``only`` names the scans to simulate.
    - ``truth``: the true H of the station ``loaded`` describes with that seed and geometry,
      nothing simulated.
    """

    name: str

    def simulate_run(
        self,
        loaded: LoadedRecipe,
        out: Path,
        *,
        seed: int | None = None,
        range_m: float | None = None,
        pitch_deg: float | None = None,
        progress: bool = True,
        only: Collection[str] | None = None,
    ) -> dict[str, Path]:
        """Simulate a whole run into ``out``; the files by name."""
        ...

    def truth(
        self,
        loaded: LoadedRecipe,
        *,
        seed: int | None = None,
        range_m: float | None = None,
        pitch_deg: float | None = None,
    ) -> Extrinsics:
        """The simulated station's true H (m, rad)."""
        ...
