"""The simulated station's real-sensor errors (``simulation.sensor``): each one against the ideal
station's ranges of the same rays, and recorded in the truth."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import pytest
from calstation_sim import SimulatedStation

from calstation.drivers import LidarLine
from calstation.engine.frames import lidar_to_dynamic, polar_to_lidar
from calstation.recipes import LoadedRecipe

MakeRecipe = Callable[..., LoadedRecipe]


def _lines(recipe: LoadedRecipe, fixture: str = "static_target", n: int = 3,
           at_s: float = 0.0) -> tuple[SimulatedStation, list[LidarLine]]:
    """``n`` lines of ``fixture`` at rest, the first ``at_s`` seconds after the station
    started: (station, lines)."""
    station = SimulatedStation(recipe)
    station.place(fixture)
    t0 = station.clock.now_ns() + round(at_s * 1e9)
    times = t0 + np.arange(n, dtype=np.int64) * round(station.line_period_ns)
    return station, station.scan_lines(times)


def _ranges(lines: Sequence[LidarLine]) -> tuple[np.ndarray, np.ndarray]:
    return (np.stack([ln.range_m for ln in lines]), np.stack([ln.valid for ln in lines]))


def _platter_incidence(station: SimulatedStation) -> np.ndarray:
    """cos of each azimuth's ray with the platter's normal (+X_P), from the true H."""
    d_P = np.column_stack([np.sin(station.azimuths), np.cos(station.azimuths),
                           np.zeros_like(station.azimuths)]) @ station.truth.R
    out: np.ndarray = np.abs(d_P[:, 0])
    return out


def test_range_offset_and_scale_are_applied_to_every_return(make_recipe: MakeRecipe) -> None:
    ideal = make_recipe(ideal=True)
    b, k = 0.004, 1e-3
    real = make_recipe({"simulation.sensor.range.offset": b,
                        "simulation.sensor.range.scale": k}, ideal=True)
    r0, v0 = _ranges(_lines(ideal)[1])
    station, lines = _lines(real)
    r1, v1 = _ranges(lines)
    assert np.array_equal(v0, v1) and v0.sum() > 1000
    assert np.allclose(r1[v1], (1 + k) * r0[v0] + b, atol=1e-9)
    truth = station.truth_dict()
    assert truth["range_offset"] == b and truth["range_scale"] == k
    assert truth["sensor"]["range"] == {"offset": b, "scale": k, "incidence_bias": 0.0}


def test_incidence_bias_grows_as_one_over_cosine(make_recipe: MakeRecipe) -> None:
    c = 0.002
    ideal = make_recipe(ideal=True)
    real = make_recipe({"simulation.sensor.range.incidence_bias": c}, ideal=True)
    r0, v0 = _ranges(_lines(ideal, "none")[1])
    station, lines = _lines(real, "none")
    r1, _ = _ranges(lines)
    cos = _platter_incidence(station)
    # the bare platter: every return of the middle of the view hits its top
    middle = np.abs(station.azimuths) < math.radians(8)
    hit = v0[0] & middle
    assert hit.sum() > 100
    expected = c * (1.0 / cos[hit] - 1.0)
    assert np.allclose(r1[0, hit] - r0[0, hit], expected, atol=1e-7)
    assert expected.max() > expected.min() + 2e-4  # the bias changes across the platter


def test_reflectivity_bias_by_surface(make_recipe: MakeRecipe) -> None:
    ideal = make_recipe(ideal=True)
    real = make_recipe({"simulation.sensor.reflectivity.bias": 0.004,
                        "simulation.sensor.reflectivity.platter": 0.1,
                        "simulation.sensor.reflectivity.static_target": 0.9}, ideal=True)
    station, lines = _lines(real)
    r0, v0 = _ranges(_lines(ideal)[1])
    r1, _ = _ranges(lines)
    diff = np.round((r1 - r0)[v0], 9)
    # the dark platter reads 4 mm long, the white target as it is, the background (0.9) too
    assert set(np.unique(diff)) == {0.0, 0.004}
    assert station.truth_dict()["sensor"]["reflectivity"]["platter"] == 0.1


def test_warmup_drift_follows_the_time_since_power_on(make_recipe: MakeRecipe) -> None:
    drift, tau = 0.003, 100.0
    ideal = make_recipe(ideal=True)
    real = make_recipe({"simulation.sensor.warmup.drift": drift,
                        "simulation.sensor.warmup.time_constant_s": tau}, ideal=True)
    for at in (0.0, 100.0):
        r0, v0 = _ranges(_lines(ideal, at_s=at, n=1)[1])
        station, lines = _lines(real, at_s=at, n=1)
        r1, _ = _ranges(lines)
        # each return at its own time, a line lasting a millisecond: within 0.1 µm
        assert np.allclose((r1 - r0)[v0], drift * (1 - math.exp(-at / tau)), atol=1e-7)
    assert station.range_offset_at(station.clock.now_ns()) == pytest.approx(
        station.truth_dict()["sensor"]["warmup_drift_now_m"])


def test_encoder_eccentricity_and_second_harmonic(make_recipe: MakeRecipe) -> None:
    e1, p1, e2 = 0.5, 30.0, 0.2
    real = SimulatedStation(make_recipe({
        "simulation.sensor.encoder.eccentricity_deg": e1,
        "simulation.sensor.encoder.eccentricity_phase_deg": p1,
        "simulation.sensor.encoder.second_harmonic_deg": e2}, ideal=True))
    real.set_speed(30.0, real.clock.now_ns())
    t = real.clock.now_ns() + np.arange(0, 4_000_000_000, 10_000_000, dtype=np.int64)
    phi = real.platter_angles(t)
    counts = real.encoder_counts(t)
    error = (counts * 2 * math.pi / real.counts_per_revolution) - phi
    expected = (math.radians(e1) * np.sin(phi + math.radians(p1))
                + math.radians(e2) * np.sin(2 * phi))
    quantum = 2 * math.pi / real.counts_per_revolution
    assert np.all(np.abs(error - expected) <= quantum)
    assert np.abs(expected).max() > 5 * quantum


def _platter_points(
    station: SimulatedStation, lines: Sequence[LidarLine], phi: float
) -> np.ndarray:
    r, v = _ranges(lines)
    az = np.broadcast_to(station.azimuths, r.shape)
    p_L = polar_to_lidar(r[v], az[v])
    p_D = lidar_to_dynamic(p_L, np.full(len(p_L), phi), station.truth)
    rim = 0.98 * station.recipe.recipe.fixtures.platter.radius  # the rim's edge aside
    out: np.ndarray = p_D[(np.abs(p_D[:, 0]) < 0.003) & (np.hypot(p_D[:, 1], p_D[:, 2]) < rim)]
    return out


def test_axis_wobble_tilts_the_platter_toward_its_phase(make_recipe: MakeRecipe) -> None:
    w = 0.2
    tilts = []
    for phase in (0.0, 90.0):
        # tilted about +Y_D (phase 0) the platter keeps its chord in the scan plane level;
        # about +Z_D (phase 90°) the chord slopes by the wobble: the axis precesses with φ
        station, lines = _lines(make_recipe({"simulation.sensor.axis.wobble_deg": w,
                                             "simulation.sensor.axis.wobble_phase_deg": phase},
                                            ideal=True), "none")
        pts = _platter_points(station, lines, 0.0)
        slope = np.polyfit(pts[:, 1], pts[:, 0], 1)[0]
        tilts.append(abs(math.degrees(math.atan(slope))))
    assert tilts[0] < 0.1 * w
    assert tilts[1] == pytest.approx(w, abs=0.01)


def test_platter_dish_has_its_flatness(make_recipe: MakeRecipe) -> None:
    f = 0.0004
    station, lines = _lines(make_recipe({"simulation.sensor.platter.flatness": f}, ideal=True),
                            "none")
    pts = _platter_points(station, lines, 0.0)
    radius = np.hypot(pts[:, 1], pts[:, 2]) / station.recipe.recipe.fixtures.platter.radius
    heights = 0.5 * f * (2 * radius**2 - 1)
    assert np.allclose(pts[:, 0], heights, atol=2e-5)  # the dish's mesh is linear between rings
    assert pts[:, 0].max() - pts[:, 0].min() > 0.7 * f


def test_footprint_mixed_pixels_blend_by_the_footprint(make_recipe: MakeRecipe) -> None:
    ideal = {"simulation.lidar.beam_divergence_deg": 0.3}
    sharp = make_recipe(ideal, ideal=True)
    foot = make_recipe({**ideal, "simulation.sensor.mixed_pixels": "footprint"}, ideal=True)
    r0, v0 = _ranges(_lines(sharp, n=1)[1])
    r1, v1 = _ranges(_lines(foot, n=1)[1])
    r2, _ = _ranges(_lines(foot, n=1)[1])
    assert np.array_equal(r1, r2)  # no randomness: the footprint decides
    blended = v0[0] & v1[0] & (np.abs(r1[0] - r0[0]) > 1e-6)
    assert 0 < blended.sum() < 40  # only at depth edges
    # each blend lies between the ranges of its neighbours on either side of the edge
    for i in np.flatnonzero(blended):
        lo, hi = sorted((r0[0, max(i - 2, 0)], r0[0, min(i + 2, r0.shape[1] - 1)]))
        assert lo - 1e-6 <= r1[0, i] <= hi + 1e-6
