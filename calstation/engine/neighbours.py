"""Nearest neighbours and local planes on point clouds: the hot loop of fine-tuning.

All searches run in SciPy's ``cKDTree`` on every core (``workers=-1``). Local planes come from
a batched closed-form eigen-solution of the 3×3 neighbourhood covariances (trigonometric
eigenvalues, eigenvector by cross products), which is several times faster than
``numpy.linalg.eigh`` on millions of tiny matrices and agrees with it to ~1e-12 on planes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from calstation.engine.blocks import pool
from calstation.engine.frames import FloatArray

WORKERS = -1
"""Threads for the KD-tree queries (-1: every core)."""

T = TypeVar("T")


def pair(fn: Callable[..., T], a: tuple[object, ...], b: tuple[object, ...]) -> tuple[T, T]:
    """``(fn(*a), fn(*b))``, the two calls side by side: NumPy and the KD-tree release the GIL,
    so the two half-turns of a spin scan are processed on two cores."""
    second = pool("pair", 2).submit(fn, *b)
    return fn(*a), second.result()


def tree(points: FloatArray) -> cKDTree:
    """A KD-tree on (N, 3) points (built unbalanced: quicker to build and to query on scan
    clouds, the same neighbours)."""
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


def knn(t: cKDTree, query: FloatArray, k: int) -> NDArray[np.int64]:
    """(Q, k) indices of the ``k`` nearest tree points of each (Q, 3) query point."""
    k = min(k, t.n)
    _, idx = t.query(query, k=k, workers=WORKERS)
    out: NDArray[np.int64] = np.asarray(idx, dtype=np.int64).reshape(query.shape[0], k)
    return out


def mutual_neighbours(
    a: FloatArray,
    b: FloatArray,
    radius: float,
    *,
    tree_a: cKDTree | None = None,
    tree_b: cKDTree | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Index pairs (i, j) of mutual nearest neighbours between (N, 3) a and (M, 3) b within
    ``radius`` metres. Trees already built on a and b may be passed in."""
    if a.shape[0] == 0 or b.shape[0] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty.copy()
    if tree_a is None or tree_b is None:
        ta, tb = pair(tree, (a,), (b,))
    else:
        ta, tb = tree_a, tree_b
    da, ia = tb.query(a, distance_upper_bound=radius, workers=WORKERS)
    i = np.flatnonzero(np.isfinite(da))
    j = ia[i]
    # only the candidates need the reverse query, each once (many points of a share one)
    cand, inverse = np.unique(j, return_inverse=True)
    _, back = ta.query(b[cand], distance_upper_bound=radius, workers=WORKERS)
    mutual = back[inverse.reshape(-1)] == i
    return i[mutual].astype(np.int64), j[mutual].astype(np.int64)


def local_planes(
    points: FloatArray, idx: NDArray[np.int64]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Planes through the neighbourhoods ``points[idx]`` ((Q, k) indices).

    Returns ((Q, 3) unit normals, (Q,) planarity weights ``w = 2(λ2 − λ3)/(λ1 + λ2 + λ3)``,
    (Q, 3) centroids), λ1 ≥ λ2 ≥ λ3 the eigenvalues of each neighbourhood's covariance.
    """
    k = idx.shape[1]
    # one coordinate at a time (a (Q, k) gather is several times quicker than a (Q, k, 3) one),
    # relative to each neighbourhood's first point so that the sums do not cancel
    ref = points[idx[:, 0]]
    c = [points[:, a][idx] - ref[:, a : a + 1] for a in range(3)]
    m = [x.mean(axis=1) for x in c]
    cov = np.empty((idx.shape[0], 3, 3))
    for a in range(3):
        for b in range(a, 3):
            v = np.einsum("ij,ij->i", c[a], c[b]) / k - m[a] * m[b]
            cov[:, a, b] = v
            cov[:, b, a] = v
    mean = ref + np.column_stack(m)
    normal, lam = smallest_eigenvectors(cov)
    l3, l2, l1 = lam[:, 0], lam[:, 1], lam[:, 2]
    total = np.maximum(l1 + l2 + l3, 1e-30)
    w = np.clip(2.0 * (l2 - l3) / total, 0.0, 1.0)
    return normal, w, mean


def inside_neighbourhoods(
    points: FloatArray,
    idx: NDArray[np.int64],
    centroid: FloatArray,
    normal: FloatArray,
    query: FloatArray,
    limit: float = 1.0,
    *,
    plane_of: NDArray[np.int64] | None = None,
) -> NDArray[np.bool_]:
    """(Q,) whether each (Q, 3) ``query`` point lies within the neighbourhood ``points[idx]``
    ((Q, k) indices into the (N, 3) ``points``, with its (Q, 3) ``centroid`` and unit
    ``normal``) along the surface: its offset from the centroid, the normal part removed, at
    most ``limit`` of the neighbourhood's spread in that direction (a Mahalanobis distance in
    the tangent plane).

    A point outside its matched neighbourhood has no counterpart there (the other half-turn did
    not see that part of the surface, or the plane ends at an edge): its distance to the plane
    measures the extrapolation, not H.

    ``plane_of``: (Q,) the neighbourhood (row of ``idx``, ``centroid`` and ``normal``, given
    once each) of each query point, when several share one; else the query's own row.
    """
    k = idx.shape[1]
    if plane_of is not None:
        centroid_q, normal_q = centroid[plane_of], normal[plane_of]
    else:
        centroid_q, normal_q = centroid, normal
    off = query - centroid_q
    off -= np.einsum("ij,ij->i", off, normal_q)[:, None] * normal_q
    c = [points[:, a][idx] - centroid[:, a : a + 1] for a in range(3)]
    cov = np.empty((idx.shape[0], 3, 3))
    for a in range(3):
        for b in range(a, 3):
            v = np.einsum("ij,ij->i", c[a], c[b]) / k
            cov[:, a, b] = v
            cov[:, b, a] = v
    # the normal direction made as wide as the whole patch: only the tangential spread counts
    spread = np.trace(cov, axis1=1, axis2=2)
    cov += spread[:, None, None] * np.einsum("qi,qj->qij", normal, normal)
    cov += 1e-18 * np.eye(3)  # a degenerate patch (all on a line) stays solvable
    if plane_of is not None:
        cov = cov[plane_of]
    d2 = np.einsum("qi,qi->q", off, np.linalg.solve(cov, off[:, :, None])[:, :, 0])
    out: NDArray[np.bool_] = d2 <= limit**2
    return out


def smallest_eigenvectors(cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit eigenvectors of the smallest eigenvalue of (Q, 3, 3) symmetric matrices, and the
    (Q, 3) eigenvalues in ascending order, in closed form.

    Eigenvalues by the trigonometric solution of the characteristic cubic; the eigenvector is
    the largest cross product of two rows of ``A − λ3·I``. Isotropic matrices (no preferred
    plane) get an arbitrary unit vector; their planarity weight is 0 anyway.
    """
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    p = np.sqrt(np.maximum(p2, 0.0) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    det = (
        b00 * (b11 * b22 - a12 * a12)
        - a01 * (a01 * b22 - a12 * a02)
        + a02 * (a01 * a12 - b11 * a02)
    )
    r = np.clip(det / (2.0 * safe**3), -1.0, 1.0)
    angle = np.arccos(r) / 3.0
    l1 = q + 2.0 * p * np.cos(angle)
    l3 = q + 2.0 * p * np.cos(angle + 2.0 * math.pi / 3.0)
    l2 = 3.0 * q - l1 - l3
    lam = np.column_stack([l3, l2, l1])
    m = cov - l3[:, None, None] * np.eye(3)
    r0, r1, r2 = m[:, 0], m[:, 1], m[:, 2]
    c = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)  # (Q, 3, 3)
    norms = np.einsum("qij,qij->qi", c, c)
    best = np.argmax(norms, axis=1)
    v = c[np.arange(c.shape[0]), best]
    length = np.sqrt(norms[np.arange(c.shape[0]), best])
    ok = length > 0
    v[ok] /= length[ok, None]
    v[~ok] = (1.0, 0.0, 0.0)
    return v, lam


def weighted_normals(
    points: FloatArray,
    k: int,
    query: NDArray[np.int64] | None = None,
    *,
    t: cKDTree | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Unit normals and planarity weights from the k nearest points (paper §IV-C).

    ``points`` (N, 3); ``query`` optional indices of the points that need a normal (default
    all); ``t`` a tree already built on ``points``. Returns ((Q, 3) unit normals, (Q,) weights,
    (Q, 3) neighbourhood centroids) with ``w = 2(λ2 − λ3)/(λ1 + λ2 + λ3)``: 1 on a plane, 0 on
    an edge or in a blob.
    """
    n = points.shape[0]
    q = np.arange(n) if query is None else np.asarray(query, dtype=np.int64)
    if n < 3 or q.size == 0:
        return np.zeros((q.size, 3)), np.zeros(q.size), np.zeros((q.size, 3))
    idx = knn(tree(points) if t is None else t, points[q], k)
    return local_planes(points, idx)
