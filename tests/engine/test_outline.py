"""Where a fixture appears in the scan plane (calstation.engine.outline): under the simulator's
true H, its returns lie on the outline; under a wrong H they do not."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from calstation.engine.frames import Extrinsics
from calstation.engine.outline import (
    cube_pieces,
    distance_to_outline,
    frustum_pieces,
    frustum_top_scale,
    l_target_pieces,
    placed,
    plane_section,
    platter_pieces,
    scan_outline,
)
from calstation.engine.reconstruct import platter_cloud
from calstation.recipes import frustum_outline, load_recipe

calstation_sim = pytest.importorskip("calstation_sim")
from calstation_sim.station import SimulatedStation  # noqa: E402

RECIPE = Path(__file__).resolve().parents[2] / "recipes" / "sim-periodicity.yaml"


def _returns(station: SimulatedStation, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x_L, y_L) of the lines' valid returns, and each return's platter angle."""
    xy, phi = [], []
    for line in station.scan_lines(t_ns):
        v = np.asarray(line.valid)
        rho, az = np.asarray(line.range_m)[v], np.asarray(line.azimuth_rad)[v]
        xy.append(np.column_stack([rho * np.sin(az), rho * np.cos(az)]))
        phi.append(np.full(rho.size, station.platter_angle(line.timestamp_ns)))
    return np.vstack(xy), np.concatenate(phi)


def _pieces_in_D(station: SimulatedStation, fixture: str, pieces: list[np.ndarray]
                 ) -> list[np.ndarray]:
    """``pieces`` where the simulator placed ``fixture`` (frame D, placement error included)."""
    p = station.placements[fixture]
    return placed(pieces, p["y"], p["z"], p["yaw_rad"])


def _on_platter(xy: np.ndarray, H: Extrinsics, radius: float) -> np.ndarray:
    """Returns within the platter's radius of its centre (the platter or what stands on it)."""
    return np.asarray(xy[np.hypot(xy[:, 0] - H.tx, xy[:, 1] - H.ty) < radius - 0.01])


def test_l_target_returns_lie_on_its_outline_under_the_true_H() -> None:
    loaded = load_recipe(RECIPE)
    fx = loaded.recipe.fixtures
    station = SimulatedStation(loaded, seed=5)
    station.place("static_target")
    t0 = station.clock.now_ns()
    xy, _ = _returns(station, t0 + np.arange(20, dtype=np.int64) * 1_000_000)
    H = station.truth
    target = _pieces_in_D(station, "static_target", l_target_pieces(fx.static_target))
    platter = platter_pieces(fx.platter.radius, fx.platter.thickness)
    phi = station.platter_angle(t0)
    near = _on_platter(xy, H, fx.platter.radius)
    outline = scan_outline(platter + target, H, phi)
    assert len(outline) == 3  # the platter, the base plate and the wall
    d = distance_to_outline(near, outline)
    assert near.shape[0] > 2000
    assert np.median(d) < 0.0015 and np.percentile(d, 98) < 0.004
    # the target's own returns (off the platter's line) lie on the target's outline
    on_target = distance_to_outline(near, scan_outline(platter, H, phi)) > 0.005
    assert on_target.sum() > 500
    d_target = distance_to_outline(near[on_target], scan_outline(target, H, phi))
    assert np.percentile(d_target, 95) < 0.004
    # an H 15 mm off along z_L moves the wall's section: the returns leave the outline
    wrong = scan_outline(platter + target, H.with_(tz=H.tz + 0.015, tx=H.tx + 0.01), phi)
    assert np.percentile(distance_to_outline(near, wrong), 90) > 0.005


def test_spin_target_returns_lie_on_its_outline_as_the_platter_turns() -> None:
    loaded = load_recipe(RECIPE)
    fx = loaded.recipe.fixtures
    station = SimulatedStation(loaded, seed=2)
    station.place("spin_target")
    t0 = station.clock.now_ns()
    moving = station.set_speed(20.0, t0)
    poly = np.asarray(frustum_outline(fx.spin_target))
    spin = frustum_pieces(poly, fx.spin_target.height,
                          frustum_top_scale(poly, fx.spin_target.height, fx.spin_target.slope_deg))
    target = _pieces_in_D(station, "spin_target", spin)
    platter = platter_pieces(fx.platter.radius, fx.platter.thickness)
    H = station.truth
    checked = 0
    for k in range(6):  # a line every ~40° of platter angle
        t = np.array([moving + k * 330_000_000], dtype=np.int64)
        xy, phi = _returns(station, t)
        near = _on_platter(xy, H, fx.platter.radius)
        outline = scan_outline(platter + target, H, float(phi[0]))
        d = distance_to_outline(near, outline)
        assert np.percentile(d, 95) < 0.004, f"line {k}"
        checked += near.shape[0]
    assert checked > 1000


def test_plane_section_of_a_cube() -> None:
    # a cube of edge 0.1 with its centre on the scan plane: a 0.1 × 0.1 square
    cube = cube_pieces(0.1)[0] - np.array([0.05, 0.0, 0.0])
    section = plane_section(cube)
    assert section.shape == (4, 2)
    assert np.allclose(np.sort(np.abs(section).ravel()), 0.05)
    # a cube wholly above the plane has no section
    assert plane_section(cube + np.array([0.0, 0.0, 0.2])).shape == (0, 2)
    H = Extrinsics(ty=1.0, rz=-math.radians(45))
    assert scan_outline([cube + np.array([0.0, 0.0, 0.2])], H) == []


def test_platter_cloud_keeps_the_platter_and_what_stands_on_it() -> None:
    H = Extrinsics(tx=0.01, ty=1.2, tz=0.003, ry=0.002, rz=-math.radians(40))
    p_D = np.array([[0.0, 0.1, 0.05], [0.05, -0.2, 0.1], [0.0, 0.5, 0.0], [-0.3, 0.0, 0.0]])
    phi = np.array([0.3, 1.2, 2.0, 0.0])
    from calstation.engine.frames import dynamic_to_lidar

    p_L = np.vstack([dynamic_to_lidar(p_D[i], phi[i], H) for i in range(4)])
    cloud = platter_cloud(p_L, phi, H, platter_radius=0.2925)
    assert np.allclose(cloud, p_D[:2], atol=1e-9)  # beyond the rim and below it: left out
