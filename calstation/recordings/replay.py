"""The replay drivers, which play a recording back as if it were hardware (registered by
:mod:`calstation.plugins.builtin.replay`).

Driver name ``replay`` for the lidar, the turntable and the encoder. Settings (the same for all
three):

- ``path``: a recording (``.mcap``), or a folder of them such as ``calstation simulate`` writes.
  With a folder, the recording follows the fixture on the platter: ``static_target`` →
  ``static.mcap``, ``spin_target`` → ``spin.mcap``, ``qa_cube`` → ``cube.mcap`` (override with
  ``recordings: {fixture: file}``). A relative path is relative to the recipe's folder.
- ``realtime`` (default false): pace the replay in real time instead of as fast as possible.

The three drivers of one ``path`` share one replay session (``context.shared["replay"][path]``)
and one :class:`ReplayClock`, exposed as ``.clock``: it starts at the recording's first timestamp
and advances as lines are delivered (each to the time it is complete: one nominal line period
after its start, capped at the next line's start, never before its last point) and as the caller
sleeps on it. The lidar delivers the recorded lines in order with their own timestamps; the
encoder delivers the recorded readings up to the clock (so, up to the last line delivered); the
turntable reports the last recorded status at the clock (or, for recordings without any, a
status derived from the encoder). Turntable commands are accepted and have no effect on the data
(``stop`` on a turning platter returns at the next recorded standstill, moving the clock there).
When the lidar has delivered the last line, its ``lines()`` iterator ends and the clock moves to
the end of the recording, so the encoder hands out its remaining readings.
"""

from __future__ import annotations

import bisect
import contextlib
import math
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from calstation.drivers import (
    DriverContext,
    EncoderSample,
    LidarInfo,
    LidarLine,
    TurntableState,
    TurntableStatus,
)
from calstation.errors import CalstationError, DriverError
from calstation.recordings.reader import read_recording
from calstation.recordings.recorded import Recording

DRIVER_NAME = "replay"
DEFAULT_RECORDINGS: dict[str, str] = {
    "static_target": "static.mcap",
    "spin_target": "spin.mcap",
    "qa_cube": "cube.mcap",
}
SETTINGS = ("path", "realtime", "recordings")


@runtime_checkable
class ResolvesPaths(Protocol):
    """A recipe that resolves the paths it names against its folder (a
    :class:`~calstation.recipes.LoadedRecipe`, which this layer does not import)."""

    def resolve(self, relative: str) -> Path:
        """``relative`` against the recipe's folder."""
        ...


class ReplayClock:
    """The replay's time base (host-clock ns of the recording). Moves only when told to.

    ``sleep`` advances it; with ``realtime`` both ``sleep`` and :meth:`advance_to` also wait the
    same amount of wall time, so a replay runs at the recording's pace.
    """

    def __init__(self, start_ns: int, *, realtime: bool = False) -> None:
        self._now = int(start_ns)
        self.realtime = realtime
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        """The replay time (ns since the Unix epoch)."""
        with self._lock:
            return self._now

    def advance_to(self, t_ns: int) -> None:
        """Move forward to ``t_ns`` (never backwards), waiting in real time if ``realtime``."""
        with self._lock:
            step = int(t_ns) - self._now
            if step <= 0:
                return
            self._now = int(t_ns)
        if self.realtime:
            time.sleep(step * 1e-9)

    def sleep(self, seconds: float) -> None:
        """Advance by ``seconds`` (waiting as long in real time if ``realtime``)."""
        with self._lock:
            target = self._now + round(max(0.0, seconds) * 1e9)
        self.advance_to(target)

    def reset(self, t_ns: int) -> None:
        """Jump to ``t_ns`` (also backwards): a new recording starts."""
        with self._lock:
            self._now = int(t_ns)


class ReplaySession:
    """One recording (or folder of recordings) being replayed; shared by the three drivers."""

    def __init__(
        self, source: Path, *, realtime: bool = False, recordings: Mapping[str, str] | None = None
    ) -> None:
        self.source = source
        self.recordings = dict(DEFAULT_RECORDINGS if recordings is None else recordings)
        self.clock = ReplayClock(0, realtime=realtime)
        self.lock = threading.RLock()
        self.recording: Recording
        self.fixture: str | None = None
        if source.is_dir():
            first = next(
                (source / f for f in self.recordings.values() if (source / f).is_file()), None
            )
            if first is None:
                names = ", ".join(sorted(self.recordings.values()))
                raise DriverError(f"replay: folder {source} holds none of {names}")
            self._load(first)
        elif source.is_file():
            self._load(source)
        else:
            raise DriverError(f"replay: recording {source} does not exist")

    # --- the recording ---------------------------------------------------------------------
    def _load(self, path: Path) -> None:
        try:
            rec = read_recording(path)
        except CalstationError as exc:
            raise DriverError(f"replay: {exc}") from exc
        with self.lock:
            self.recording = rec
            self.path = path
            self.next_line = 0
            self.next_sample = 0
            self.exhausted = False
            self._bounds = rec.line_bounds()
            self._statuses = sorted(rec.turntable, key=lambda s: s.timestamp_ns)
            self._status_t = [s.timestamp_ns for s in self._statuses]
            t, c = rec.encoder_t_ns, rec.encoder_count
            self._repeated = np.zeros(len(t), dtype=bool)
            self._repeated[1:] = (t[1:] == t[:-1]) & (c[1:] == c[:-1])
            starts = [int(rec.line_timestamp_ns[0])]
            ends = [int(rec.t_ns.max()) if rec.n_points else int(rec.line_timestamp_ns[-1])]
            if len(rec.encoder_t_ns):
                starts.append(int(rec.encoder_t_ns[0]))
                ends.append(int(rec.encoder_t_ns[-1]))
            if self._status_t:
                starts.append(min(self._status_t))
                ends.append(max(self._status_t))
            self.start_ns, self.end_ns = min(starts), max(ends)
            self.clock.reset(self.start_ns)

    def place(self, fixture: str) -> None:
        """A fixture was placed: a folder replay switches to that fixture's recording."""
        if not self.source.is_dir() or fixture not in self.recordings:
            return
        path = self.source / self.recordings[fixture]
        if not path.is_file():
            raise DriverError(f"replay: no recording for fixture {fixture!r}: {path} is missing")
        self.fixture = fixture
        self._load(path)

    # --- lidar -----------------------------------------------------------------------------
    def next_line_or_none(self) -> LidarLine | None:
        """The next recorded line (the clock advances to when it is complete); None at the end."""
        with self.lock:
            rec = self.recording
            i = self.next_line
            if i >= rec.n_lines:
                if not self.exhausted:
                    self.exhausted = True
                    self.clock.advance_to(self.end_ns)
                return None
            a, b = int(self._bounds[i]), int(self._bounds[i + 1])
            ts = int(rec.line_timestamp_ns[i])
            explicit = rec.line_has_offsets is None or bool(rec.line_has_offsets[i])
            period = (
                0.0 if rec.line_point_period_ns is None else float(rec.line_point_period_ns[i])
            )
            line = LidarLine(
                timestamp_ns=ts,
                azimuth_rad=rec.azimuth_rad[a:b].copy(),
                range_m=rec.range_m[a:b].copy(),
                valid=rec.valid[a:b].copy(),
                point_period_ns=period,
                time_offset_ns=(rec.t_ns[a:b] - ts) if explicit else None,
                intensity=None if rec.intensity is None else rec.intensity[a:b].copy(),
            )
            self.next_line = i + 1
            end = self._line_end(i, ts, int(rec.t_ns[b - 1]) if b > a else ts)
        self.clock.advance_to(end)
        return line

    def _line_end(self, i: int, ts: int, last_point: int) -> int:
        """When line ``i`` is complete, as a device delivers it: one nominal line period after
        its start (but not past the next line's start), and never before its last point."""
        rec = self.recording
        rate = rec.lidar_info.line_rate_hz
        end = ts + round(1e9 / rate) if rate > 0 and math.isfinite(rate) else last_point
        if i + 1 < rec.n_lines:
            end = min(end, int(rec.line_timestamp_ns[i + 1]))
        return max(end, last_point)

    # --- encoder ---------------------------------------------------------------------------
    def samples_until_now(self) -> list[EncoderSample]:
        """Recorded readings not yet handed out, up to the clock.

        A reading that repeats the previous one exactly (same time and count: a recorded
        ``read()`` that added nothing to the stream) is left out; :meth:`reading_now` gives it.
        """
        with self.lock:
            rec = self.recording
            now = self.clock.now_ns()
            stop = int(np.searchsorted(rec.encoder_t_ns, now, side="right"))
            sl = slice(self.next_sample, stop)
            out = [
                EncoderSample(int(t), int(c))
                for t, c, dup in zip(
                    rec.encoder_t_ns[sl].tolist(),
                    rec.encoder_count[sl].tolist(),
                    self._repeated[sl].tolist(),
                    strict=True,
                )
                if not dup
            ]
            self.next_sample = max(self.next_sample, stop)
            return out

    def reading_now(self) -> EncoderSample:
        """A reading "now": the latest recorded reading at the clock; before the first one, the
        clock waits for it (and the stream will not repeat it)."""
        with self.lock:
            rec = self.recording
            if len(rec.encoder_t_ns) == 0:
                raise DriverError(f"replay: recording {self.path} has no encoder readings")
            i = int(np.searchsorted(rec.encoder_t_ns, self.clock.now_ns(), side="right")) - 1
            if i < 0:
                i = 0
                self.clock.advance_to(int(rec.encoder_t_ns[0]))
                self.next_sample = max(self.next_sample, 1)
            return EncoderSample(int(rec.encoder_t_ns[i]), int(rec.encoder_count[i]))

    # --- turntable -------------------------------------------------------------------------
    def wait_for_standstill(self) -> None:
        """If the recorded platter is turning at the clock, advance the clock to the next
        recorded status at standstill (speed 0), if there is one."""
        with self.lock:
            now = self.clock.now_ns()
            i = bisect.bisect_right(self._status_t, now)
            if i == 0 or self._statuses[i - 1].speed_rpm == 0.0:
                return
            for s in self._statuses[i:]:
                if s.speed_rpm == 0.0:
                    target = s.timestamp_ns
                    break
            else:
                return
        self.clock.advance_to(target)

    def status_now(self, state: TurntableState) -> TurntableStatus:
        """The last recorded status at the clock; else one derived from the encoder."""
        with self.lock:
            rec = self.recording
            now = self.clock.now_ns()
            if self._status_t:
                i = bisect.bisect_right(self._status_t, now) - 1
                s = self._statuses[max(i, 0)]
                return TurntableStatus(now, s.state, s.speed_rpm, s.position_rad, s.faults)
            speed, position = 0.0, None
            t, c = rec.encoder_t_ns, rec.encoder_count
            if len(t):
                j = int(np.searchsorted(t, now, side="right"))
                lo, hi = max(j - 10, 0), min(max(j, 1), len(t) - 1)
                if hi > lo and t[hi] > t[lo]:
                    revs = float(c[hi] - c[lo]) / rec.counts_per_revolution
                    speed = rec.encoder_direction * revs / (float(t[hi] - t[lo]) * 1e-9) * 60.0
                phi = rec.platter_angle(now)
                position = float(phi) if math.isfinite(float(phi)) else None
            if state is TurntableState.ENABLED and speed != 0.0:
                state = TurntableState.MOVING
            return TurntableStatus(now, state, speed, position)


# --- the drivers ---------------------------------------------------------------------------
class ReplayLidar:
    """Plays back the recorded lidar lines (satisfies :class:`calstation.drivers.Lidar`)."""

    def __init__(self, session: ReplaySession) -> None:
        self.session = session
        self.clock = session.clock
        self._running = False

    def info(self) -> LidarInfo:
        """The recorded device's identity and geometry."""
        return self.session.recording.lidar_info

    def start(self) -> None:
        """Start delivering lines (from where the previous ``lines()`` stopped)."""
        self._running = True

    def stop(self) -> None:
        """Stop delivering lines; a running :meth:`lines` iterator ends."""
        self._running = False

    def lines(self) -> Iterator[LidarLine]:
        """The recorded lines in order, each advancing the clock to when it is complete, until
        :meth:`stop` or the end of the recording."""
        if not self._running:
            raise DriverError("replay lidar: lines() called before start()")
        while self._running:
            line = self.session.next_line_or_none()
            if line is None:
                return
            yield line

    def close(self) -> None:
        """Stop. Idempotent."""
        self._running = False


class ReplayTurntable:
    """Reports the recorded turntable status (satisfies :class:`calstation.drivers.Turntable`).

    Commands are accepted (and checked for finite values) but cannot change the recorded data.
    """

    def __init__(self, session: ReplaySession) -> None:
        self.session = session
        self.clock = session.clock
        self._state = TurntableState.DISABLED
        self.commanded_rpm = 0.0

    def enable(self) -> None:
        """Mark the drive enabled."""
        self._state = TurntableState.ENABLED

    def disable(self) -> None:
        """Mark the drive disabled."""
        self._state = TurntableState.DISABLED
        self.commanded_rpm = 0.0

    def spin(self, rpm: float) -> None:
        """Record the commanded speed (the data is the recording's)."""
        if not math.isfinite(rpm):
            raise DriverError(f"replay turntable: speed must be finite, got {rpm}")
        self.commanded_rpm = float(rpm)

    def move_to(self, angle_rad: float) -> None:
        """Returns at once (a replay cannot move the platter)."""
        if not math.isfinite(angle_rad):
            raise DriverError(f"replay turntable: angle must be finite, got {angle_rad}")

    def stop(self) -> None:
        """Returns when stopped: the clock moves on to the next recorded standstill, if any."""
        self.commanded_rpm = 0.0
        self.session.wait_for_standstill()

    def emergency_stop(self) -> None:
        """Like :meth:`stop`. Never raises."""
        self.commanded_rpm = 0.0
        self._state = TurntableState.EMERGENCY_STOP
        with contextlib.suppress(Exception):  # an emergency stop must never raise
            self.session.wait_for_standstill()

    def status(self) -> TurntableStatus:
        """The recorded status at the replay clock (see the module docs)."""
        return self.session.status_now(self._state)

    def close(self) -> None:
        """Nothing to release. Idempotent."""
        self.commanded_rpm = 0.0


class ReplayEncoder:
    """Plays back the recorded encoder readings (satisfies :class:`calstation.drivers.Encoder`)."""

    def __init__(self, session: ReplaySession) -> None:
        self.session = session
        self.clock = session.clock

    @property
    def counts_per_revolution(self) -> int:
        """From the recording's ``encoder`` metadata."""
        return self.session.recording.counts_per_revolution

    def read(self) -> EncoderSample:
        """The latest recorded reading at the replay clock."""
        return self.session.reading_now()

    def samples(self) -> list[EncoderSample]:
        """Recorded readings since the previous call, up to the replay clock."""
        return self.session.samples_until_now()

    def close(self) -> None:
        """Nothing to release. Idempotent."""


# --- factories and hooks -------------------------------------------------------------------
def _session(settings: Mapping[str, object], context: DriverContext, kind: str) -> ReplaySession:
    unknown = sorted(set(settings) - set(SETTINGS))
    if unknown:
        raise DriverError(
            f"replay {kind}: unknown setting(s) {', '.join(unknown)}; known: {', '.join(SETTINGS)}"
        )
    raw = settings.get("path")
    if not isinstance(raw, (str, Path)) or not str(raw):
        raise DriverError(f"replay {kind}: setting 'path' (a recording or a folder) is required")
    realtime = settings.get("realtime", False)
    if not isinstance(realtime, bool):
        raise DriverError(
            f"replay {kind}: setting 'realtime' must be true or false, got {realtime!r}"
        )
    recordings = settings.get("recordings")
    if recordings is not None and (
        not isinstance(recordings, Mapping)
        or not all(isinstance(k, str) and isinstance(v, str) for k, v in recordings.items())
    ):
        raise DriverError(f"replay {kind}: setting 'recordings' must map fixture names to files")
    path = Path(raw)
    recipe = context.recipe
    if not path.is_absolute() and isinstance(recipe, ResolvesPaths):
        path = Path(recipe.resolve(str(path)))
    sessions: dict[str, ReplaySession] = context.shared.setdefault("replay", {})
    key = str(path.resolve())
    if key not in sessions:
        sessions[key] = ReplaySession(path, realtime=realtime, recordings=recordings)
    return sessions[key]


def replay_lidar(settings: Mapping[str, object], context: DriverContext) -> ReplayLidar:
    """Factory of the ``replay`` lidar."""
    return ReplayLidar(_session(settings, context, "lidar"))


def replay_turntable(settings: Mapping[str, object], context: DriverContext) -> ReplayTurntable:
    """Factory of the ``replay`` turntable."""
    return ReplayTurntable(_session(settings, context, "turntable"))


def replay_encoder(settings: Mapping[str, object], context: DriverContext) -> ReplayEncoder:
    """Factory of the ``replay`` encoder."""
    return ReplayEncoder(_session(settings, context, "encoder"))
