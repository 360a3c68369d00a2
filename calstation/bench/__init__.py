"""The paper-reproduction bench: the source paper's experiments on the simulated station.

``calstation bench paper`` simulates the nine paper scenarios (range 1.00/1.25/1.50 m × pitch
30/45/60°), runs the initial calibration and both fine-tuning strategies from the initial
calibration and from the paper's perturbed starts (sets A and B), and measures each result against
the simulator's true H (DESIGN §8). :mod:`.scenarios` builds the scenarios and starts,
:mod:`.runner` runs them in parallel, :mod:`.landscape` samples the cost functions,
:mod:`.report` and :mod:`.figures` turn the records into ``results.md`` and PNG figures.
"""

from __future__ import annotations

from calstation.errors import CalstationError


class BenchError(CalstationError):
    """The bench was configured wrongly or its data cannot be used."""


__all__ = ["BenchError"]
