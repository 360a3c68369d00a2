"""What one calibration is made from: its recordings, each spin scan with its returns prepared
once for every stage that reads them, and what a recording says that the recipe does not.

A spin scan (the spin target's or the QA cube's) is a :class:`Turned`: the recording as the
calibration uses it — cut to the lines a fit made while scanning saw (:func:`as_fitted`), so
that whoever computes the result again (a resumed run, a re-processing) gets the station's to
the last digit — and its returns prepared (:class:`~calstation.engine.spinscan.SpinScan`). The
station hands over the preparation it made while the lines arrived
(:class:`~calstation.engine.spinscan.SpinScanBuilder`); everyone else has it made here, once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from calstation.recipes import LoadedRecipe

if TYPE_CHECKING:
    from calstation.engine.spinscan import SpinScan, SpinScanBuilder
    from calstation.recordings.recorded import Recording


@dataclass(frozen=True)
class Turned:
    """A scan taken while the platter turned, as a calibration uses it.

    - ``recording``: the recording as used (cut to what a fit made while scanning saw, else
      whole); None for a scan still being taken, of which only ``prepared`` (its lines so far)
      exists: only a strategy with ``run_prepared`` fine-tunes that.
    - ``prepared``: ``recording``'s returns prepared, made once for every stage.
    - ``whole``: the whole recording when ``recording`` is a cut of it (the time offset compares
      whole passes), and ``whole_prepared`` its returns when they are prepared already.
    """

    recording: Recording | None
    prepared: SpinScan
    whole: Recording | None = None
    whole_prepared: SpinScan | None = None

    def complete(self) -> tuple[Recording | None, SpinScan | None]:
        """The whole recording and its prepared returns (None when not prepared yet)."""
        if self.whole is not None:
            return self.whole, self.whole_prepared
        return self.recording, self.prepared

    def turns(self) -> float:
        """The whole turns of the recording as used (of the lines so far when it has none)."""
        if self.recording is not None:
            return float(self.recording.whole_turns())
        return 0.0


def turned(
    recording: Recording,
    *,
    fitted: tuple[int, int | None] | None = None,
    builder: SpinScanBuilder | None = None,
) -> Turned:
    """``recording`` as a calibration uses it: cut to ``fitted`` (:func:`as_fitted`), with its
    returns prepared — from ``builder``, the preparation made while the scan was taken, when it
    is the one of this recording (same lines, same encoder latency), else from the file."""
    from calstation.engine.spinscan import from_recording

    used = as_fitted(recording, fitted)
    cut = used is not recording
    if builder is not None and _prepared_from(builder, recording):
        whole = builder.finish()
        return Turned(used, builder.first_lines(used.n_lines) if cut else whole,
                      recording if cut else None, whole if cut else None)
    prepared = from_recording(used)
    return Turned(used, prepared, recording if cut else None, None)


def _prepared_from(builder: SpinScanBuilder, recording: Recording) -> bool:
    """Whether ``builder`` prepared ``recording``'s lines, as it reads them."""
    return (builder.lines == recording.n_lines
            and builder.encoder_latency_s == recording.encoder_latency_s
            and builder.counts_per_revolution == recording.counts_per_revolution
            and builder.encoder_direction == recording.encoder_direction)


def so_far(prepared: SpinScan) -> Turned:
    """The lines of a scan still being taken, prepared as they arrived."""
    return Turned(None, prepared)


def as_fitted(recording: Recording, fitted: tuple[int, int | None] | None) -> Recording:
    """``recording`` cut to what a fit made while scanning saw (``fitted``: its whole turns and
    the recording's first lines it saw, the lines None when not known; all of it when None): its
    first lines — else its first turns — whoever computes the result again (a resumed run, a
    re-processing), so that it is the station's to the last digit."""
    if fitted is None:
        return recording
    turns, lines = fitted
    if lines is not None:
        return recording.first_lines(lines)
    if turns >= recording.whole_turns():
        return recording
    return recording.first_turns(turns + 0.02)


def recording_disagreements(recording: Recording, loaded: LoadedRecipe) -> list[str]:
    """Where ``recording``'s metadata and the recipe differ: encoder direction, counts per
    revolution (4·ppr) and the recipe's sha256. One message per difference, naming both values
    and which one is used (the recording's: it describes the data as it was taken)."""
    rc = loaded.recipe
    name = recording.path.name
    out: list[str] = []
    enc = rc.station.encoder
    if recording.encoder_direction != enc.direction:
        out.append(
            f"{name}: encoder direction {recording.encoder_direction:+d} in the recording, "
            f"{enc.direction:+d} in the recipe (station.encoder.direction); the recording's "
            "value is used"
        )
    if recording.counts_per_revolution != 4 * enc.ppr:
        out.append(
            f"{name}: {recording.counts_per_revolution} encoder counts per revolution in the "
            f"recording, {4 * enc.ppr} in the recipe (4 × station.encoder.ppr {enc.ppr}); the "
            "recording's value is used"
        )
    recorded = str(recording.metadata.get("calstation", {}).get("recipe_sha256") or "")
    if recorded and recorded != loaded.sha256:
        out.append(
            f"{name}: taken with recipe sha256 {recorded[:12]}…, calibrated with recipe sha256 "
            f"{loaded.sha256[:12]}… (the recipe text differs from the one of the scan)"
        )
    return out
