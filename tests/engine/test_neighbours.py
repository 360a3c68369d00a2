"""Nearest neighbours and local planes (calstation.engine.neighbours), and the periodicity problem's
closed-form Jacobian."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings, strategies as st
from scipy.optimize._numdiff import approx_derivative

from calstation.engine.neighbours import local_planes, mutual_neighbours, smallest_eigenvectors
from calstation.engine.periodicity.problem import _Matched, _Problem


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    scales=st.tuples(*[st.floats(1e-6, 1.0) for _ in range(3)]),
)
def test_closed_form_eigenvectors_agree_with_eigh(seed: int, scales: tuple[float, ...]) -> None:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    lam = np.sort(np.array(scales)) ** 2
    cov = (q * lam) @ q.T
    v, got = smallest_eigenvectors(cov[None])
    ref_lam, ref_vec = np.linalg.eigh(cov)
    # the trigonometric solution loses ~√ε of the scale where eigenvalues coincide
    assert np.allclose(got[0], ref_lam, rtol=0, atol=1e-7 * lam.max())
    if lam[1] - lam[0] > 1e-3 * lam[2]:  # the smallest eigenvector is defined
        assert abs(abs(v[0] @ ref_vec[:, 0]) - 1.0) < 1e-6


def test_local_planes_of_a_noisy_plane_far_from_the_origin() -> None:
    rng = np.random.default_rng(0)
    pts = np.column_stack(
        [rng.uniform(0, 0.05, 2000), rng.uniform(0, 0.05, 2000), rng.normal(0, 1e-5, 2000)]
    )
    pts += (100.0, -50.0, 3.0)  # a large offset must not cancel the sums
    idx = np.argsort(np.linalg.norm(pts[:, None, :2] - pts[None, :50, :2], axis=2), axis=0)[:20].T
    n, w, c = local_planes(pts, idx)
    assert np.all(np.abs(n[:, 2]) > 0.999) and np.median(w) > 0.6
    assert np.allclose(c, pts[idx].mean(axis=1), atol=1e-12)


def test_mutual_neighbours_are_exactly_the_brute_force_pairs() -> None:
    rng = np.random.default_rng(1)
    a, b = rng.uniform(0, 1, (500, 3)), rng.uniform(0, 1, (400, 3))
    i, j = mutual_neighbours(a, b, 0.05)
    # every pair of points that are each other's nearest, within the radius, and no other
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    nearest_b, nearest_a = d.argmin(axis=1), d.argmin(axis=0)
    expected = {(k, int(nearest_b[k])) for k in range(a.shape[0])
                if nearest_a[nearest_b[k]] == k and d[k, nearest_b[k]] <= 0.05}
    assert len(expected) > 20  # the check has pairs to find
    assert set(zip(i.tolist(), j.tolist(), strict=True)) == expected
    assert i.size == len(expected)  # each pair once


def test_periodicity_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(2)
    m = 300
    phi_a, phi_b = rng.uniform(0, np.pi, m), rng.uniform(np.pi, 2 * np.pi, m)
    normals = rng.normal(size=(2, m, 3))
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    matched = _Matched(
        rng.uniform(-1, 1, (m, 3)) * (1, 1, 0),
        np.cos(phi_a),
        np.sin(phi_a),
        rng.uniform(-1, 1, (m, 3)) * (1, 1, 0),
        np.cos(phi_b),
        np.sin(phi_b),
        normals[0],
        normals[1],
        rng.uniform(0, 1, m),
        rng.uniform(0, 1, m),
        rng.normal(0, 1e-3, m),
        rng.normal(0, 1e-3, m),
        np.zeros(m, dtype=np.int64),
    )
    platter = rng.uniform(-1, 1, (50, 3)) * (1, 1, 0)
    x6 = np.array([0.01, 1.2, -0.03, 0.0, 0.02, -0.7])
    free = [0, 1, 2, 4, 5]
    problem = _Problem(matched, platter, 1.0, free, x6)
    x = x6[free] + rng.normal(0, 1e-2, len(free))
    numeric = approx_derivative(problem.residuals, x, method="3-point")
    assert np.allclose(problem.jacobian(x), numeric, atol=1e-7)


def test_planes_shared_by_several_points_are_fitted_once_to_the_same_figures() -> None:
    """The one-sided matching fits each plane once however many points it is matched to
    (``plane_of``): each point's test, and each plane's normal, weight and centroid, are to the
    last bit those of the plane fitted again for every point."""
    from calstation.engine.neighbours import inside_neighbourhoods, knn, tree

    rng = np.random.default_rng(11)
    n = 4000
    points = np.column_stack([rng.uniform(0, 0.2, n), rng.uniform(0, 0.2, n),
                              rng.normal(0.0, 0.001, n)]) + np.array([0.3, -1.1, 0.7])
    hoods = knn(tree(points), points[:300], 16)
    plane_of = rng.integers(0, 300, 2000)  # many points per plane, some planes unused
    query = points[hoods[plane_of, 0]] + rng.normal(0.0, 0.01, (2000, 3))
    normal, weight, centroid = local_planes(points, hoods)
    each = local_planes(points, hoods[plane_of])
    for once, again in zip((normal, weight, centroid), each, strict=True):
        np.testing.assert_array_equal(once[plane_of], again)
    shared = inside_neighbourhoods(points, hoods, centroid, normal, query, plane_of=plane_of)
    own = inside_neighbourhoods(points, hoods[plane_of], centroid[plane_of], normal[plane_of],
                                query)
    np.testing.assert_array_equal(shared, own)
    assert 0 < np.count_nonzero(shared) < shared.size  # some points in, some out
