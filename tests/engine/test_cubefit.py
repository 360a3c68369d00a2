"""The known-size cube fit (calstation.engine.cubefit): the shape strategy's last stage."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calstation.engine.cubefit import known_size_fit
from calstation.engine.frames import lidar_to_dynamic
from calstation.engine.metrics import axis_errors
from calstation.engine.spinscan import from_recording, prepare
from calstation.errors import FineTuningError
from calstation.recipes import load_recipe
from calstation.recordings.reader import read_recording


@pytest.fixture(scope="module")
def cube_scan(sim_run):  # type: ignore[no-untyped-def]
    """The default scenario's cube scan, its truth and its recipe."""
    run = sim_run()
    recipe = load_recipe("recipes/sim-periodicity.yaml").recipe
    rec = read_recording(run["cube"])
    assert rec.truth is not None
    return from_recording(rec), rec.truth, recipe


def test_from_a_start_a_millimetre_off_it_finds_the_axis(cube_scan) -> None:  # type: ignore[no-untyped-def]
    scan, truth, recipe = cube_scan
    start = truth.with_(tx=truth.tx + 0.0008, tz=truth.tz - 0.0006, rz=truth.rz + 0.0005)
    fit = known_size_fit(scan, start, recipe.fixtures.qa_cube,
                         platter_radius=recipe.fixtures.platter.radius)
    e = axis_errors(fit.H, truth)
    assert e["axis_offset_m"] <= 0.1e-3
    assert math.degrees(e["axis_angle_rad"]) <= 0.05
    for name in ("tz", "ry", "rz"):
        assert abs(e[f"{name}_error"]) <= 3 * fit.sigma[name], name
    assert fit.details["faces"] >= 4 and fit.details["range_noise_m"] == pytest.approx(1e-3, 0.1)
    assert fit.covariance is not None and fit.covariance["parameters"] == ["tx", "tz", "ry", "rz"]


def test_the_cubes_edge_is_what_places_the_axis_and_its_tolerance_is_in_sigma(
    cube_scan,  # type: ignore[no-untyped-def]
) -> None:
    """A cube 0.4 mm larger than the recipe says moves the axis by about (π/4)·0.4 mm; a recipe
    that states that tolerance gets a σ that covers the move."""
    scan, truth, recipe = cube_scan
    cube = recipe.fixtures.qa_cube
    radius = recipe.fixtures.platter.radius
    exact = known_size_fit(scan, truth, cube.model_copy(update={"edge_tolerance": 0.0}),
                           platter_radius=radius)
    wrong = cube.model_copy(update={"edge": cube.edge - 0.0004, "edge_tolerance": 0.0})
    moved = known_size_fit(scan, truth, wrong, platter_radius=radius)
    off = axis_errors(moved.H, exact.H)["axis_offset_m"]
    assert 0.15e-3 <= off <= 0.6e-3
    # the same wrong edge, stated with its tolerance: σ covers the axis it gives
    honest = known_size_fit(scan, truth, wrong.model_copy(update={"edge_tolerance": 0.0004}),
                            platter_radius=radius)
    e = axis_errors(honest.H, truth)
    assert all(abs(e[f"{n}_error"]) <= 3 * honest.sigma[n] for n in ("tz", "ry", "rz"))
    assert honest.sigma["tx"] > 3 * exact.sigma["tx"]


def test_without_the_cube_it_says_so(cube_scan) -> None:  # type: ignore[no-untyped-def]
    scan, truth, recipe = cube_scan
    p_D = lidar_to_dynamic(scan.p_L, scan.phi, truth)
    below = p_D[:, 0] < 0.005  # the platter and the background, no cube
    empty = prepare(scan.p_L[below], scan.phi[below])
    with pytest.raises(FineTuningError, match=r"known-size cube fit found .* returns of the cube"):
        known_size_fit(empty, truth, recipe.fixtures.qa_cube,
                       platter_radius=recipe.fixtures.platter.radius)
    assert np.count_nonzero(below) < scan.p_L.shape[0]
