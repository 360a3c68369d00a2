"""Initial calibration from the static L-target scan (paper §III-A, DESIGN §3)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calstation.engine.frames import Extrinsics, lidar_to_polar, platform_to_lidar
from calstation.engine.initial import initial_calibration, initial_from_returns
from calstation.errors import InitialCalibrationError
from calstation.recipes import InitialSettings, LTargetGeometry, load_recipe
from calstation.recordings.reader import read_recording

TARGET = LTargetGeometry()


def _static_scan(H: Extrinsics, target: LTargetGeometry = TARGET, lines: int = 100, seed: int = 0):
    """Returns of a static scan of the L-target cut by the scan plane (ry = 0: z_P = −tz)."""
    z = -H.tz - target.offset[1]
    bt, L = target.base_thickness, target.base_length
    h = target.h_mid - (target.h_tall - target.h_short) * z / target.width
    step = 0.0005
    platter = np.column_stack([np.zeros(200), np.linspace(-0.29, -L - 0.01, 200), np.full(200, z)])
    base_y = np.arange(-L, 0.0, step)
    base = np.column_stack([np.full(base_y.size, bt), base_y, np.full(base_y.size, z)])
    wall_x = np.arange(bt, bt + h, step)
    wall = np.column_stack([wall_x, np.zeros(wall_x.size), np.full(wall_x.size, z)])
    p_P = np.vstack([platter, base, wall])
    p_P[:, 1] += target.offset[0]
    p_P[:, 2] += target.offset[1]
    rng_m, az = lidar_to_polar(platform_to_lidar(p_P, H))
    gen = np.random.default_rng(seed)
    az_all = np.tile(az, lines)
    rng_all = np.tile(rng_m, lines) + gen.normal(0.0, 0.001, az_all.size)
    return az_all, rng_all


@pytest.mark.parametrize(
    ("pitch_deg", "tz", "offset"),
    [(30.0, 0.0, (0.0, 0.0)), (45.0, 0.012, (0.0, 0.0)), (60.0, -0.01, (0.004, -0.003))],
)
def test_recovers_H_from_a_synthetic_scan(
    pitch_deg: float, tz: float, offset: tuple[float, float]
) -> None:
    H = Extrinsics(tx=0.01, ty=1.2, tz=tz, rz=math.radians(-pitch_deg))
    target = TARGET.model_copy(update={"offset": offset})
    az, rng = _static_scan(H, target)
    res = initial_from_returns(az, rng, None, target)
    assert res.strategy == "initial"
    assert res.H.tx == pytest.approx(H.tx, abs=5e-4)
    assert res.H.ty == pytest.approx(H.ty, abs=5e-4)
    assert res.H.tz == pytest.approx(H.tz, abs=2e-3)
    assert math.degrees(res.H.rz - H.rz) == pytest.approx(0.0, abs=0.05)
    assert res.H.ry == 0.0 and res.H.rx == 0.0
    assert math.isnan(res.sigma["ry"]) and res.sigma["tx"] > 0
    assert res.diagnostics["base_length_m"] == pytest.approx(TARGET.base_length, abs=0.003)


def test_empty_scan_is_a_clear_error() -> None:
    with pytest.raises(InitialCalibrationError, match="empty"):
        initial_from_returns(np.zeros(0), np.zeros(0), None, TARGET)


def test_no_target_lists_what_was_seen() -> None:
    # only the platter: one straight segment
    H = Extrinsics(ty=1.25, rz=math.radians(-45))
    p_P = np.column_stack([np.zeros(400), np.linspace(-0.29, 0.29, 400), np.zeros(400)])
    rng_m, az = lidar_to_polar(platform_to_lidar(p_P, H))
    with pytest.raises(InitialCalibrationError) as err:
        initial_from_returns(np.tile(az, 10), np.tile(rng_m, 10), None, TARGET)
    msg = str(err.value)
    assert "L-target not found" in msg and "1 segments" in msg and "150 mm" in msg


def test_wrong_recipe_geometry_is_a_clear_error() -> None:
    H = Extrinsics(ty=1.25, rz=math.radians(-45))
    az, rng = _static_scan(H)
    wrong = TARGET.model_copy(update={"base_length": 0.3})
    with pytest.raises(InitialCalibrationError) as err:
        initial_from_returns(az, rng, None, wrong, InitialSettings())
    assert "does not match 300 mm" in str(err.value)


def test_simulated_static_scan_within_set_a_of_truth(sim_run) -> None:
    run = sim_run()
    recipe = load_recipe("recipes/sim-periodicity.yaml").recipe
    rec = read_recording(run["static"])
    res = initial_calibration(rec, recipe.fixtures.static_target, recipe.calibration.initial)
    truth = rec.truth or Extrinsics()
    err = res.H.as_vector() - truth.as_vector()
    assert np.all(np.abs(err[:3]) < 0.1)
    assert np.all(np.abs(np.degrees(err[3:])) < 1.0)
    # and much better than set A in practice: a few mm, a few hundredths of a degree in rz
    assert np.all(np.abs(err[:3]) < 0.01)
    assert abs(math.degrees(err[5])) < 0.2


def test_empty_recording_is_a_clear_error(tmp_path) -> None:
    from calstation.drivers import LidarInfo, LidarLine
    from calstation.errors import CalstationError
    from calstation.recordings.writer import RecordingWriter

    info = LidarInfo("sim", "line", "0", math.radians(72), 100, 1000.0, 0.2, 10.0)
    kw = {"kind": "static", "lidar_info": info, "counts_per_revolution": 4096}
    empty = tmp_path / "empty.mcap"
    with RecordingWriter(empty, encoder_direction=1, **kw):
        pass
    with pytest.raises(CalstationError, match=r"empty\.mcap"):
        initial_calibration(read_recording(empty), TARGET)
    # lines whose returns are all invalid (nothing in front of the lidar)
    dark = tmp_path / "dark.mcap"
    az = np.radians(np.linspace(-36, 36, 100))
    with RecordingWriter(dark, encoder_direction=1, **kw) as w:
        for i in range(5):
            w.write_line(
                LidarLine(
                    timestamp_ns=1_000_000 * (i + 1),
                    azimuth_rad=az,
                    range_m=np.zeros(100),
                    valid=np.zeros(100, dtype=bool),
                    point_period_ns=1000.0,
                )
            )
    with pytest.raises(InitialCalibrationError, match=r"dark\.mcap.*(no returns|empty)"):
        initial_calibration(read_recording(dark), TARGET)
