"""Acquisition loops end to end on the simulated station, and the foundation acceptance test:
the QA-cube spin scan reconstructed with the true H is a 100 mm cube within the noise."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from calstation.drivers import EncoderSample, LidarLine, TurntableStatus
from calstation.engine.frames import Extrinsics
from calstation.engine.reconstruct import reconstruct
from calstation.errors import DriverError
from calstation.recipes import load_recipe
from calstation.recordings.reader import read_recording
from calstation.recordings.writer import RecordingWriter
from calstation.station.acquisition import (
    LineGaps,
    acquire_spin,
    acquire_static,
    lost_lines_warning,
)

REPO = Path(__file__).resolve().parents[2]
RECIPE = REPO / "recipes" / "sim-periodicity.yaml"


# --- the cube check of the acceptance test ------------------------------------------------------
def cube_faces(
    points_D: NDArray[np.float64],
    pose: dict[str, Any],
    *,
    window: float = 0.005,
    trim: float = 0.005,
) -> dict[str, Any]:
    """Fit the cube's visible faces (top and four sides) and the platter plane around it.

    ``pose`` is the cube's true placement from truth.json (y, z, yaw_rad, geometry.edge). Points
    are taken in the cube's own frame; each face's plane is fitted by SVD to the points within
    ``window`` of the true face plane, at least ``trim`` inside the face's borders (mixed pixels
    sit at the borders), then refitted to the points within ``window`` of that first fit.
    Returns per-face RMS (m) and point counts, and the three face-fit edges (m): the distances
    between opposite side faces, and from the top face to the platter plane.
    """
    s = float(pose["geometry"]["edge"])
    c, sn = math.cos(pose["yaw_rad"]), math.sin(pose["yaw_rad"])
    q = points_D - np.array([0.0, pose["y"], pose["z"]])
    loc = np.column_stack([q[:, 0], c * q[:, 1] + sn * q[:, 2], -sn * q[:, 1] + c * q[:, 2]])
    extent = {0: (0.0, s), 1: (-s / 2, s / 2), 2: (-s / 2, s / 2)}
    faces = {
        "top": (0, s),
        "y-": (1, -s / 2),
        "y+": (1, s / 2),
        "z-": (2, -s / 2),
        "z+": (2, s / 2),
    }
    fits: dict[str, tuple[NDArray[np.float64], NDArray[np.float64], float, int]] = {}
    for name, (axis, value) in faces.items():
        inside = np.abs(loc[:, axis] - value) < window
        for other in {0, 1, 2} - {axis}:
            lo, hi = extent[other]
            inside &= (loc[:, other] > lo + trim) & (loc[:, other] < hi - trim)
        fits[name] = _plane(loc[inside], window)
    # the platter around the cube: the bottom face's plane
    r = np.hypot(loc[:, 1], loc[:, 2])
    ring = (np.abs(loc[:, 0]) < window) & (r > s * 0.8) & (r < s * 1.5)
    ring &= (np.abs(loc[:, 1]) > s / 2 + trim) | (np.abs(loc[:, 2]) > s / 2 + trim)
    fits["platter"] = _plane(loc[ring], window)

    def gap(a: str, b: str) -> float:
        (ca, na, _, _), (cb, nb, _, _) = fits[a], fits[b]
        return 0.5 * (abs(float(na @ (cb - ca))) + abs(float(nb @ (ca - cb))))

    return {
        "rms": {k: v[2] for k, v in fits.items()},
        "count": {k: v[3] for k, v in fits.items()},
        "edges": np.array([gap("top", "platter"), gap("y-", "y+"), gap("z-", "z+")]),
    }


def _plane(
    pts: NDArray[np.float64], window: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], float, int]:
    """(centroid, unit normal, RMS of residuals, count): SVD fit, refitted within ``window``."""
    if len(pts) < 3:
        return np.zeros(3), np.array([1.0, 0.0, 0.0]), math.inf, len(pts)
    for _ in range(2):
        centroid = pts.mean(axis=0)
        normal = np.linalg.svd(pts - centroid, full_matrices=False)[2][2]
        d = (pts - centroid) @ normal
        keep = np.abs(d) < window
        if keep.sum() < 3:
            break
        pts = pts[keep]
    centroid = pts.mean(axis=0)
    normal = np.linalg.svd(pts - centroid, full_matrices=False)[2][2]
    d = (pts - centroid) @ normal
    return centroid, normal, float(np.sqrt(np.mean(d * d))), len(pts)


def cube_check_passes(faces: dict[str, Any], edge: float, sigma: float) -> list[str]:
    """The acceptance criteria; returns the failures (empty when the cube passes)."""
    failures = []
    for name, n in faces["count"].items():
        if n < 500:
            failures.append(f"{name}: only {n} points")
    for name, rms in faces["rms"].items():
        if not rms <= 1.3 * sigma:
            failures.append(f"{name}: RMS {rms * 1e3:.3f} mm")
    for i, e in enumerate(faces["edges"]):
        if not abs(e - edge) <= 0.0003:
            failures.append(f"edge {i}: {e * 1e3:.3f} mm")
    return failures


@pytest.fixture(scope="module")
def cube_scan(sim_run: Callable[..., dict[str, Path]]) -> tuple[Any, dict[str, Any]]:
    paths = sim_run()
    truth = json.loads(paths["truth"].read_text())
    return read_recording(paths["cube"]), truth


def test_cube_reconstructed_with_true_H_is_a_100mm_cube(
    cube_scan: tuple[Any, dict[str, Any]],
) -> None:
    recording, truth = cube_scan
    assert recording.truth == Extrinsics.from_dict(truth)
    simulation = load_recipe(RECIPE).recipe.simulation
    assert simulation is not None
    sigma = simulation.lidar.range_noise
    assert sigma == 0.001  # the acceptance criterion is stated at σ = 1 mm
    faces = cube_faces(reconstruct(recording, recording.truth), truth["fixtures"]["qa_cube"])
    assert cube_check_passes(faces, 0.100, sigma) == [], faces


def test_cube_check_fails_with_rz_off_by_one_degree(cube_scan: tuple[Any, dict[str, Any]]) -> None:
    recording, truth = cube_scan
    H = recording.truth.with_(rz=recording.truth.rz + math.radians(1.0))
    faces = cube_faces(reconstruct(recording, H), truth["fixtures"]["qa_cube"])
    assert cube_check_passes(faces, 0.100, 0.001) != []


@pytest.mark.slow
@pytest.mark.parametrize(("range_m", "pitch_deg"), [(1.0, 30.0), (1.5, 60.0), (1.0, 60.0)])
def test_cube_with_true_H_in_other_scenarios(
    sim_run: Callable[..., dict[str, Path]], range_m: float, pitch_deg: float
) -> None:
    paths = sim_run(range_m=range_m, pitch_deg=pitch_deg, seed=2)
    truth = json.loads(paths["truth"].read_text())
    recording = read_recording(paths["cube"])
    assert recording.truth is not None
    faces = cube_faces(reconstruct(recording, recording.truth), truth["fixtures"]["qa_cube"])
    assert cube_check_passes(faces, 0.100, 0.001) == [], faces


# --- the loops themselves, on a small fast station ------------------------------------------------
SMALL = {"points_per_line": 100, "line_rate_hz": 1000}


def small_station(tmp_path: Path, **lidar: Any) -> Any:
    """A SimulatedStation of the default recipe with a 100-point lidar (fast)."""
    import yaml
    from calstation_sim import SimulatedStation

    from calstation.recipes import load_recipe

    data = yaml.safe_load(RECIPE.read_text())
    data["simulation"]["lidar"].update({**SMALL, **lidar})
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(data))
    return SimulatedStation(load_recipe(path), seed=3)


def _writer(path: Path, station: Any) -> RecordingWriter:
    return RecordingWriter(
        path,
        kind="test",
        lidar_info=station.lidar_info,
        counts_per_revolution=station.counts_per_revolution,
        encoder_direction=station.encoder_direction,
        metadata={"truth": station.truth_dict()},
    )


def test_acquire_static_records_lines_and_encoder(tmp_path: Path) -> None:
    from calstation_sim import SimEncoder, SimLidar

    station = small_station(tmp_path)
    station.place("static_target")
    lidar, encoder = SimLidar(station), SimEncoder(station)
    fractions: list[float] = []
    with _writer(tmp_path / "static.mcap", station) as writer:
        acquire_static(lidar, encoder, writer, lines=37, progress=lambda _p, f: fractions.append(f))
    rec = read_recording(tmp_path / "static.mcap")
    assert len(rec.line_timestamp_ns) == 37
    assert np.all(np.diff(rec.line_timestamp_ns) == 1_000_000)  # 1000 lines/s
    assert fractions[-1] == 1.0 and len(fractions) == 37
    # the encoder covers every point's time, and the platter is at rest
    assert rec.encoder_t_ns[0] <= rec.t_ns.min() and rec.encoder_t_ns[-1] >= rec.t_ns.max()
    assert np.all(rec.encoder_count == 0)
    # the simulated clock moved exactly to the end of the last line
    assert station.clock.now_ns() == rec.line_timestamp_ns[-1] + 1_000_000


def test_acquire_spin_covers_the_turns_and_stops(tmp_path: Path) -> None:
    from calstation_sim import SimEncoder, SimLidar, SimTurntable

    station = small_station(tmp_path)
    station.place("qa_cube")
    lidar, tt, encoder = SimLidar(station), SimTurntable(station), SimEncoder(station)
    phases: set[str] = set()
    with _writer(tmp_path / "spin.mcap", station) as writer:
        acquire_spin(
            lidar,
            tt,
            encoder,
            writer,
            rpm=60.0,
            revolutions=1.05,
            settle_s=0.2,
            clock=station.clock,
            progress=lambda p, _f: phases.add(p),
        )
    assert phases == {"waiting for speed", "scanning"}
    status = tt.status()
    assert status.speed_rpm == 0.0 and status.state == "enabled"
    rec = read_recording(tmp_path / "spin.mcap")
    phi = rec.platter_angle(rec.line_timestamp_ns)
    end = rec.platter_angle(rec.line_timestamp_ns[-1] + 1_000_000)  # end of the last line
    turns = (end - phi[0]) / (2 * math.pi)
    assert 1.05 <= turns < 1.05 + 0.01  # stops at the first line past the requested turns
    # all lines taken at speed (after the ramp and the settle time)
    t = rec.line_timestamp_ns[::50] * 1e-9  # 50 ms steps: the encoder's quantisation averages out
    speed = np.diff(phi[::50]) / np.diff(t) * 60 / (2 * math.pi)
    assert np.all(np.abs(speed - 60.0) < 60.0 * 0.03)
    assert rec.turntable[-1].speed_rpm == 0.0 and len(rec.turntable) > 5


class _LateLidar:
    """The simulated lidar's lines, each handed over ``lag`` line periods after the previous
    one was (a loaded host working through the lidar's buffer): its stamps fall ever further
    behind the station's clock, and none is lost."""

    def __init__(self, station: Any, lag: int) -> None:
        self.station, self.lag, self.running = station, lag, False

    def start(self) -> None:
        self.running, self.t0 = True, self.station.clock.now_ns()

    def stop(self) -> None:
        self.running = False

    def lines(self) -> Iterable[LidarLine]:
        period = self.station.line_period_ns
        k = 0
        while self.running:
            times = self.t0 + np.round(np.arange(k, k + 100) * period).astype(np.int64)
            for line in self.station.scan_lines(times):
                now = self.station.clock.now_ns()
                self.station.clock.advance_to(now + round(self.lag * period))
                yield line
            k += 100


class _StuckEncoder:
    """The simulated encoder, its count stuck where it was first read (a cable pulled)."""

    def __init__(self, encoder: Any) -> None:
        self.encoder, self.count = encoder, None
        self.counts_per_revolution = encoder.counts_per_revolution

    def _stuck(self, sample: EncoderSample) -> EncoderSample:
        self.count = sample.count if self.count is None else self.count
        return EncoderSample(timestamp_ns=sample.timestamp_ns, count=self.count)

    def read(self) -> EncoderSample:
        return self._stuck(self.encoder.read())

    def samples(self) -> list[EncoderSample]:
        return [self._stuck(x) for x in self.encoder.samples()]


def test_a_spin_scan_whose_lines_come_late_still_covers_its_turns(tmp_path: Path) -> None:
    """Lines handed over eight times slower than scanned take the scan eight times as long on
    the clock, beyond the stalled-encoder limit's time: the turns count in the lines' own time,
    so the scan ends with its turns rather than fail the encoder."""
    from calstation_sim import SimEncoder, SimTurntable

    station = small_station(tmp_path)
    station.place("qa_cube")
    tt, encoder = SimTurntable(station), SimEncoder(station)
    with _writer(tmp_path / "spin.mcap", station) as writer:
        acquire_spin(_LateLidar(station, lag=8), tt, encoder, writer, rpm=60.0,
                     revolutions=1.05, settle_s=0.0, clock=station.clock)
    rec = read_recording(tmp_path / "spin.mcap")
    assert np.all(np.diff(rec.line_timestamp_ns) == 1_000_000)  # every line, none skipped
    turns = np.ptp(rec.platter_angle(rec.line_timestamp_ns)) / (2 * math.pi)
    assert 1.04 <= turns < 1.06
    assert station.clock.now_ns() - rec.line_timestamp_ns[0] > 8e9  # past the 7.1 s limit


def test_a_spin_scan_with_a_stuck_encoder_stops_and_names_it(tmp_path: Path) -> None:
    from calstation_sim import SimEncoder, SimLidar, SimTurntable

    station = small_station(tmp_path)
    lidar, tt = SimLidar(station), SimTurntable(station)
    with pytest.raises(DriverError, match=r"covered only 0\.000 of 1 turns in 7\.\d s of lines"):
        acquire_spin(lidar, tt, _StuckEncoder(SimEncoder(station)), _FailingWriter(lines=None),
                     rpm=60.0, revolutions=1.0, settle_s=0.0, clock=station.clock)
    assert station.motion.commanded_speed() == 0.0


class _FailingWriter:
    """Accepts encoder and turntable data, fails on the 10th lidar line (a full disk, say), or
    never with ``lines=None``."""

    def __init__(self, lines: int | None = 10) -> None:
        self.lines, self.fails_at = 0, lines

    def write_line(self, line: LidarLine) -> None:
        self.lines += 1
        if self.lines == self.fails_at:
            raise OSError("disk full")

    def write_encoder(self, samples: Iterable[EncoderSample]) -> None:
        list(samples)

    def write_turntable(self, status: TurntableStatus) -> None:
        pass


def test_acquire_spin_stops_the_turntable_when_recording_fails(tmp_path: Path) -> None:
    from calstation_sim import SimEncoder, SimLidar, SimTurntable

    station = small_station(tmp_path)
    lidar, tt, encoder = SimLidar(station), SimTurntable(station), SimEncoder(station)
    with pytest.raises(OSError, match="disk full"):
        acquire_spin(
            lidar,
            tt,
            encoder,
            _FailingWriter(),
            rpm=30.0,
            revolutions=1.0,
            settle_s=0.0,
            clock=station.clock,
        )
    assert tt.status().speed_rpm == 0.0
    assert station.motion.commanded_speed() == 0.0


def test_acquire_rejects_bad_requests(tmp_path: Path) -> None:
    from calstation_sim import SimEncoder, SimLidar, SimTurntable

    station = small_station(tmp_path)
    lidar, tt, encoder = SimLidar(station), SimTurntable(station), SimEncoder(station)
    writer = _FailingWriter()
    with pytest.raises(DriverError, match="at least one line"):
        acquire_static(lidar, encoder, writer, lines=0)
    with pytest.raises(DriverError, match="non-zero"):
        acquire_spin(
            lidar, tt, encoder, writer, rpm=0.0, revolutions=1, settle_s=0, clock=station.clock
        )


def test_lost_lines_are_counted_from_the_gaps_and_jitter_is_not() -> None:
    """2000 lines 10 ms apart whose stamps jitter by up to ±2 ms (a sensor clock's steps)
    lost none; the same with 30 lines gone after the 500th lost 30, which the operator is
    told (beyond 1 % of the scan's lines), and a single line gone is not worth a warning."""
    rng = np.random.default_rng(0)
    stamps = np.arange(2000) * 10_000_000 + rng.integers(-2_000_000, 2_000_001, 2000)

    def gaps(kept: NDArray[np.int64]) -> LineGaps:
        g = LineGaps()
        for t in kept:
            g.add(int(t))
        return g

    whole = gaps(stamps)
    assert whole.lost()[:2] == (2000, 0) and lost_lines_warning("spin", *whole.lost()) is None
    holed = gaps(np.r_[stamps[:500], stamps[530:]])
    delivered, lost, longest = holed.lost()
    assert (delivered, lost) == (1970, 30) and longest == pytest.approx(0.31, abs=0.005)
    said = lost_lines_warning("spin", delivered, lost, longest)
    assert said is not None and said.startswith("the spin scan lost 30 of its 2000 lidar lines")
    assert lost_lines_warning("spin", *gaps(np.r_[stamps[:500], stamps[501:]]).lost()) is None
