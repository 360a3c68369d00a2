"""The paper-reproduction bench: the source paper's experiments on the simulated station.

``calstation bench paper`` simulates the nine paper scenarios (range 1.00/1.25/1.50 m × pitch
30/45/60°), runs the initial calibration and both fine-tuning strategies from the initial
calibration and from the paper's perturbed starts (sets A and B), and measures each result against
the simulator's true H (DESIGN §8).

The modules, from the bottom up: :mod:`.scenarios` builds the scenarios and starts,
:mod:`.tasks` the configuration and the units of work, :mod:`.records` what a finished task
records; :mod:`.landscape` samples the cost functions, :mod:`.worker` runs one task in a worker
process and :mod:`.execute` runs tasks in a pool of them; :mod:`.runner` runs the paper bench's
phases, :mod:`.basin`, :mod:`.speed` and :mod:`.targetless` the other benches; :mod:`.tables`,
:mod:`.report` and :mod:`.figures` turn the records into ``results.md`` and PNG figures.
"""

from __future__ import annotations

from calstation.errors import CalstationError


class BenchError(CalstationError):
    """The bench was configured wrongly or its data cannot be used."""


__all__ = ["BenchError"]
