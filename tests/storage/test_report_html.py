"""The run report's residuals, on clouds whose answer is known."""

from __future__ import annotations

import numpy as np

from calstation.storage.report_html import half_turn_residuals, local_plane_residuals


def test_half_turn_residuals_measure_the_offset_between_half_turns() -> None:
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.linspace(0, 0.1, 40), np.linspace(0, 0.1, 40)), -1)
    plane = np.column_stack([np.zeros(1600), grid.reshape(-1, 2)])
    shift = np.array([0.002, 0.0, 0.0])  # the second half-turn 2 mm above the first
    points = np.vstack([plane, plane + shift])
    first = np.arange(points.shape[0]) < plane.shape[0]
    r = half_turn_residuals(points[rng.permutation(points.shape[0])], first)
    assert r.shape == (3200,)
    r = half_turn_residuals(points, first)
    assert np.allclose(r, 0.002)
    assert np.all(np.isinf(half_turn_residuals(plane, np.ones(1600, dtype=bool))))


def test_local_plane_residuals_are_the_noise_off_a_plane() -> None:
    rng = np.random.default_rng(4)
    yz = rng.uniform(0, 0.1, size=(4000, 2))
    flat = np.column_stack([np.zeros(4000), yz])
    assert np.max(local_plane_residuals(flat)) < 1e-12
    noisy = flat + np.column_stack([rng.normal(0, 0.001, 4000), np.zeros((4000, 2))])
    r = local_plane_residuals(noisy)
    # mean |n·(x − c)| of Gaussian noise σ = 1 mm is about 0.8 mm (fewer with 20 neighbours)
    assert 0.4e-3 < float(np.median(r)) < 1.0e-3
