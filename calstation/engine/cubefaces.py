"""The cube's faces, found in its returns and fitted as planes (the cube check's face-fit
dimensions, :mod:`calstation.engine.cube`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import FloatArray
from calstation.engine.geometry import fit_plane


@dataclass(frozen=True)
class Face:
    """A cube face's plane: a point on it, its unit normal, its RMS, its returns."""

    centroid: FloatArray
    normal: FloatArray
    rms: float
    n: int
    members: NDArray[np.intp]
    """indices of the face's returns in the cleaned cube cloud"""


FACE_SPREAD = 0.025
"""A face's returns fit a plane only if they spread over at least this fraction of the cube's
edge (1σ) in both of the face's directions. A face crossed by one or two scan lines (lines lost
in a gap of the lidar's stream) has returns along a line: its plane may turn about that line
at will, and its angle to a neighbour is the fit's, not the cube's. On the default simulated
cube a face crossed by two neighbouring lines spread 0.018 of the edge (1 mm of range noise), a
face seen whole spreads ~0.23, and a sliver seen at grazing incidence 0.037."""


def find_faces(
    cube: FloatArray,
    axes: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    band: float,
    keep_out: float,
    min_spread: float,
) -> dict[str, Face]:
    """The planes of the side faces (``1-``, ``1+``, ``2-``, ``2+``) and the top of the cube's
    returns ``cube`` in the box ``axes``/``lo``/``hi`` (its local frame, height first): the
    returns within ``band`` of each of the box's sides, ``keep_out`` or more from the other
    faces; a face without a plane (:func:`plane_face`) is left out."""
    local = cube @ axes
    faces: dict[str, Face] = {}
    inner_top = local[:, 0] < hi[0] - keep_out
    for j in (1, 2):
        other = 3 - j
        inner = (local[:, other] > lo[other] + keep_out) & (local[:, other] < hi[other] - keep_out)
        for name, ref in ((f"{j}-", lo[j]), (f"{j}+", hi[j])):
            sel = (np.abs(local[:, j] - ref) < band) & inner & inner_top
            if (face := plane_face(cube, sel, min_spread)) is not None:
                faces[name] = face
    inner = np.ones(local.shape[0], dtype=bool)
    for j in (1, 2):
        inner &= (local[:, j] > lo[j] + keep_out) & (local[:, j] < hi[j] - keep_out)
    sel = inner & (np.abs(local[:, 0] - hi[0]) < band)
    if (face := plane_face(cube, sel, min_spread)) is not None:
        faces["top"] = face
    return faces


def plane_face(cube: FloatArray, sel: NDArray[np.bool_], min_spread: float) -> Face | None:
    """The plane through ``cube[sel]``, or None with fewer than 30 returns or returns that do not
    spread ``min_spread`` (1σ, m) across the plane in both directions."""
    count = int(sel.sum())
    if count < 30:
        return None
    pts = cube[sel]
    c, n, rms = fit_plane(pts)
    q = pts - c
    q -= np.outer(q @ n, n)
    if math.sqrt(max(float(np.linalg.eigvalsh(q.T @ q / count)[1]), 0.0)) < min_spread:
        return None
    return Face(c, n, rms, count, np.flatnonzero(sel))


def angle_deg(n1: FloatArray, n2: FloatArray) -> float:
    """The angle between two planes of unit normals ``n1`` and ``n2`` (degrees, 0–90)."""
    return math.degrees(math.acos(min(1.0, abs(float(np.dot(n1, n2))))))
