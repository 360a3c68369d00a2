"""The calibration pipeline: one calibration from its recordings to a judged result.

    start (the L-target, or the platter's chord) → the strategy → the QA cube (ry combined
    from its side faces) → the lidar–encoder time offset → the judgement

:func:`calibrate` runs it whole (``calstation calibrate``, re-processing, the fleet,
``calstation plan``, the bench); the station's steps call its stages one at a time
(:mod:`calstation.pipeline.stages`, :mod:`calstation.pipeline.judgement`). Its inputs are
:class:`Scans` of :class:`Turned` spin scans, each with its returns prepared once
(:mod:`calstation.pipeline.scans`). The layer sits on the plugins (the strategies) and under
storage and the station: it reads no database and drives no hardware.
"""

from calstation.pipeline.calibrate import Calibrated, Scans, calibrate
from calstation.pipeline.scans import Turned, as_fitted, recording_disagreements, turned

__all__ = [
    "Calibrated",
    "Scans",
    "Turned",
    "as_fitted",
    "calibrate",
    "recording_disagreements",
    "turned",
]
