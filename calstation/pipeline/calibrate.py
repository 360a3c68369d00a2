"""One calibration from its recordings, start to judgement: :func:`calibrate`.

    start (the L-target, or the platter's chord) → the strategy → the QA cube (ry combined
    from its side faces) → the lidar–encoder time offset → the judgement

This is the one assembly of the stages (:mod:`calstation.pipeline.stages`): ``calstation
calibrate``, a re-processing (``calibrate --run``, ``reprocess``, the fleet's campaigns),
``calstation plan`` and the bench call it whole; the station calls its stages one step at a
time.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from calstation.pipeline.judgement import judge
from calstation.pipeline.scans import Turned
from calstation.pipeline.stages import (
    Progress,
    certified,
    fine_tune,
    part,
    start,
    time_offset,
    with_cube,
)
from calstation.recipes import Recipe

if TYPE_CHECKING:
    from calstation.engine.cube import CubeCheck
    from calstation.engine.result import CalibrationResult
    from calstation.plugins.cost_strategies import Strategy
    from calstation.recordings.recorded import Recording


@dataclass(frozen=True)
class Scans:
    """The recordings of one calibration.

    - ``spin``: the scan the strategy fine-tunes (the spin target's, or the QA cube's for a
      strategy that fits the cube);
    - ``static``: the L-target's static scan; None starts from the platter's chord in ``spin``;
    - ``spin_pass2``: the spin scan's second pass (another speed or the other way): the
      lidar–encoder time offset is estimated from the two;
    - ``cube``: the QA cube's scan: checked under the result, and for a spin-target strategy its
      side faces combined into ry.
    """

    spin: Turned
    static: Recording | None = None
    spin_pass2: Recording | None = None
    cube: Turned | None = None


@dataclass(frozen=True)
class Calibrated:
    """What :func:`calibrate` made.

    - ``start``: where the fine-tuning started (the initial calibration, or the platter's
      chord with the tz it kept);
    - ``fine_tuned``: the strategy's result, before the cube and the time offset;
    - ``result``: the calibration, judged (its predicted error in
      ``diagnostics["predicted_error"]``);
    - ``refused``: every reason it is refused (empty: it is accepted);
    - ``warnings``: the strategy's (:func:`~calstation.plugins.cost_strategies.check_result`);
    - ``cube_check``: the cube under ``result``'s H (None without a cube scan), and
      ``ry_failure`` why the cube could not determine ry (also in ``refused``).
    """

    start: CalibrationResult
    fine_tuned: CalibrationResult
    result: CalibrationResult
    refused: list[str]
    warnings: list[str] = field(default_factory=list)
    cube_check: CubeCheck | None = None
    ry_failure: str | None = None


def calibrate(
    recipe: Recipe, scans: Scans, strategy: Strategy, progress: Progress | None = None
) -> Calibrated:
    """Calibrate from ``scans`` with ``strategy`` and ``recipe``'s settings, as the station
    does (see the module docstring), and judge the result as a run judges it: the
    ``calibration.max_sigma`` limits, ry with the cube, the accuracy budget over the turns of
    the strategy's scan. ``progress(message, fraction)`` is told each stage."""
    say = progress or (lambda message, fraction: None)
    say("start from the L-target" if scans.static is not None
        else "start from the platter's chord", 0.0)
    begun = start(recipe, scans.static, scans.spin)
    fine = fine_tune(recipe, strategy, begun, scans.spin, part(progress, 0.05, 0.85))
    result, check, ry_failure = fine.result, None, None
    if scans.cube is not None:
        say("combining ry with the cube's side faces" if strategy.fixture == "spin_target"
            else "checking the QA cube", 0.85)
        cubed = with_cube(recipe, strategy, result, scans.cube, part(progress, 0.85, 0.95),
                          spin=scans.spin)
        result, check, ry_failure = cubed.result, cubed.check, cubed.ry_failure
    elif strategy.fixture != "spin_target":  # the cube is its own scan: no check, a certificate
        result, ry_failure = certified(recipe, result)
    if scans.spin_pass2 is not None:  # under the final H (it moves a little with ry)
        say("lidar–encoder time offset", 0.95)
        result = time_offset(recipe, result, scans.spin, scans.spin_pass2)
    judged, refused = judge(result, recipe, ry_failure=ry_failure, turns=scans.spin.turns())
    say("calibrated", 1.0)
    return Calibrated(fine.start or begun.result, fine.result, judged, refused, fine.warnings,
                      check, ry_failure)
