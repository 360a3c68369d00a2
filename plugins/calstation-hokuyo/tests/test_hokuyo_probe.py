"""``calstation probe`` against the emulators (the operator's manual preflight)."""

from __future__ import annotations

import json
import math

import pytest
from calstation_hokuyo import ScipSensor, TcpServer, WallScene

from calstation.cli import main


def test_probe_lidar_json_is_exactly_info_and_scan(capsys: pytest.CaptureFixture[str]) -> None:
    with TcpServer(ScipSensor(WallScene(2.0))) as server:
        with pytest.raises(SystemExit) as exit_info:
            main(["probe", "lidar", "--driver", "hokuyo", "--port", server.url, "--json"])
        assert exit_info.value.code in (0, None)
    out = json.loads(capsys.readouterr().out)
    assert list(out) == ["info", "scan"]
    assert list(out["scan"]) == ["timestamp_ns", "azimuth_rad", "range_m"]
    assert out["info"]["points_per_line"] == 1001
    az, rng = out["scan"]["azimuth_rad"], out["scan"]["range_m"]
    assert len(az) == len(rng) == 1001
    assert math.degrees(max(az)) == pytest.approx(36.0)
    for a, r in zip(az, rng, strict=True):
        assert r == pytest.approx(2.0 / math.cos(a), abs=0.0011)


def test_probe_of_a_dead_port_is_a_clean_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["probe", "lidar", "--driver", "hokuyo", "--port", "socket://127.0.0.1:1"])
    assert exit_info.value.code == 2
    assert "cannot open socket://127.0.0.1:1" in capsys.readouterr().err
