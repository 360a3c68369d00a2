"""Fixture meshes: dimensions from the recipe, and what the lidar sees of them."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from calstation_sim import SimulatedStation, meshes

from calstation.engine.frames import lidar_to_platform, polar_to_lidar
from calstation.errors import RecipeError, SimulationError
from calstation.recipes import (
    CubeGeometry,
    FrustumGeometry,
    LoadedRecipe,
    LTargetGeometry,
    PrismGeometry,
    PyramidGeometry,
)


def _bounds(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(mesh.vertices)
    return v.min(axis=0), v.max(axis=0)


def test_solid_meshes_are_closed_with_recipe_dimensions() -> None:
    cube = meshes.cube_mesh(CubeGeometry(edge=0.1))
    lo, hi = _bounds(cube)
    assert np.allclose(lo, [0, -0.05, -0.05]) and np.allclose(hi, [0.1, 0.05, 0.05])
    assert math.isclose(cube.get_volume(), 0.001, rel_tol=1e-9)
    pyr = meshes.pyramid_mesh(PyramidGeometry(base=0.15, height=0.15))
    assert math.isclose(pyr.get_volume(), 0.15**2 * 0.15 / 3, rel_tol=1e-9)
    prism = meshes.prism_mesh(PrismGeometry(edge=0.15, depth=0.225))
    lo, hi = _bounds(prism)
    assert np.allclose(hi - lo, [0.15 * math.sqrt(3) / 2, 0.15, 0.225])
    assert math.isclose(prism.get_volume(), 0.15**2 * math.sqrt(3) / 4 * 0.225, rel_tol=1e-9)
    for mesh in (cube, pyr, prism, meshes.platter_mesh(_platter())):
        assert mesh.is_watertight()


def _platter():  # type: ignore[no-untyped-def]
    from calstation.recipes import PlatterGeometry

    return PlatterGeometry()


def test_l_target_mesh_follows_design_section_3() -> None:
    g = LTargetGeometry()
    lo, hi = _bounds(meshes.l_target_mesh(g))
    assert np.allclose(lo, [0.0, -g.base_length, -g.width / 2])
    assert np.allclose(hi, [g.base_thickness + g.h_tall, g.wall_thickness, g.width / 2])
    assert meshes.wall_height(g, -g.width / 2) == pytest.approx(g.h_tall)
    assert meshes.wall_height(g, 0.0) == pytest.approx(g.h_mid)
    assert meshes.wall_height(g, g.width / 2) == pytest.approx(g.h_short)


@pytest.mark.parametrize("tz", [0.0, 0.012, -0.02])
def test_static_scan_shows_the_l_target_as_designed(
    make_recipe: Callable[..., LoadedRecipe], tz: float
) -> None:
    """Ray-cast the L-target with an ideal station at a known tz: A′B′ lies on the base top and
    is base_length long, B′ is at (base_thickness, 0), and the wall is seen h(−tz) tall —
    the paper's Eq. 3 read backwards."""
    H = {"tx": 0.004, "ty": 1.1, "tz": tz, "rx": 0.0, "ry": 0.0, "rz": math.radians(-40)}
    station = SimulatedStation(make_recipe({"simulation.truth.H": H}, ideal=True))
    station.place("static_target")
    g = station.recipe.recipe.fixtures.static_target
    line = station.scan_line(station.clock.now_ns())
    p = lidar_to_platform(polar_to_lidar(line.range_m, line.azimuth_rad)[line.valid], station.truth)
    assert np.allclose(p[:, 2], -tz, atol=1e-6)  # the scan plane cuts z_P = −tz
    base = p[np.abs(p[:, 0] - g.base_thickness) < 1e-5]
    wall = p[(np.abs(p[:, 1]) < 1e-5) & (p[:, 0] > g.base_thickness + 1e-4)]
    step = 0.004  # point spacing on the target is about 1.5–3 mm
    assert base[:, 1].min() == pytest.approx(-g.base_length, abs=step)
    assert base[:, 1].max() == pytest.approx(0.0, abs=step)
    seen = wall[:, 0].max() - g.base_thickness
    expected = g.h_mid + (g.h_tall - g.h_short) * tz / g.width
    assert seen == pytest.approx(expected, abs=step)
    assert g.width * (seen - g.h_mid) / (g.h_tall - g.h_short) == pytest.approx(tz, abs=0.01)


def test_frustum_facets_slope_as_configured() -> None:
    g = FrustumGeometry()
    mesh = meshes.frustum_mesh(g)
    assert mesh.is_watertight()
    v, t = meshes.mesh_arrays(mesh)
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    centre_x = v[t].mean(axis=1)[:, 0]
    sides = (centre_x > 1e-9) & (centre_x < g.height - 1e-9)
    slopes = np.degrees(np.arccos(np.abs(n[sides, 0])))  # facet inclination from the platter
    assert np.median(slopes) == pytest.approx(g.slope_deg, abs=0.5)
    assert np.all(slopes < 45.0)  # below the 45° pitch: every facet is seen in both half-turns
    lo, hi = _bounds(mesh)
    assert lo[0] == 0.0 and hi[0] == pytest.approx(g.height)
    poly = meshes.frustum_polygon(g)
    assert len(poly) == 7
    r = np.hypot(poly[:, 0], poly[:, 1])
    assert np.sort(r)[0] == pytest.approx(g.circumradius * (1 - g.notch_depth))
    assert np.allclose(np.sort(r)[1:], g.circumradius)


def test_frustum_too_tall_for_its_slope_is_an_error() -> None:
    with pytest.raises(SimulationError, match="spin_target"):
        meshes.frustum_mesh(FrustumGeometry(height=0.2, slope_deg=20))


def test_mesh_file_fixture(tmp_path: Path, make_recipe: Callable[..., LoadedRecipe]) -> None:
    box = o3d.geometry.TriangleMesh.create_box(0.05, 0.06, 0.07)
    box.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(tmp_path / "box.stl"), box)
    recipe = make_recipe({"fixtures.qa_cube.mesh": "box.stl"}, ideal=True)
    station = SimulatedStation(recipe)
    station.place("qa_cube")
    placed = station.fixture_mesh_in_D()
    assert placed is not None
    lo, hi = _bounds(placed)
    assert hi[0] - lo[0] == pytest.approx(0.05, abs=1e-6)  # the file's mesh, not a 100 mm cube


def test_missing_or_empty_mesh_file_is_a_clear_error(
    tmp_path: Path, make_recipe: Callable[..., LoadedRecipe]
) -> None:
    with pytest.raises(RecipeError, match=r"fixtures\.qa_cube\.mesh: mesh file not found"):
        make_recipe({"fixtures.qa_cube.mesh": "nope.stl"})
    # a file that disappears after the recipe was loaded
    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.1, 0.1)
    box.translate((0.0, -0.05, -0.05))
    assert o3d.io.write_triangle_mesh(str(tmp_path / "gone.stl"), box.compute_triangle_normals())
    station = SimulatedStation(make_recipe({"fixtures.qa_cube.mesh": "gone.stl"}))
    (tmp_path / "gone.stl").unlink()
    with pytest.raises(SimulationError, match=r"fixtures\.qa_cube\.mesh: mesh file not found"):
        station.place("qa_cube")
    # an empty mesh is refused when the recipe is validated, before anything moves
    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nend_header\n")
    with pytest.raises(RecipeError, match=r"fixtures\.qa_cube\.mesh: .*holds no triangles"):
        make_recipe({"fixtures.qa_cube.mesh": "empty.ply"})
