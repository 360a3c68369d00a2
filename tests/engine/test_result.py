"""The calibration result type: serialisation and exports."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calstation.engine.frames import Extrinsics
from calstation.engine.result import CalibrationResult
from calstation.errors import CalibrationError


def _result() -> CalibrationResult:
    return CalibrationResult(
        H=Extrinsics(0.01, 1.25, -0.004, 0.0, math.radians(0.2), math.radians(-45)),
        sigma={"tx": 1e-5, "ty": math.nan, "tz": 2e-5, "rx": math.nan, "ry": 1e-3, "rz": 2e-5},
        cost=3.5e-7,
        iterations=12,
        strategy="periodicity",
        timings={"total": 2.5},
        diagnostics={"matches_per_iteration": [10, 20], "arr": np.arange(3), "gauge": "platter"},
    )


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_save_load_round_trip(tmp_path, suffix: str) -> None:
    r = _result()
    path = tmp_path / f"calib{suffix}"
    r.save(path)
    back = CalibrationResult.load(path)
    np.testing.assert_allclose(back.H.as_vector(), r.H.as_vector(), rtol=0, atol=1e-15)
    assert back.strategy == "periodicity" and back.iterations == 12
    assert back.cost == pytest.approx(r.cost)
    assert math.isnan(back.sigma["ty"]) and back.sigma["tz"] == pytest.approx(2e-5)
    assert back.diagnostics["matches_per_iteration"] == [10, 20]
    assert back.diagnostics["arr"] == [0, 1, 2]


def test_json_is_strict_and_has_exports() -> None:
    d = json.loads(_result().to_json())  # NaN would not parse as strict JSON values
    assert d["sigma"]["ty"] is None
    T = np.array(d["T_L_P"])
    np.testing.assert_allclose(T[:3, 3], [0.01, 1.25, -0.004])
    q = np.array(d["quaternion_xyzw"])
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), T[:3, :3], atol=1e-12)


def test_exports_agree() -> None:
    r = _result()
    T = r.as_matrix()
    assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
    np.testing.assert_allclose(Rotation.from_quat(r.as_quaternion()).as_matrix(), r.H.R, atol=1e-12)
    assert r.urdf_origin().startswith('<origin xyz="0.01 1.25 -0.004"')
    s = r.summary()
    for key in ("tx", "ty", "tz", "rx", "ry", "rz", "sigma_tx", "sigma_rz", "strategy", "cost"):
        assert key in s
    assert s["sigma_ty"] is None


def test_load_errors_name_the_file(tmp_path) -> None:
    with pytest.raises(CalibrationError, match="not found"):
        CalibrationResult.load(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("strategy: x\n")
    with pytest.raises(CalibrationError, match=r"bad\.yaml.*missing 'H'"):
        CalibrationResult.load(bad)
    bad.write_text("H: {tx: a, ty: 0, tz: 0, ry: 0, rz: 0}\n")
    with pytest.raises(CalibrationError, match="numbers"):
        CalibrationResult.load(bad)
