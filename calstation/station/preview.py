"""What an operator sees of a scan while it is taken, beside the lidar's line.

- ``outline``: where the platter and the fixture being scanned should appear in the scan plane,
  under the calibration known so far (:func:`preview_calibration`), at the platter's angle;
  closed polylines (x_L, y_L) in metres (:func:`calstation.engine.outline.scan_outline`).
- ``cloud``: for a spin or cube scan, the returns prepared so far reconstructed in D under that
  calibration (:func:`calstation.engine.reconstruct.platter_cloud`): only the points new since
  the last event, a subsample such that a scan of its planned turns sends at most
  :data:`CLOUD_POINTS`.

They are published every :data:`OUTLINE_PERIOD_S` and :data:`CLOUD_PERIOD_S` at most, right
after a line (an operator may show that line with the outline), and only to an operator that asks
for them (``previews = True``, the web station): a terminal or unattended run pays nothing.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING

import numpy as np
from sqlalchemy import select

from calstation.engine.frames import Extrinsics, FloatArray
from calstation.engine.outline import (
    cube_pieces,
    frustum_pieces,
    frustum_top_scale,
    l_target_pieces,
    placed,
    platter_pieces,
    scan_outline,
)
from calstation.engine.reconstruct import platter_cloud
from calstation.engine.settings import CubeGeometry, LTargetGeometry
from calstation.recipes import FrustumGeometry, Recipe, frustum_outline
from calstation.station.context import RunContext
from calstation.station.operator import Operator, WantsPreviews, publish
from calstation.station.stored import latest_calibration
from calstation.storage.db import Calibration, Run

if TYPE_CHECKING:
    from calstation.engine.spinscan import SpinScanBuilder

OUTLINE_PERIOD_S = 0.5
"""At most this often the outline is published (as often as the web station shows a line)."""

CLOUD_PERIOD_S = 1.0
"""At most this often the new cloud points are published."""

CLOUD_POINTS = 6_000
"""Most cloud points one scan sends: the live view's 3D plot draws them in a browser that may
have no graphics processor, while the run goes on (the report shows 12 000 from the file)."""

NO_CALIBRATION = "no calibration known yet: the L-target scan gives the first"

STAGE_WORDS = {"initial": "the initial calibration", "fine": "the fine-tuned calibration"}


def wants_previews(ui: Operator) -> bool:
    """Whether ``ui`` shows previews (an operator's optional ``previews`` attribute)."""
    return isinstance(ui, WantsPreviews) and bool(ui.previews)


def preview_calibration(ctx: RunContext) -> tuple[Extrinsics | None, str]:
    """The calibration known so far and what it is, in words: the run's newest (fine before
    initial), else the station's last accepted one, else the recipe's nominal mounting (the
    simulated lidar's range and pitch); (None, why) when none is known."""
    H, stage = latest_calibration(ctx.db, ctx.run_id)
    if H is not None:
        return H, STAGE_WORDS.get(stage, f"the {stage} calibration")
    with ctx.db.session() as s:
        station = s.scalar(select(Run.station_id).where(Run.id == ctx.run_id))
        previous = s.scalars(
            select(Calibration).join(Run, Calibration.run_id == Run.id)
            .where(Run.station_id == station, Calibration.accepted, Run.id != ctx.run_id)
            .order_by(Calibration.id.desc())
        ).first()
        if previous is not None:
            return (Extrinsics.from_dict(previous.params()),
                    f"the calibration of run {previous.run_id} on this station")
    nominal = nominal_mounting(ctx.recipe)
    if nominal is not None:
        return nominal, "the recipe's nominal mounting"
    return None, NO_CALIBRATION


def nominal_mounting(recipe: Recipe) -> Extrinsics | None:
    """The mounting a recipe's simulated station is built around: its ``simulation.truth.H``,
    else the lidar ``range`` from the axis at ``pitch_deg`` (no offsets, no tilt); None
    without a simulation section."""
    sim = recipe.simulation
    if sim is None:
        return None
    truth = sim.truth
    if truth.H is not None:
        return Extrinsics.from_dict(truth.H)
    return Extrinsics(ty=float(truth.range), rz=-math.radians(float(truth.pitch_deg)))


def fixture_pieces(recipe: Recipe, fixture: str) -> list[FloatArray]:
    """The convex pieces of ``fixture`` where the recipe places it (in P when placed); [] for
    a fixture without a parametric shape (a mesh, a demo object, none)."""
    geom = getattr(recipe.fixtures, fixture, None)
    if isinstance(geom, LTargetGeometry):
        pieces = l_target_pieces(geom)
    elif isinstance(geom, CubeGeometry):
        pieces = cube_pieces(geom.edge)
    elif isinstance(geom, FrustumGeometry) and geom.mesh is None:
        poly = np.asarray(frustum_outline(geom))
        pieces = frustum_pieces(poly, geom.height,
                                frustum_top_scale(poly, geom.height, geom.slope_deg))
    else:
        return []
    y, z = geom.offset
    return placed(pieces, y, z, math.radians(float(getattr(geom, "yaw_deg", 0.0))))


def scan_fixture(ctx: RunContext, kind: str) -> str:
    """The fixture on the platter during a ``kind`` recording."""
    if kind == "spin":
        return str(ctx.strategy().fixture)
    return {"static": "static_target", "cube": "qa_cube"}.get(kind, "none")


class ScanPreview:
    """Publishes a scan's ``outline`` and ``cloud`` events (see the module docstring);
    ``builder`` is the scan's :class:`~calstation.engine.spinscan.SpinScanBuilder` (platter
    angles and returns), None for a static scan or a second pass."""

    def __init__(
        self, ctx: RunContext, kind: str, builder: SpinScanBuilder | None, revolutions: float
    ) -> None:
        self.ui, self.kind, self.builder = ctx.ui, kind, builder
        self.H, self.source = preview_calibration(ctx)
        platter = ctx.recipe.fixtures.platter
        self.platter_radius = platter.radius
        self.fixture = scan_fixture(ctx, kind)
        fixture = fixture_pieces(ctx.recipe, self.fixture)
        # a turning fixture's place is known only with the platter's angle
        self.pieces = platter_pieces(platter.radius, platter.thickness) + (
            fixture if kind == "static" or builder is not None else [])
        self.revolutions = max(float(revolutions), 0.1)
        self._last = self._last_cloud = -math.inf
        self._phi0: float | None = None
        self._read = 0
        self._sent = 0
        self._sent_turns = 0.0

    def line(self, final: bool = False) -> None:
        """After each lidar line: publish when the period has passed (``final``: the scan
        ended, publish what is left)."""
        now = time.monotonic()
        if now - self._last < OUTLINE_PERIOD_S and not final:
            return
        self._last = now
        scan = None if self.builder is None else self.builder.so_far()
        turned = 0.0
        if scan is not None and scan.n_points:
            if self._phi0 is None:
                self._phi0 = float(scan.phi[0])  # where the fixture was placed
            turned = float(scan.phi[-1]) - self._phi0
        self._outline(turned)
        if (scan is not None and self.H is not None and self._read < scan.n_points
                and (final or now - self._last_cloud >= CLOUD_PERIOD_S)):
            self._last_cloud = now
            self._cloud(scan.p_L[self._read:], scan.phi[self._read:])
            self._read = scan.n_points

    def _outline(self, turned: float) -> None:
        lines = [] if self.H is None else scan_outline(self.pieces, self.H, turned)
        publish(self.ui, "outline", scan=self.kind, fixture=self.fixture, source=self.source,
                known=self.H is not None, platter_angle_deg=math.degrees(turned),
                lines=[np.round(line, 5).tolist() for line in lines])

    def _cloud(self, p_L: FloatArray, phi: FloatArray) -> None:
        assert self.H is not None
        turns = float(phi[-1] - phi[0]) / (2 * math.pi)
        self._sent_turns += turns
        # a share of the points in proportion to the turns these returns cover
        goal = math.ceil(CLOUD_POINTS * min(1.0, self._sent_turns / self.revolutions))
        budget = min(goal, CLOUD_POINTS) - self._sent
        if budget <= 0:
            return
        every = max(1, p_L.shape[0] // (20 * budget))  # transform a fraction only
        cloud = platter_cloud(p_L[::every], phi[::every], self.H, self.platter_radius)
        if cloud.shape[0] > budget:
            cloud = cloud[np.linspace(0, cloud.shape[0] - 1, budget).astype(int)]
        if cloud.shape[0] == 0:
            return
        self._sent += cloud.shape[0]
        publish(self.ui, "cloud", scan=self.kind, source=self.source,
                start=self._sent - cloud.shape[0], points=np.round(cloud, 4).tolist())
