"""Matching the two half-turns' cells under an H, for one stage of the periodicity fine-tuning:
mutual nearest neighbours in frame D and the local planes around each end (the coarse stages),
or every cell against the plane around its nearest cell in the other half (the last stage)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from calstation.engine.frames import FloatArray
from calstation.engine.neighbours import (
    WORKERS,
    inside_neighbourhoods,
    knn,
    local_planes,
    mutual_neighbours,
    pair,
    tree,
)
from calstation.engine.periodicity.cells import _Half, to_dynamic
from calstation.engine.periodicity.covariance import SIGMA_BLOCK, block_ids
from calstation.engine.periodicity.problem import _Matched
from calstation.engine.periodicity.schedule import Stage
from calstation.errors import FineTuningError

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

MIN_MATCHES = 50
"""Fewest matched cells between the two half-turns an iteration accepts."""


class _Matcher:
    """Matches the two half-turns' cells of one stage under successive H.

    The cells, their platter angles and each cell's neighbourhood within its own half are fixed
    for the stage. A neighbourhood (the ``normal_neighbours`` nearest cells in D) is found under
    the H of the stage's first iteration, and again only once H has moved by more than a cell:
    a half-turn's reconstruction deforms smoothly with H, so its neighbourhoods stay while the
    planes through them are refitted at every H. Only the matching between the halves, which
    is what H changes, is searched again at every iteration. Cells well below the platter drop
    (the platter top itself) are left out of the neighbourhoods until they are refreshed.
    """

    def __init__(self, halves: list[_Half], stage: Stage) -> None:
        self.halves = halves
        self.stage = stage
        self.cs = [(np.cos(h.phi), np.sin(h.phi)) for h in halves]
        self.candidates: list[NDArray[np.int64]] = []
        self.frozen: list[FloatArray] = []
        self.trees: list[cKDTree] = []
        self.neighbourhoods: list[NDArray[np.int64]] = []
        self.x6: FloatArray | None = None

    def _stale(self, x6: FloatArray) -> bool:
        if self.x6 is None:
            return True
        moved = np.abs(x6 - self.x6)
        return bool(moved[:3].max() > self.stage.voxel or moved[3:].max() * 0.3 > self.stage.voxel)

    def _refresh(self, d_all: list[FloatArray], x6: FloatArray) -> None:
        drop = self.stage.platter_drop
        # half the drop height: clear of the platter top, with room for H to move
        self.candidates = [
            np.arange(d.shape[0]) if drop is None else np.flatnonzero(d[:, 0] > drop / 2)
            for d in d_all
        ]
        self.frozen = [d[cand] for d, cand in zip(d_all, self.candidates, strict=True)]
        self.trees = [tree(f) for f in self.frozen]
        k = min(self.stage.normal_neighbours, *(f.shape[0] for f in self.frozen))
        self.neighbourhoods = [np.full((f.shape[0], k), -1, dtype=np.int64) for f in self.frozen]
        self.x6 = x6.copy()

    def _neighbourhoods(self, half: int, pos: NDArray[np.int64]) -> NDArray[np.int64]:
        """(Q, k) neighbourhoods (indices into the half's cells) of the candidates ``pos``,
        searched on first use under the H of the last refresh."""
        table = self.neighbourhoods[half]
        missing = np.unique(pos[table[pos, 0] < 0])
        if missing.size:
            found = knn(self.trees[half], self.frozen[half][missing], table.shape[1])
            table[missing] = self.candidates[half][found]
        return table[pos]

    def __call__(self, x6: FloatArray) -> tuple[_Matched, int]:
        """Map both halves to D under H, drop the platter, match, fit the local planes."""
        stage = self.stage
        stale = self._stale(x6)
        (ha, hb), (ca, sa), (cb, sb) = self.halves, self.cs[0], self.cs[1]
        d_all = list(pair(to_dynamic, (ha.p_L, ca, sa, x6), (hb.p_L, cb, sb, x6)))
        if stale:
            self._refresh(d_all, x6)
        kept = []  # positions in the candidates
        for d, cand in zip(d_all, self.candidates, strict=True):
            drop = stage.platter_drop
            kept.append(np.arange(cand.size) if drop is None else np.flatnonzero(d[cand, 0] > drop))
        if min(k.size for k in kept) < MIN_MATCHES:
            raise FineTuningError(
                f"periodicity ({stage.voxel * 1e3:.0f} mm cells): only {kept[0].size} and "
                f"{kept[1].size} cells of the two half-turns lie above the platter under the "
                "current estimate; the start is too far off (run the coarse stages, or start "
                "from the initial calibration) or the spin target is not in view"
            )
        ka, kb = self.candidates[0][kept[0]], self.candidates[1][kept[1]]
        da, db = d_all[0][ka], d_all[1][kb]
        if stage.one_sided:
            return self._one_sided(d_all, kept, ka, kb, da, db)
        i, j = mutual_neighbours(da, db, stage.match_radius)
        (na, wa, ma), (nb, wb, mb) = pair(
            local_planes,
            (d_all[0], self._neighbourhoods(0, kept[0][i])),
            (d_all[1], self._neighbourhoods(1, kept[1][j])),
        )
        # each residual measures a point against the other half's local plane fit (through its
        # neighbourhood centroid), not against one noisy point; the offset moves with the point
        oa = np.einsum("ij,ij->i", na, ma - da[i])
        ob = np.einsum("ij,ij->i", nb, mb - db[j])
        gi, gj = ka[i], kb[j]
        matched = _Matched(
            ha.p_L[gi],
            ca[gi],
            sa[gi],
            hb.p_L[gj],
            cb[gj],
            sb[gj],
            na,
            nb,
            wa,
            wb,
            oa,
            ob,
            block_ids(da[i], SIGMA_BLOCK),
        )
        return matched, int(da.shape[0] + db.shape[0])

    def _one_sided(
        self,
        d_all: list[FloatArray],
        kept: list[NDArray[np.int64]],
        ka: NDArray[np.int64],
        kb: NDArray[np.int64],
        da: FloatArray,
        db: FloatArray,
    ) -> tuple[_Matched, int]:
        """Every cell of each half against the plane around its nearest cell in the other half,
        when it lies within that plane's neighbourhood along the surface.

        The mutual test keeps the pairs whose noise brings them together: with cells whose
        noise is a third of their spacing it absorbs part of any displacement between the
        halves, so the residuals under-state how H moves them and the covariance under-states
        the error (by 1.5–2× on the simulator, for every number of turns). One-sided matches
        select on nothing but the position along the surface; the test that the point lies
        within the plane's neighbourhood drops the cells the other half-turn did not see, whose
        distance to an extrapolated plane biased ry (+0.1 to +0.2° on a centred target).
        ``d_all`` are both halves' cells in D, ``kept`` the positions of those above the
        platter among the candidates, ``ka``/``kb`` their indices into the halves and
        ``da``/``db`` their positions in D.
        """
        radius = self.stage.match_radius
        ta, tb = pair(tree, (da,), (db,))
        (dist_b, near_b), (dist_a, near_a) = pair(
            lambda t, q: t.query(q, distance_upper_bound=radius, workers=WORKERS),
            (tb, da),
            (ta, db),
        )
        a_ok, b_ok = np.flatnonzero(np.isfinite(dist_b)), np.flatnonzero(np.isfinite(dist_a))
        # planes: B's around the nearest B cell of each A cell; A's around that of each B cell
        plane_half = [1, 0]
        plane_pos = [near_b[a_ok], near_a[b_ok]]  # positions in kept[1], kept[0]
        points = [ka[a_ok], kb[b_ok]]  # cells (indices into the halves) matched to them
        # each plane once: about two cells of the other half share each nearest cell
        sides = list(pair(
            lambda side: self._inside(d_all, kept, plane_half[side], plane_pos[side],
                                      points[side]),
            (0,), (1,),
        ))
        return self._one_sided_matches(sides, d_all), int(da.shape[0] + db.shape[0])

    def _inside(
        self,
        d_all: list[FloatArray],
        kept: list[NDArray[np.int64]],
        h: int,
        plane_pos: NDArray[np.int64],
        points: NDArray[np.int64],
    ) -> _OneSide:
        """The matches of the other half's cells ``points`` against the planes of half ``h``
        around its cells at ``plane_pos`` (positions in ``kept[h]``) whose point lies within
        the plane's neighbourhood along the surface. Each plane is fitted once, however many
        points it is matched to (each plane's figures depend on its neighbourhood alone)."""
        unique, plane_of = np.unique(plane_pos, return_inverse=True)
        hood = self._neighbourhoods(h, kept[h][unique])
        normal, weight, centroid = local_planes(d_all[h], hood)
        q = d_all[1 - h][points]
        inside = inside_neighbourhoods(d_all[h], hood, centroid, normal, q, plane_of=plane_of)
        at = plane_of[inside]
        cell = self.candidates[h][kept[h][unique]]
        return _OneSide(h, cell[at], points[inside], normal[at], weight[at], centroid[at],
                        q[inside])

    def _one_sided_matches(self, sides: list[_OneSide], d_all: list[FloatArray]) -> _Matched:
        """Both sides' one-sided matches as one :class:`_Matched`: each plane's cell in A's
        place, the point matched to it in B's."""
        planes_L, planes_c, planes_s, pts_L, pts_c, pts_s = [], [], [], [], [], []
        normals, weights, offsets, where = [], [], [], []
        for side in sides:
            h = side.half
            hp, hq = self.halves[h], self.halves[1 - h]
            cp, cq = self.cs[h], self.cs[1 - h]
            planes_L.append(hp.p_L[side.cell])
            planes_c.append(cp[0][side.cell])
            planes_s.append(cp[1][side.cell])
            pts_L.append(hq.p_L[side.point])
            pts_c.append(cq[0][side.point])
            pts_s.append(cq[1][side.point])
            normals.append(side.normal)
            weights.append(side.weight)
            # the residual measures the point against the plane through the centroid
            offsets.append(np.einsum("ij,ij->i", side.normal, side.centroid - d_all[h][side.cell]))
            where.append(side.where)
        na = np.concatenate(normals)
        wa = np.concatenate(weights)
        zero = np.zeros(wa.shape[0])
        return _Matched(
            np.concatenate(planes_L),
            np.concatenate(planes_c),
            np.concatenate(planes_s),
            np.concatenate(pts_L),
            np.concatenate(pts_c),
            np.concatenate(pts_s),
            na,
            na,
            wa,
            zero,
            np.concatenate(offsets),
            zero,
            block_ids(np.concatenate(where), SIGMA_BLOCK),
            one_sided=True,
        )


@dataclass(frozen=True)
class _OneSide:
    """The one-sided matches of one half's cells against the other half's planes."""

    half: int
    """the half whose planes they are"""
    cell: NDArray[np.int64]
    """(M,) the plane's cell (index into that half)"""
    point: NDArray[np.int64]
    """(M,) the matched cell of the other half"""
    normal: FloatArray
    weight: FloatArray
    centroid: FloatArray
    """(M, 3) the plane's unit normal, planarity weight and centroid in D"""
    where: FloatArray
    """(M, 3) the matched cell in D (its spatial block)"""


def _match(halves: list[_Half], x6: FloatArray, stage: Stage) -> tuple[_Matched, int]:
    """Match the two half-turns' cells once under H (:class:`_Matcher`)."""
    return _Matcher(halves, stage)(x6)
