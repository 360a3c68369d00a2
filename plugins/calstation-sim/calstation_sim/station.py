"""The simulated station: a ray-cast scene, a line scanner, a turntable and an encoder (DESIGN §6).

Scenes: the dynamic scene (platter + the fixture on it) lives in frame D and turns with the
platter; the static background (floor, back wall) lives in frame P. A lidar point i of a line that
starts at t₀ is measured at t₀ + round(i·point_period); its ray (origin 0, direction
(sin α, cos α, 0) in L) is taken to P with the true H⁻¹ and to D with the platter angle φ at that
point's own time, then cast against both scenes; the nearest hit wins.

Everything random comes from ``numpy.random.SeedSequence`` streams derived from the seed (truth,
placements, measurement noise), so a seed and the same sequence of calls give identical data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypedDict

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from calstation.clock import Clock, SimClock
from calstation.drivers import DriverContext, LidarInfo, LidarLine
from calstation.engine.frames import Extrinsics, counts_per_revolution
from calstation.errors import FrameError, SimulationError
from calstation.jsonvalue import JSONObject
from calstation.recipes import LoadedRecipe, Recipe, SimulationConfig

from . import meshes
from .motion import PlatterMotion, rpm_to_rad_s

FloatArray = NDArray[np.float64]

FIXTURE_NAMES = ("static_target", "spin_target", "qa_cube")
"""Fixtures ``place`` accepts besides ``"none"`` and ``"demo:<index>"``."""

MIXED_PIXEL_GAP_M = 0.03
"""Two sub-beams whose ranges differ by more than this straddle a depth edge (mixed pixel)."""

FOOTPRINT_BEAMS = 7
"""Sub-beams across the beam's divergence of the footprint model of mixed pixels."""

_STREAM_TRUTH, _STREAM_PLACEMENT, _STREAM_NOISE = 1, 2, 3
_FAR = 1.0e3  # stands in for "no return" when comparing neighbouring ranges


class PlacementRecord(TypedDict):
    """A :class:`Placement` as the truth keeps it (metres, radians)."""

    kind: str
    y: float
    z: float
    yaw_rad: float
    platter_angle_rad: float
    error_y: float
    error_z: float
    error_yaw_rad: float
    geometry: JSONObject


@dataclass(frozen=True)
class Placement:
    """Where a fixture was put: its reference point (on its local X axis) at (0, y, z) in D,
    turned by ``yaw_rad`` about +X_D. ``error_*`` is the seeded placement error included."""

    fixture: str
    kind: str
    y: float
    z: float
    yaw_rad: float
    platter_angle_rad: float
    error_y: float
    error_z: float
    error_yaw_rad: float
    geometry: JSONObject

    def as_dict(self) -> PlacementRecord:
        """A JSON-ready mapping (metres, radians)."""
        return {
            "kind": self.kind,
            "y": self.y,
            "z": self.z,
            "yaw_rad": self.yaw_rad,
            "platter_angle_rad": self.platter_angle_rad,
            "error_y": self.error_y,
            "error_z": self.error_z,
            "error_yaw_rad": self.error_yaw_rad,
            "geometry": self.geometry,
        }


def _rotation_about(axis: FloatArray, angle: float) -> FloatArray:
    """3×3 rotation by ``angle`` (rad) about the unit vector ``axis`` (Rodrigues)."""
    k = np.asarray(axis, dtype=np.float64)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    out: FloatArray = np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)
    return out


def _tensor_scene(parts: list[o3d.geometry.TriangleMesh]) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    for mesh in parts:
        v, t = meshes.mesh_arrays(mesh)
        scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(v.astype(np.float32))),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(t.astype(np.uint32))),
        )
    return scene


@dataclass(frozen=True)
class _Hits:
    """What a batch of rays hit: ranges (M,) (inf where nothing), the cosine of each ray with
    the surface's normal (M,) (1 where nothing) and the mesh each hit (M,) (the order the
    scene's meshes were added in; −1 where nothing)."""

    range: FloatArray
    cosine: FloatArray
    mesh: NDArray[np.int64]


def _cast(scene: o3d.t.geometry.RaycastingScene, rays: NDArray[np.float32]) -> _Hits:
    """Cast (M, 6) rays (origin, unit direction) against ``scene``."""
    hit = scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)), nthreads=0)
    r = np.asarray(hit["t_hit"].numpy(), dtype=np.float64)
    normals = np.asarray(hit["primitive_normals"].numpy(), dtype=np.float64)
    cosine = np.abs(np.einsum("ij,ij->i", normals, rays[:, 3:].astype(np.float64)))
    found = np.isfinite(r)
    mesh = np.where(found, np.asarray(hit["geometry_ids"].numpy(), dtype=np.int64), -1)
    return _Hits(r, np.where(found, np.clip(cosine, 1e-6, 1.0), 1.0), mesh)


def _rays(origins: FloatArray, dirs: FloatArray) -> NDArray[np.float32]:
    rays = np.empty((len(dirs), 6), dtype=np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = dirs
    return rays


class SimulatedStation:
    """One simulated station for one run, shared by the ``sim`` lidar, turntable and encoder.

    ``recipe`` gives the fixtures, the station's encoder (ppr, direction) and the simulation
    models (``simulation:``; defaults when absent). ``seed``, ``range_m`` (m) and ``pitch_deg``
    override the recipe's ``simulation.seed`` and ``simulation.truth.range``/``pitch_deg`` (an
    override also replaces an explicit ``simulation.truth.H``). ``clock`` defaults to a fresh
    :class:`~calstation.clock.SimClock`; its time at construction is the station's time origin
    (platter at φ = 0, encoder count 0).
    """

    def __init__(
        self,
        recipe: LoadedRecipe,
        *,
        seed: int | None = None,
        range_m: float | None = None,
        pitch_deg: float | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.recipe: LoadedRecipe = recipe
        r: Recipe = recipe.recipe
        self.config: SimulationConfig = r.simulation or SimulationConfig()
        self.seed = int(self.config.seed if seed is None else seed)
        if self.seed < 0:
            raise SimulationError(f"seed must be a non-negative integer, got {self.seed}")
        self.clock: Clock = clock if clock is not None else SimClock()
        self._t0_ns = self.clock.now_ns()
        self.truth: Extrinsics = self._draw_truth(range_m, pitch_deg)
        self._setup_lidar()
        self._setup_turntable_and_encoder()
        self._setup_scenes()
        self.placements: dict[str, PlacementRecord] = {}
        self.current_fixture = "none"
        self._placement_count = 0
        self._noise_rng = np.random.default_rng(np.random.SeedSequence([self.seed, _STREAM_NOISE]))
        self.revision = 0
        """Bumped on every change of scene or motion (lets batched lines be invalidated)."""

    # --- set-up -----------------------------------------------------------------------------
    def _draw_truth(self, range_m: float | None, pitch_deg: float | None) -> Extrinsics:
        tc = self.config.truth
        if tc.H is not None and range_m is None and pitch_deg is None:
            try:
                H = Extrinsics.from_dict(tc.H)
            except FrameError as exc:
                raise SimulationError(f"simulation.truth.H: {exc}") from None
            self.range_m = float(np.linalg.norm(H.t))
            self.pitch_deg = -math.degrees(H.rz)
            return H
        self.range_m = float(tc.range if range_m is None else range_m)
        self.pitch_deg = float(tc.pitch_deg if pitch_deg is None else pitch_deg)
        if not (self.range_m > 0 and math.isfinite(self.range_m)):
            raise SimulationError(f"range must be a positive distance in metres, got {range_m}")
        if not 5.0 < self.pitch_deg < 85.0:
            raise SimulationError(f"pitch must lie between 5° and 85°, got {self.pitch_deg}°")
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, _STREAM_TRUTH]))
        u = rng.uniform(-1.0, 1.0, 4)
        return Extrinsics(
            tx=float(u[0] * tc.tx_max),
            ty=self.range_m,
            tz=float(u[1] * tc.tz_max),
            rx=0.0,
            ry=math.radians(float(u[2] * tc.ry_max_deg)),
            rz=math.radians(-self.pitch_deg + float(u[3] * tc.rz_max_deg)),
        )

    def _setup_lidar(self) -> None:
        lm = self.config.lidar
        n = lm.points_per_line
        fov = math.radians(lm.fov_deg)
        self.azimuths = np.linspace(-fov / 2, fov / 2, n)
        self.azimuths.flags.writeable = False
        self.line_period_ns = 1.0e9 / lm.line_rate_hz
        self.point_period_ns = 1.0e9 / (lm.line_rate_hz * n)
        # exactly LidarLine.point_times_ns's rounding, so recorded times are the simulated ones
        self._offsets_ns = np.round(np.arange(n) * self.point_period_ns).astype(np.int64)
        self.lidar_info = LidarInfo(
            vendor="calstation",
            model="simulated line scanner",
            serial=f"sim-{self.seed}",
            fov_rad=fov,
            points_per_line=n,
            line_rate_hz=lm.line_rate_hz,
            range_min_m=lm.range_min,
            range_max_m=lm.range_max,
            extra={
                "simulated": True,
                "range_noise_m": lm.range_noise,
                "dropout": lm.dropout,
                "mixed_pixel_prob": lm.mixed_pixel_prob,
                "beam_divergence_deg": lm.beam_divergence_deg,
            },
        )
        # rays in P: one origin (the lidar), one direction per azimuth (and per sub-beam)
        R = self.truth.R
        self._origin_P = -(R.T @ self.truth.t)
        half = 0.5 * math.radians(lm.beam_divergence_deg)

        def dirs(offset: float) -> FloatArray:
            a = self.azimuths + offset
            d_L = np.column_stack([np.sin(a), np.cos(a), np.zeros_like(a)])
            return np.asarray(d_L @ R, dtype=np.float64)  # rows Rᵀ·d_L

        self._dirs_P = (dirs(0.0), dirs(-half), dirs(+half))
        spread = np.linspace(-half, half, FOOTPRINT_BEAMS)
        self._footprint_dirs = tuple(dirs(float(a)) for a in spread)
        axis = self.config.sensor.axis
        tilt = np.array([0.0, math.cos(math.radians(axis.wobble_phase_deg)),
                         math.sin(math.radians(axis.wobble_phase_deg))])
        self._wobble = _rotation_about(tilt, math.radians(axis.wobble_deg))

    def _setup_turntable_and_encoder(self) -> None:
        tm = self.config.turntable
        enc = self.recipe.recipe.station.encoder
        self.motion = PlatterMotion(
            rpm_to_rad_s(tm.acceleration_rpm_s), tm.speed_ripple, tm.ripple_per_rev
        )
        self.ppr = enc.ppr
        self.counts_per_revolution = counts_per_revolution(enc.ppr)
        self.encoder_direction: int = enc.direction
        self.encoder_sample_period_ns = 1.0e9 / self.config.encoder.sample_rate_hz
        self.encoder_latency_ns = round(self.config.encoder.latency_s * 1e9)

    def _setup_scenes(self) -> None:
        fx = self.recipe.recipe.fixtures
        self._platter = meshes.platter_mesh(
            fx.platter, flatness=self.config.sensor.platter.flatness
        )
        self._scene_D = _tensor_scene([self._platter])
        bg = self.config.background
        self._background: list[o3d.geometry.TriangleMesh] = []
        if bg.enabled:
            big, depth, wall = 20.0, bg.floor_depth, bg.wall_distance
            floor = meshes.to_mesh(
                np.array(
                    [
                        [-depth, -big, -big],
                        [-depth, big, -big],
                        [-depth, big, big],
                        [-depth, -big, big],
                    ]
                ),
                np.array([[0, 1, 2], [0, 2, 3]]),
            )
            back = meshes.to_mesh(
                np.array(
                    [[-depth, wall, -big], [big, wall, -big], [big, wall, big], [-depth, wall, big]]
                ),
                np.array([[0, 1, 2], [0, 2, 3]]),
            )
            self._background = [floor, back]
            scene_P = _tensor_scene(self._background)
            origins = np.broadcast_to(self._origin_P, self._dirs_P[0].shape)
            # the background is static: its ranges per azimuth never change, cast them once
            self._bg = tuple(_cast(scene_P, _rays(origins, d)) for d in self._dirs_P)
        else:
            n = len(self.azimuths)
            none = _Hits(np.full(n, np.inf), np.ones(n), np.full(n, -1, dtype=np.int64))
            self._bg = (none, none, none)
        self._bg_ranges = tuple(h.range for h in self._bg)
        if bg.enabled and self.config.sensor.mixed_pixels == "footprint":
            self._footprint_bg = tuple(
                _cast(scene_P, _rays(origins, d)).range for d in self._footprint_dirs)
        else:
            self._footprint_bg = tuple(np.full(len(self.azimuths), np.inf)
                                       for _ in self._footprint_dirs)

    # --- time helpers -----------------------------------------------------------------------
    def _seconds(self, t_ns: NDArray[np.int64] | int) -> FloatArray:
        return np.asarray(np.asarray(t_ns, dtype=np.int64) - self._t0_ns, dtype=np.float64) * 1e-9

    @property
    def time_origin_ns(self) -> int:
        """Clock time (ns) at which the platter was at φ = 0 with encoder count 0."""
        return self._t0_ns

    # --- fixtures ---------------------------------------------------------------------------
    def _fixture_geometry(self, fixture: str) -> tuple[meshes.Geometry, str]:
        fx = self.recipe.recipe.fixtures
        if fixture in FIXTURE_NAMES:
            return getattr(fx, fixture), f"fixtures.{fixture}"
        if fixture.startswith("demo:"):
            try:
                i = int(fixture[5:])
                return fx.demo[i], f"fixtures.demo[{i}]"
            except (ValueError, IndexError):
                raise SimulationError(
                    f"no demo fixture {fixture!r}: the recipe has {len(fx.demo)} demo object(s) "
                    f"(demo:0 … demo:{len(fx.demo) - 1})"
                ) from None
        raise SimulationError(
            f"unknown fixture {fixture!r}; expected one of {', '.join(FIXTURE_NAMES)}, "
            f"'none' or 'demo:<index>'"
        )

    def place(self, fixture: str) -> None:
        """Put ``fixture`` on the platter (replacing whatever was there), as an operator would.

        ``fixture`` is ``"static_target"``, ``"spin_target"``, ``"qa_cube"``, ``"demo:<index>"``
        or ``"none"`` (clear the platter). The recipe's offset and yaw are where the operator
        aims in frame P at this moment (facing the lidar), plus a seeded placement error; the
        resulting pose in D (which turns with the platter) goes into :attr:`placements`.
        """
        if fixture == "none":
            self.current_fixture = "none"
            self._scene_D = _tensor_scene([self._platter])
            self.revision += 1
            return
        geom, field = self._fixture_geometry(fixture)
        local = meshes.fixture_mesh(geom, self.recipe, field)
        pe = self.config.placement
        rng = np.random.default_rng(
            np.random.SeedSequence([self.seed, _STREAM_PLACEMENT, self._placement_count])
        )
        self._placement_count += 1
        err = rng.normal(size=3) * np.array(
            [pe.position_sigma, pe.position_sigma, math.radians(pe.yaw_sigma_deg)]
        )
        oy, oz = geom.offset
        y_P, z_P = oy + float(err[0]), oz + float(err[1])
        yaw_P = math.radians(getattr(geom, "yaw_deg", 0.0)) + float(err[2])
        phi = self.platter_angle(self.clock.now_ns())
        c, s = math.cos(phi), math.sin(phi)
        y_D, z_D, yaw_D = c * y_P + s * z_P, -s * y_P + c * z_P, yaw_P - phi
        placed = meshes.place_mesh(local, y_D, z_D, yaw_D)
        self.placements[fixture] = Placement(
            fixture=fixture,
            kind=geom.kind,
            y=y_D,
            z=z_D,
            yaw_rad=yaw_D,
            platter_angle_rad=phi,
            error_y=float(err[0]),
            error_z=float(err[1]),
            error_yaw_rad=float(err[2]),
            geometry=geom.model_dump(mode="json"),
        ).as_dict()
        self.current_fixture = fixture
        self._scene_D = _tensor_scene([self._platter, placed])
        self.revision += 1

    def fixture_mesh_in_D(self) -> o3d.geometry.TriangleMesh | None:
        """The fixture now on the platter, placed, in frame D (None when the platter is bare)."""
        if self.current_fixture == "none":
            return None
        geom, field = self._fixture_geometry(self.current_fixture)
        p = self.placements[self.current_fixture]
        return meshes.place_mesh(
            meshes.fixture_mesh(geom, self.recipe, field), p["y"], p["z"], p["yaw_rad"]
        )

    def truth_dict(self) -> dict[str, object]:
        """Ground truth for ``truth.json`` and the recordings' ``"truth"`` metadata.

        Top level tx, ty, tz (m), rx, ry, rz (rad) (DESIGN §2), the lidar's ``range_offset``
        (m) and ``range_scale`` (DESIGN §9), ``sensor`` (every systematic error simulated,
        ``simulation.sensor``, and the warm-up drift at this moment), ``fixtures`` (pose in D
        of every fixture placed so far), ``fixture_on_platter``, ``seed``, ``scenario``
        (range_m, pitch_deg) and the encoder's simulated latency.
        """
        sensor = self.config.sensor
        return {
            **self.truth.as_dict(),
            # the lidar's true range model (DESIGN §9), beside the physical H
            "range_offset": sensor.range.offset,
            "range_scale": sensor.range.scale,
            "sensor": {
                **sensor.model_dump(mode="json"),
                "warmup_drift_now_m": float(self.warmup_drift(self.clock.now_ns())),
            },
            "fixtures": {k: dict(v) for k, v in self.placements.items()},
            "fixture_on_platter": self.current_fixture,
            "seed": self.seed,
            "scenario": {"range_m": self.range_m, "pitch_deg": self.pitch_deg},
            "encoder": {
                "latency_s": self.config.encoder.latency_s,
                "ppr": self.ppr,
                "direction": self.encoder_direction,
                "sample_rate_hz": self.config.encoder.sample_rate_hz,
            },
        }

    # --- turntable and encoder ------------------------------------------------------------
    def set_speed(self, rpm: float, t_ns: int, *, acceleration_rpm_s: float | None = None) -> int:
        """Command the platter to ``rpm`` (signed, + = right-handed about +X_P) at ``t_ns``.

        It ramps at the model's acceleration (or ``acceleration_rpm_s``); returns the time (ns)
        at which the new speed is reached.
        """
        acc = None if acceleration_rpm_s is None else rpm_to_rad_s(acceleration_rpm_s)
        end_s = self.motion.command(float(self._seconds(t_ns)), rpm_to_rad_s(rpm), acc)
        self.revision += 1
        return self._t0_ns + math.ceil(end_s * 1e9)

    def platter_angle(self, t_ns: int) -> float:
        """True platter angle φ (rad, unwrapped) at ``t_ns``."""
        return float(self.motion.angle(self._seconds(t_ns)))

    def platter_angles(self, t_ns: NDArray[np.int64]) -> FloatArray:
        """True φ (rad) at an array of times (ns)."""
        return self.motion.angle(self._seconds(t_ns))

    def platter_speed_rpm(self, t_ns: int) -> float:
        """True platter speed (rpm, ripple included) at ``t_ns``."""
        return float(self.motion.speed(self._seconds(t_ns))) * 60.0 / (2.0 * math.pi)

    def encoder_counts(self, t_ns: NDArray[np.int64]) -> NDArray[np.int64]:
        """Counts the encoder reports with timestamps ``t_ns``: the quantised angle at
        ``t_ns − latency``, ``floor(direction·φ·counts_per_rev/2π)`` (DESIGN §2)."""
        phi = self.platter_angles(np.asarray(t_ns, dtype=np.int64) - self.encoder_latency_ns)
        phi = phi + self._encoder_error(phi)
        x = self.encoder_direction * phi * (self.counts_per_revolution / (2.0 * math.pi))
        return np.floor(x + 1e-9).astype(np.int64)

    def _encoder_error(self, phi: FloatArray) -> FloatArray:
        """The encoder's angle error (rad) at true angles ``phi``: an eccentric code disc once
        per turn and its second harmonic (``simulation.sensor.encoder``)."""
        e = self.config.sensor.encoder
        out = np.zeros_like(phi)
        if e.eccentricity_deg:
            out += math.radians(e.eccentricity_deg) * np.sin(
                phi + math.radians(e.eccentricity_phase_deg))
        if e.second_harmonic_deg:
            out += math.radians(e.second_harmonic_deg) * np.sin(
                2.0 * phi + math.radians(e.second_harmonic_phase_deg))
        return out

    def encoder_count(self, t_ns: int) -> int:
        """The quantised count the encoder reports stamped ``t_ns`` (see :meth:`encoder_counts`)."""
        return int(self.encoder_counts(np.array([t_ns], dtype=np.int64))[0])

    # --- lidar ------------------------------------------------------------------------------
    def scan_line(self, t_ns: int) -> LidarLine:
        """One lidar line whose first point is measured at ``t_ns``."""
        return self.scan_lines(np.array([t_ns], dtype=np.int64))[0]

    def scan_lines(self, line_t_ns: NDArray[np.int64]) -> list[LidarLine]:
        """Lidar lines starting at each of ``line_t_ns`` (B,), ray-cast in one batch."""
        lm = self.config.lidar
        t_ns = np.asarray(line_t_ns, dtype=np.int64)[:, None] + self._offsets_ns[None, :]
        phi = self.platter_angles(t_ns)  # (B, N) per-point platter angle
        n_lines, n = phi.shape
        cols = np.broadcast_to(np.arange(n), (n_lines, n))
        dyn = self._cast_D(phi.ravel(), self._dirs_P[0], cols.ravel())
        bg = self._bg[0]
        bg_r = np.tile(bg.range, n_lines)
        nearer = dyn.range <= bg_r
        r = np.where(nearer, dyn.range, bg_r).reshape(n_lines, n)
        rng = self._noise_rng
        footprint = self.config.sensor.mixed_pixels == "footprint"
        if (lm.mixed_pixel_prob > 0 or footprint) and lm.beam_divergence_deg > 0:
            self._mix_pixels(r, phi, rng)
        hit = np.isfinite(r)
        r = self._systematic(r, t_ns, dyn, bg, nearer.reshape(n_lines, n))
        noisy = r + lm.range_noise * rng.standard_normal(r.shape) if lm.range_noise else r.copy()
        dropped = rng.random(r.shape) < lm.dropout if lm.dropout > 0 else np.zeros(r.shape, bool)
        noisy[~hit] = 0.0
        valid = hit & ~dropped & (noisy >= lm.range_min) & (noisy <= lm.range_max)
        return [
            LidarLine(
                timestamp_ns=int(line_t_ns[b]),
                azimuth_rad=self.azimuths,
                range_m=noisy[b],
                valid=valid[b],
                point_period_ns=self.point_period_ns,
            )
            for b in range(n_lines)
        ]

    def _systematic(
        self, r: FloatArray, t_ns: NDArray[np.int64], dyn: _Hits, bg: _Hits,
        nearer: NDArray[np.bool_],
    ) -> FloatArray:
        """The ranges ``r`` (B, N) as the lidar reports them before its noise (DESIGN §9):
        (1 + scale)·r + offset + the incidence bias + the surface's reflectivity bias + the
        warm-up drift at each return's time ``t_ns``. ``dyn``/``bg``: what the main beams hit
        in the platter's scene and in the background; ``nearer``: the platter's was nearer."""
        sensor = self.config.sensor
        rm, refl, warm = sensor.range, sensor.reflectivity, sensor.warmup
        if not (rm.offset or rm.scale or rm.incidence_bias or refl.bias or warm.drift):
            return r
        shape = r.shape
        flat_near = nearer.ravel()
        out = (1.0 + rm.scale) * r + rm.offset
        if rm.incidence_bias:
            cosine = np.where(flat_near, dyn.cosine, np.tile(bg.cosine, shape[0]))
            out = out + rm.incidence_bias * (1.0 / cosine - 1.0).reshape(shape)
        if refl.bias:
            fixture = self._surface_name()
            dyn_bias = np.where(dyn.mesh == 0, refl.range_bias("platter"),
                                refl.range_bias(fixture) if fixture else 0.0)
            bias = np.where(flat_near, dyn_bias, refl.range_bias("background"))
            out = out + bias.reshape(shape)
        if warm.drift:
            out = out + self.warmup_drift(t_ns)
        return np.asarray(out, dtype=np.float64)

    def _surface_name(self) -> str | None:
        """The reflectivity surface of the fixture on the platter (None when bare)."""
        if self.current_fixture == "none":
            return None
        return "demo" if self.current_fixture.startswith("demo:") else self.current_fixture

    def warmup_drift(self, t_ns: NDArray[np.int64] | int) -> FloatArray:
        """The warm-up drift (m) the lidar adds to its ranges at ``t_ns``."""
        w = self.config.sensor.warmup
        on = self._seconds(t_ns) + w.on_before_s
        return np.asarray(w.drift * (1.0 - np.exp(-np.maximum(on, 0.0) / w.time_constant_s)))

    def range_offset_at(self, t_ns: int) -> float:
        """The lidar's whole range offset (m) at ``t_ns``: its offset and its warm-up drift."""
        return float(self.config.sensor.range.offset + self.warmup_drift(t_ns))

    def _cast_D(self, phi: FloatArray, dirs_P: FloatArray, cols: NDArray[np.intp]) -> _Hits:
        """What the rays of azimuth columns ``cols`` at platter angles ``phi`` (M,) hit in the
        dynamic scene: origin and direction turned from P into D, Rx(φ)ᵀ, then by the axis
        wobble's tilt of the platter (:meth:`_unwobble`)."""
        c, s = np.cos(phi), np.sin(phi)
        o = self._origin_P
        d = dirs_P[cols]
        rays = np.empty((len(phi), 6), dtype=np.float32)
        rays[:, 0] = o[0]
        rays[:, 1] = c * o[1] + s * o[2]
        rays[:, 2] = -s * o[1] + c * o[2]
        rays[:, 3] = d[:, 0]
        rays[:, 4] = c * d[:, 1] + s * d[:, 2]
        rays[:, 5] = -s * d[:, 1] + c * d[:, 2]
        return _cast(self._scene_D, self._unwobble(rays))

    def _unwobble(self, rays: NDArray[np.float32]) -> NDArray[np.float32]:
        """Rays in D taken into the wobbling platter's own frame. A once-per-turn precession
        of the axis, locked to the platter, is a fixed tilt of the platter (and of what stands
        on it) in D: by ``wobble_deg`` about the horizontal direction ``wobble_phase_deg``
        from +Y_D."""
        axis = self.config.sensor.axis
        if axis.wobble_deg == 0.0:
            return rays
        W = self._wobble
        out = np.empty_like(rays)
        out[:, :3] = rays[:, :3] @ W  # rows Wᵀ·v
        out[:, 3:] = rays[:, 3:] @ W
        return out

    def _mix_pixels(self, r: FloatArray, phi: FloatArray, rng: np.random.Generator) -> None:
        """Mixed pixels, in place, where a point sits at a depth edge (its range differs from a
        neighbour's by more than :data:`MIXED_PIXEL_GAP_M`). ``sensor.mixed_pixels: random``:
        cast its two sub-beams (±divergence/2 in azimuth); if they disagree by more than the
        gap, with probability ``mixed_pixel_prob`` return a random blend of the two ranges.
        ``footprint``: the mean range over :data:`FOOTPRINT_BEAMS` sub-beams spread across the
        beam's divergence (the share of the footprint on each surface sets the blend)."""
        cmp = np.where(np.isfinite(r), r, _FAR)
        jump = np.abs(np.diff(cmp, axis=1)) > MIXED_PIXEL_GAP_M
        edge = np.zeros(r.shape, dtype=bool)
        edge[:, :-1] |= jump
        edge[:, 1:] |= jump
        rows, cols = np.nonzero(edge)
        if len(rows) == 0:
            return
        ph = phi[rows, cols]
        if self.config.sensor.mixed_pixels == "footprint":
            self._footprint_blend(r, rows, cols, ph)
            return
        ra = np.minimum(self._cast_D(ph, self._dirs_P[1], cols).range, self._bg_ranges[1][cols])
        rb = np.minimum(self._cast_D(ph, self._dirs_P[2], cols).range, self._bg_ranges[2][cols])
        u = rng.random(len(rows))
        w = rng.random(len(rows))
        with np.errstate(invalid="ignore"):  # two misses: inf − inf, not a mixed pixel
            gap = np.abs(ra - rb)
        mixed = (
            np.isfinite(ra)
            & np.isfinite(rb)
            & (gap > MIXED_PIXEL_GAP_M)
            & (u < self.config.lidar.mixed_pixel_prob)
        )
        r[rows[mixed], cols[mixed]] = ra[mixed] + w[mixed] * (rb[mixed] - ra[mixed])

    def _footprint_blend(
        self, r: FloatArray, rows: NDArray[np.intp], cols: NDArray[np.intp], ph: FloatArray
    ) -> None:
        """``sensor.mixed_pixels: footprint``: at the depth-edge returns (``rows``, ``cols``,
        platter angles ``ph``), the mean range of the footprint's sub-beams that hit."""
        total = np.zeros(len(rows))
        hits = np.zeros(len(rows))
        for dirs, bg in zip(self._footprint_dirs, self._footprint_bg, strict=True):
            sub = np.minimum(self._cast_D(ph, dirs, cols).range, bg[cols])
            found = np.isfinite(sub)
            total[found] += sub[found]
            hits[found] += 1
        blend = hits >= 1
        r[rows[blend], cols[blend]] = total[blend] / hits[blend]


def shared_station(
    context: DriverContext,
    *,
    clock: Clock | None = None,
    seed: int | None = None,
    range_m: float | None = None,
    pitch_deg: float | None = None,
) -> SimulatedStation:
    """The run's one :class:`SimulatedStation`, kept in ``context.shared["sim"]``.

    The first caller creates it from ``context.recipe`` with ``clock``, ``seed``, ``range_m`` (m)
    and ``pitch_deg`` (see :class:`SimulatedStation`); later callers get that same station and
    their arguments are ignored. The ``sim`` drivers and the in-process emulators of other
    plugins (``emulate: true``) all share it, so they see one scene and one platter.
    """
    existing = context.shared.get("sim")
    if isinstance(existing, SimulatedStation):
        return existing
    if context.recipe is None:
        raise SimulationError(
            "the simulated station (sim drivers, emulate: true) needs the run's recipe "
            "(DriverContext.recipe, its simulation section)"
        )
    station = SimulatedStation(
        context.recipe, seed=seed, range_m=range_m, pitch_deg=pitch_deg, clock=clock
    )
    context.shared["sim"] = station
    return station
