"""The simulated station: truth, turntable motion, encoder, lidar model, determinism."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from calstation_sim import SimulatedStation, simulate_run
from calstation_sim.motion import PlatterMotion

from calstation.engine.frames import counts_to_angle, lidar_to_dynamic, polar_to_lidar
from calstation.errors import SimulationError
from calstation.recipes import LoadedRecipe
from calstation.recordings.reader import read_recording

FAST = {
    "simulation.lidar.points_per_line": 200,
    "simulation.lidar.line_rate_hz": 500,
    "steps.static_scan.lines": 20,
    "steps.spin_scan.rpm": 60,
    "steps.cube_scan.rpm": 60,
    "steps.spin_scan.settle_s": 0.1,
    "steps.cube_scan.settle_s": 0.1,
}


def test_truth_is_nominal_plus_bounded_seeded_deviations(
    make_recipe: Callable[..., LoadedRecipe],
) -> None:
    recipe = make_recipe()
    tc = recipe.recipe.simulation.truth  # type: ignore[union-attr]
    seen = set()
    for seed in range(20):
        H = SimulatedStation(recipe, seed=seed, range_m=1.5, pitch_deg=30).truth
        assert H.ty == 1.5 and H.rx == 0.0
        assert abs(H.tx) <= tc.tx_max and abs(H.tz) <= tc.tz_max
        assert abs(H.ry) <= math.radians(tc.ry_max_deg)
        assert abs(H.rz - math.radians(-30)) <= math.radians(tc.rz_max_deg)
        seen.add(H.tx)
    assert len(seen) == 20
    assert SimulatedStation(recipe, seed=4).truth == SimulatedStation(recipe, seed=4).truth
    explicit = {"tx": 0.01, "ty": 1.0, "tz": -0.002, "rx": 0.0, "ry": 0.001, "rz": -0.7}
    H = SimulatedStation(make_recipe({"simulation.truth.H": explicit})).truth
    assert H.as_dict() == explicit
    with pytest.raises(SimulationError, match="pitch"):
        SimulatedStation(recipe, pitch_deg=90)


def test_turntable_ramp_is_exact() -> None:
    acc = 2 * math.pi  # rad/s²
    m = PlatterMotion(acc)
    end = m.command(1.0, 4 * math.pi)  # 0 → 2 rev/s
    assert end == pytest.approx(3.0)
    t = np.array([0.5, 1.0, 2.0, 3.0, 4.0])
    assert np.allclose(m.speed(t), [0, 0, acc, 4 * math.pi, 4 * math.pi])
    ramp_angle = 0.5 * acc * 2.0**2
    assert np.allclose(m.angle(t), [0, 0, 0.5 * acc, ramp_angle, ramp_angle + 4 * math.pi])
    stop = m.command(4.0, 0.0)  # ramps down over 2 s
    assert stop == pytest.approx(6.0)
    total = ramp_angle + 4 * math.pi + 0.5 * 4 * math.pi * 2.0
    assert m.angle(np.array([6.0, 100.0])) == pytest.approx([total, total])
    assert m.speed(np.array([5.0, 7.0])) == pytest.approx([2 * math.pi, 0.0])


def test_speed_ripple_cycles_per_revolution_and_integrates_exactly() -> None:
    m = PlatterMotion(1.0, ripple=0.01, cycles=3)
    m.command(0.0, 2 * math.pi, acceleration=1e9)  # 1 rev/s at once
    t = np.linspace(1e-6, 1.0 + 1e-6, 200_001)  # past the (near-instant) ramp
    w = m.speed(t)
    assert w.max() == pytest.approx(2 * math.pi * 1.01, rel=1e-6)
    assert w.min() == pytest.approx(2 * math.pi * 0.99, rel=1e-6)
    # three maxima in one revolution
    peaks = np.sum((w[1:-1] > w[:-2]) & (w[1:-1] >= w[2:]))
    assert peaks == 3
    # angle = integral of speed (trapezoid rule on a fine grid)
    integral = m.angle(t[:1]) + np.concatenate(
        [[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))]
    )
    assert np.max(np.abs(m.angle(t) - integral)) < 1e-8


@pytest.mark.parametrize("direction", [1, -1])
def test_encoder_quantisation_and_direction(
    make_recipe: Callable[..., LoadedRecipe], direction: int
) -> None:
    st = SimulatedStation(make_recipe({"station.encoder.direction": direction}))
    t0 = st.clock.now_ns()
    st.set_speed(20.0, t0)
    t = t0 + np.arange(0, 4_000_000_000, 1_234_567, dtype=np.int64)
    counts = st.encoder_counts(t)
    phi = st.platter_angles(t)
    cpr = st.counts_per_revolution
    assert cpr == 4 * 1024
    assert np.array_equal(counts, np.floor(direction * phi * cpr / (2 * math.pi) + 1e-9))
    back = counts_to_angle(counts, cpr, direction)  # DESIGN §2: φ = dir·2π·count/cpr
    err = direction * (phi - back)  # what floor leaves: [0, one count)
    assert np.all(err >= -1e-9) and np.all(err < 2 * math.pi / cpr + 1e-9)
    assert np.sign(counts[-1]) == direction  # positive rpm turns +φ
    assert st.encoder_count(int(t[-1])) == counts[-1]


def test_encoder_latency_shifts_timestamps(make_recipe: Callable[..., LoadedRecipe]) -> None:
    st = SimulatedStation(make_recipe({"simulation.encoder.latency_s": 0.002}))
    st.set_speed(30.0, st.clock.now_ns())
    t = st.clock.now_ns() + 2_000_000_000
    # the sample stamped t was taken 2 ms earlier
    expect = math.floor(st.platter_angle(t - 2_000_000) * st.counts_per_revolution / (2 * math.pi))
    assert st.encoder_count(t) == expect


def _valid_fraction(station: SimulatedStation, lines: int = 50) -> tuple[float, int]:
    t = station.clock.now_ns() + np.arange(lines, dtype=np.int64) * 1_000_000
    got = station.scan_lines(t)
    assert all(len(line) == station.lidar_info.points_per_line for line in got)  # nothing dropped
    valid = np.concatenate([line.valid for line in got])
    return float(valid.mean()), valid.size


def test_dropouts_and_range_limits_are_marked_invalid(
    make_recipe: Callable[..., LoadedRecipe],
) -> None:
    base, _ = _valid_fraction(SimulatedStation(make_recipe({}, ideal=True)))
    assert base > 0.99  # floor, wall, platter: almost every ray returns
    lossy = SimulatedStation(make_recipe({"simulation.lidar.dropout": 0.2}, ideal=True))
    frac, n = _valid_fraction(lossy)
    assert frac == pytest.approx(0.8 * base, abs=4 * math.sqrt(0.16 / n))
    near = SimulatedStation(make_recipe({"simulation.lidar.range_max": 1.3}, ideal=True))
    line = near.scan_line(near.clock.now_ns())
    assert np.all(line.range_m[line.valid] <= 1.3)
    assert np.any(~line.valid & (line.range_m > 1.3))  # the far floor: measured, marked invalid


def test_ranges_lie_on_the_scene_and_noise_has_sigma(
    make_recipe: Callable[..., LoadedRecipe],
) -> None:
    """Every ideal return lies on a surface of the scene; with σ = 2 mm the residuals have σ."""
    st = SimulatedStation(make_recipe({}, ideal=True))
    st.place("qa_cube")
    st.set_speed(20.0, st.clock.now_ns())
    t = st.clock.now_ns() + 1_000_000_000 + np.arange(20, dtype=np.int64) * 50_000_000
    lines = st.scan_lines(t)
    dist = _distance_to_cube_and_platter(st, lines)
    # Open3D's float32 distance query on the platter's thin fan triangles is good to ~50 µm
    assert np.max(dist) < 1e-4
    noisy = SimulatedStation(make_recipe({"simulation.lidar.range_noise": 0.002}, ideal=True))
    ideal = SimulatedStation(make_recipe({}, ideal=True))
    t = noisy.clock.now_ns() + np.arange(20, dtype=np.int64) * 1_000_000
    diff = np.concatenate(
        [
            a.range_m - b.range_m
            for a, b in zip(noisy.scan_lines(t), ideal.scan_lines(t), strict=True)
        ]
    )
    assert np.std(diff) == pytest.approx(0.002, rel=0.05)


def _distance_to_cube_and_platter(st: SimulatedStation, lines: list) -> np.ndarray:  # type: ignore[type-arg]
    """Distance (m) of every valid point on the platter or cube (not the background) to them."""
    scene = o3d.t.geometry.RaycastingScene()
    for mesh in (st.fixture_mesh_in_D(), st._platter):
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    pts = []
    for line in lines:
        phi = st.platter_angles(line.point_times_ns())[line.valid]
        p_L = polar_to_lidar(line.range_m, line.azimuth_rad)[line.valid]
        pts.append(lidar_to_dynamic(p_L, phi, st.truth))
    p = np.vstack(pts)
    near = (p[:, 0] > -0.05) & (np.hypot(p[:, 1], p[:, 2]) < 0.35)
    p = p[near]  # drop the floor and the back wall
    return np.asarray(scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy())


def test_mixed_pixels_appear_only_at_depth_edges(make_recipe: Callable[..., LoadedRecipe]) -> None:
    st = SimulatedStation(make_recipe({"simulation.lidar.mixed_pixel_prob": 1.0}, ideal=True))
    st.place("qa_cube")
    st.set_speed(20.0, st.clock.now_ns())
    t = st.clock.now_ns() + 1_000_000_000 + np.arange(50, dtype=np.int64) * 20_000_000
    lines = st.scan_lines(t)
    dist = _distance_to_cube_and_platter(st, lines)
    off = dist > 1e-3
    assert 0 < off.sum() < 0.01 * len(dist)  # a few ghost points, between surfaces
    # ... and they sit next to a range jump in their line
    jumps = 0
    for line in lines:
        r = line.range_m
        jumps += int(np.sum(np.abs(np.diff(r)) > 0.03))
    assert jumps > 0


def test_placement_error_is_seeded_and_bounded(make_recipe: Callable[..., LoadedRecipe]) -> None:
    recipe = make_recipe()
    a, b = SimulatedStation(recipe, seed=9), SimulatedStation(recipe, seed=9)
    for st in (a, b):
        st.place("qa_cube")
    assert a.placements == b.placements
    p = a.placements["qa_cube"]
    g = recipe.recipe.fixtures.qa_cube
    assert p["y"] - g.offset[0] == pytest.approx(p["error_y"])
    assert abs(p["error_y"]) < 5 * 0.002 and abs(p["error_yaw_rad"]) < math.radians(2.5)
    assert p["yaw_rad"] == pytest.approx(math.radians(g.yaw_deg) + p["error_yaw_rad"])
    with pytest.raises(SimulationError, match="unknown fixture"):
        a.place("teapot")
    with pytest.raises(SimulationError, match="demo"):
        a.place("demo:3")


def test_fixture_placed_on_a_turned_platter_keeps_its_pose_in_P(
    make_recipe: Callable[..., LoadedRecipe],
) -> None:
    st = SimulatedStation(make_recipe({}, ideal=True))
    st.set_speed(20.0, st.clock.now_ns())
    st.clock.sleep(1.3)
    st.set_speed(0.0, st.clock.now_ns())
    st.clock.sleep(2.0)
    phi = st.platter_angle(st.clock.now_ns())
    assert phi > 1.0
    st.place("qa_cube")
    p = st.placements["qa_cube"]
    g = st.recipe.recipe.fixtures.qa_cube
    c, s = math.cos(phi), math.sin(phi)
    assert c * p["y"] - s * p["z"] == pytest.approx(g.offset[0])  # Rx(φ)·p_D = p_P
    assert s * p["y"] + c * p["z"] == pytest.approx(g.offset[1])
    assert p["yaw_rad"] + phi == pytest.approx(math.radians(g.yaw_deg))


def _arrays(path: Path) -> list[np.ndarray]:
    rec = read_recording(path)
    return [
        rec.line_timestamp_ns,
        rec.t_ns,
        rec.azimuth_rad,
        rec.range_m,
        rec.valid,
        rec.encoder_t_ns,
        rec.encoder_count,
        np.array([(s.timestamp_ns, s.speed_rpm) for s in rec.turntable]),
    ]


def test_simulate_run_is_deterministic(
    tmp_path: Path, make_recipe: Callable[..., LoadedRecipe]
) -> None:
    recipe = make_recipe(FAST)
    a = simulate_run(recipe, tmp_path / "a", seed=5, progress=False)
    b = simulate_run(recipe, tmp_path / "b", seed=5, progress=False)
    c = simulate_run(recipe, tmp_path / "c", seed=6, progress=False)
    assert a["truth"].read_bytes() == b["truth"].read_bytes()
    assert a["truth"].read_bytes() != c["truth"].read_bytes()
    for kind in ("static", "spin", "cube"):
        for x, y in zip(_arrays(a[kind]), _arrays(b[kind]), strict=True):
            assert np.array_equal(x, y)
        assert not np.array_equal(_arrays(a[kind])[3], _arrays(c[kind])[3])
        rec = read_recording(a[kind])
        assert rec.metadata["truth"]["seed"] == 5
        assert (
            rec.metadata["truth"]["fixture_on_platter"]
            == {"static": "static_target", "spin": "spin_target", "cube": "qa_cube"}[kind]
        )
    truth = json.loads(a["truth"].read_text())
    assert set(truth["fixtures"]) == {"static_target", "spin_target", "qa_cube"}
    assert truth["scenario"] == {"range_m": 1.25, "pitch_deg": 45.0}
