"""ROS exports: tf, URDF and TransformStamped parsed back and checked against T_L_P, both ways."""

from __future__ import annotations

import datetime as dt
import re
import shlex
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import given, settings, strategies as st
from typer.testing import CliRunner

from calstation.cli import _build, app
from calstation.engine.frames import Extrinsics, euler_to_matrix, polar_to_lidar
from calstation.errors import CalstationError
from calstation.storage import ros
from calstation.storage.db import Calibration, Run, Station, open_database

H = Extrinsics(0.0123456789, 1.2498765432, -0.0004321098, 0.0, 0.0012345678, -0.7856781234)

angles = st.floats(-np.pi, np.pi, allow_nan=False)
metres = st.floats(-2.0, 2.0, allow_nan=False)
extrinsics = st.builds(
    Extrinsics, metres, metres, metres, angles, st.floats(-1.5, 1.5), angles
)


def _matrix(t: list[float], q_xyzw: list[float]) -> np.ndarray:
    return Extrinsics.from_quaternion(t, q_xyzw).as_matrix()


def _publishers(text: str) -> dict[tuple[str, str], np.ndarray]:
    """(parent, child) → 4×4 matrix of every ``static_transform_publisher`` line."""
    out = {}
    for line in text.splitlines():
        if not line.startswith("ros2 run tf2_ros static_transform_publisher "):
            continue
        words = shlex.split(line)[4:]
        args = dict(zip(words[::2], words[1::2], strict=True))
        t = [float(args[f"--{k}"]) for k in ("x", "y", "z")]
        q = [float(args[f"--q{k}"]) for k in ("x", "y", "z", "w")]
        out[(args["--frame-id"], args["--child-frame-id"])] = _matrix(t, q)
    return out


def _urdf_joints(
    text: str, links: tuple[str, ...] = ("lidar", "platform")
) -> dict[str, ET.Element]:
    """The joints of a complete URDF file (its root is ``<robot>``), which has ``links``."""
    root = ET.fromstring(text.encode("utf-8"))
    assert root.tag == "robot"
    assert {link.get("name") for link in root.iter("link")} == set(links)
    return {j.get("name") or "": j for j in root.iter("joint")}


def _origin(joint: ET.Element) -> np.ndarray:
    origin = joint.find("origin")
    assert origin is not None
    xyz = [float(v) for v in (origin.get("xyz") or "").split()]
    rpy = [float(v) for v in (origin.get("rpy") or "").split()]
    T = np.eye(4)
    T[:3, :3] = euler_to_matrix(*rpy)  # URDF: R = Rz(yaw)·Ry(pitch)·Rx(roll)
    T[:3, 3] = xyz
    return T


@settings(max_examples=40, deadline=None)
@given(extrinsics)
def test_tf_export_both_directions(h: Extrinsics) -> None:
    text = ros.tf_export(h, "test")
    assert "quaternion order: x y z w" in text
    tfs = _publishers(text)
    T = h.as_matrix()
    np.testing.assert_allclose(tfs[("lidar", "platform")], T, atol=1e-7)
    np.testing.assert_allclose(tfs[("platform", "lidar")], np.linalg.inv(T), atol=1e-7)
    np.testing.assert_allclose(tfs[("lidar", "platform")] @ tfs[("platform", "lidar")],
                               np.eye(4), atol=1e-7)


@settings(max_examples=40, deadline=None)
@given(extrinsics, st.sampled_from(["lidar", "platform"]))
def test_urdf_export_both_directions(h: Extrinsics, parent: str) -> None:
    text = ros.urdf_export(h, "test", parent=parent)
    assert "order x y z w" in text
    joints = _urdf_joints(text)
    child = "platform" if parent == "lidar" else "lidar"
    (joint,) = joints.values()
    assert joint.get("name") == f"{parent}_to_{child}"
    assert joint.get("type") == "fixed"
    assert joint.find("parent").get("link") == parent  # type: ignore[union-attr]
    assert joint.find("child").get("link") == child  # type: ignore[union-attr]
    want = h.as_matrix() if parent == "lidar" else np.linalg.inv(h.as_matrix())
    np.testing.assert_allclose(_origin(joint), want, atol=1e-7)
    # the fragment is the same links and joint without the <robot> root
    fragment = ros.urdf_export(h, "test", parent=parent, form="fragment")
    assert "<robot" not in fragment
    wrapped = _urdf_joints(f"<robot name='mine'>{fragment}</robot>")
    np.testing.assert_allclose(_origin(wrapped[f"{parent}_to_{child}"]), want, atol=1e-7)
    # the platter's continuous joint, in a comment, is valid URDF once uncommented
    (platter,) = re.findall(r"to add it: (.*) -->", text)
    with_platter = _urdf_joints(text.replace("</robot>", platter + "</robot>"),
                                ("lidar", "platform", "platter"))
    assert with_platter["platform_to_platter"].get("type") == "continuous"
    assert with_platter["platform_to_platter"].find("axis").get("xyz") == "1 0 0"  # type: ignore[union-attr]
    # the quaternion in the comment is the same rotation
    (q,) = re.findall(r"order x y z w \(scalar last, as ROS and scipy\): ([^>]*) -->", text)
    R = Extrinsics.from_quaternion([0, 0, 0], [float(v) for v in q.split()]).R
    np.testing.assert_allclose(R, want[:3, :3], atol=1e-7)


def _joint_matrix(origin_xyz: object, origin_rpy: object) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = euler_to_matrix(*[float(v) for v in origin_rpy])  # type: ignore[attr-defined]
    T[:3, 3] = [float(v) for v in origin_xyz]  # type: ignore[attr-defined]
    return T


@pytest.mark.parametrize("parent", ["lidar", "platform"])
def test_urdf_file_loads_in_urdf_parsers(tmp_path: Path, parent: str) -> None:
    """urdf_parser_py and yourdfpy load the exported file: 2 links, 1 joint equal to H."""
    from urdf_parser_py.urdf import URDF
    from yourdfpy import URDF as YURDF

    path = tmp_path / "station.urdf"
    path.write_text(ros.urdf_export(H, "test", parent=parent))
    want = H.as_matrix() if parent == "lidar" else np.linalg.inv(H.as_matrix())
    robot = URDF.from_xml_file(str(path))
    assert sorted(link.name for link in robot.links) == ["lidar", "platform"]
    (joint,) = robot.joints
    assert (joint.parent, joint.type) == (parent, "fixed")
    np.testing.assert_allclose(_joint_matrix(joint.origin.xyz, joint.origin.rpy), want,
                               atol=1e-8)
    model = YURDF.load(str(path))
    assert sorted(model.link_map) == ["lidar", "platform"]
    assert list(model.joint_map) == [joint.name]
    child = "platform" if parent == "lidar" else "lidar"
    np.testing.assert_allclose(model.get_transform(child, parent), want, atol=1e-8)


def test_xacro_macro_puts_h_between_your_links(tmp_path: Path) -> None:
    """The xacro form: a macro that joins two links of the user's robot by H."""
    import xacro
    from urdf_parser_py.urdf import URDF

    (tmp_path / "calstation.xacro").write_text(ros.urdf_export(H, "test", form="xacro"))
    (tmp_path / "robot.xacro").write_text(
        '<?xml version="1.0"?>\n<robot name="mine" xmlns:xacro="http://www.ros.org/wiki/xacro">'
        '<xacro:include filename="calstation.xacro"/><link name="laser"/><link name="table"/>'
        '<xacro:calstation_calibration parent="laser" child="table"/></robot>\n'
    )
    urdf = xacro.process_file(str(tmp_path / "robot.xacro")).toxml()
    robot = URDF.from_xml_string(urdf)
    (joint,) = robot.joints
    assert (joint.name, joint.parent, joint.child) == ("laser_to_table", "laser", "table")
    np.testing.assert_allclose(_joint_matrix(joint.origin.xyz, joint.origin.rpy),
                               H.as_matrix(), atol=1e-8)


@pytest.mark.parametrize("parent", ["lidar", "platform"])
def test_ros2_yaml_is_a_transform_stamped(parent: str) -> None:
    text = ros.ros2_yaml_export(H, "test", 1_767_225_600_123_456_789, parent=parent)
    assert "quaternion order: x y z w" in text
    msg = yaml.safe_load(text)
    assert msg["header"]["stamp"] == {"sec": 1_767_225_600, "nanosec": 123_456_789}
    assert (msg["header"]["frame_id"], msg["child_frame_id"]) == (
        (parent, "platform" if parent == "lidar" else "lidar")
    )
    tr, q = msg["transform"]["translation"], msg["transform"]["rotation"]
    T = _matrix([tr["x"], tr["y"], tr["z"]], [q["x"], q["y"], q["z"], q["w"]])
    want = H.as_matrix() if parent == "lidar" else np.linalg.inv(H.as_matrix())
    np.testing.assert_allclose(T, want, atol=1e-8)


def test_rep103_frames() -> None:
    """lidar_link has x along the boresight and its bearings turn the ROS way (θ = −α);
    turntable_link has z up the rotation axis."""
    tfs = {(t.parent, t.child): t.matrix() for t in ros.rep103_transforms()}
    T = tfs[("lidar", "lidar_link")]
    rho, alpha = 1.3, np.radians([-30.0, 0.0, 20.0])
    p_L = polar_to_lidar(np.full(3, rho), alpha)
    p_link = (np.linalg.inv(T) @ np.c_[p_L, np.ones(3)].T).T[:, :3]
    np.testing.assert_allclose(p_link[:, 0], rho * np.cos(-alpha), atol=1e-12)
    np.testing.assert_allclose(p_link[:, 1], rho * np.sin(-alpha), atol=1e-12)
    np.testing.assert_allclose(p_link[:, 2], 0.0, atol=1e-12)
    for parent, child in (("platform", "turntable_link"), ("platter", "platter_link")):
        R = tfs[(parent, child)][:3, :3]
        np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # z = +X_P, the axis
        assert np.isclose(np.linalg.det(R), 1.0)


def test_bad_parent_and_frames() -> None:
    with pytest.raises(CalstationError, match="parent must be 'lidar' or 'platform'"):
        ros.lidar_platform(H, parent="world")
    with pytest.raises(CalstationError, match="frame ids must differ"):
        ros.Frames("a", "a", "b")
    with pytest.raises(CalstationError, match="not a valid frame id"):
        ros.Frames("my lidar")


def _stored_run(tmp_path: Path, **calibration: Any) -> tuple[str, int]:
    """A database in ``tmp_path`` with one passed run whose accepted fine calibration is H
    (and ``calibration``'s fields): its URL and the run's id."""
    url = f"sqlite:///{tmp_path / 'ros.db'}"
    db = open_database(url)
    with db.session() as s:
        run = Run(station=Station(name="st-ros"), recipe_name="r", recipe_path="r.yaml",
                  recipe_text="name: r\n", recipe_sha256="ab" * 32, operator="qa",
                  unattended=True, data_dir=str(tmp_path), status="passed",
                  started_at=dt.datetime(2026, 3, 1, tzinfo=dt.UTC))
        s.add(run)
        s.flush()
        s.add(Calibration(run=run, stage="fine", **H.as_dict(), accepted=True,
                          created_at=dt.datetime(2026, 3, 1, 9, tzinfo=dt.UTC), **calibration))
        s.flush()
        run_id = run.id
    db.dispose()
    return url, run_id


def _exporter(url: str, run_id: int) -> Callable[..., str]:
    """``calstation export RUN`` of the stored run with more arguments: its output (exit 0)."""
    _build()
    runner = CliRunner()

    def export(*args: str) -> str:
        res = runner.invoke(app, ["export", str(run_id), "--db", url, *args])
        assert res.exit_code == 0, res.output
        return res.output

    return export


def test_export_cli_formats(tmp_path: Path) -> None:
    """``calstation export --format tf|urdf|ros2-yaml`` on a stored run, with frame names."""
    url, run_id = _stored_run(tmp_path, strategy="periodicity")
    export = _exporter(url, run_id)
    runner = CliRunner()

    tfs = _publishers(export("--format", "tf", "--lidar-frame", "laser",
                             "--platform-frame", "turntable"))
    np.testing.assert_allclose(tfs[("laser", "turntable")], H.as_matrix(), atol=1e-8)
    np.testing.assert_allclose(tfs[("turntable", "laser")], np.linalg.inv(H.as_matrix()),
                               atol=1e-8)
    joint = _urdf_joints(export("--format", "urdf", "--parent", "platform"))["platform_to_lidar"]
    np.testing.assert_allclose(_origin(joint), np.linalg.inv(H.as_matrix()), atol=1e-8)
    out = tmp_path / "station.urdf"
    export("--format", "urdf", "-o", str(out))
    from urdf_parser_py.urdf import URDF

    assert len(URDF.from_xml_file(str(out)).links) == 2  # -o writes a file URDF tools load
    fragment = export("--format", "urdf", "--fragment")
    assert "<robot" not in fragment and '<joint name="lidar_to_platform"' in fragment
    assert "xacro:macro" in export("--format", "xacro")
    res = runner.invoke(app, ["export", str(run_id), "--db", url, "--format", "tf",
                              "--fragment"])
    assert res.exit_code == 2 and "a fragment is a URDF form" in res.output
    msg = yaml.safe_load(export("--format", "ros2-yaml"))
    assert msg["header"]["stamp"]["sec"] == int(
        dt.datetime(2026, 3, 1, 9, tzinfo=dt.UTC).timestamp()
    )
    assert "qx,qy,qz,qw" in export("--format", "csv").splitlines()[0]
    res = runner.invoke(app, ["export", str(run_id), "--db", url, "--format", "urdf",
                              "--parent", "world"])
    assert res.exit_code == 2 and "parent must be 'lidar' or 'platform'" in res.output


def test_export_carries_the_lidars_range_model(tmp_path: Path) -> None:
    """A calibration with the lidar's range model: ``ros2-params`` gives the transform, the
    range terms estimated and the time offset as ROS 2 parameters (one not estimated left out,
    named in a comment); yaml carries them as fields; tf says how to correct a range."""
    url, run_id = _stored_run(
        tmp_path, strategy="periodicity+cube", range_offset=0.0031, sigma_range_offset=0.0001,
        incidence_bias=0.0004, sigma_incidence_bias=0.00005, encoder_latency_s=0.005,
        sigma_encoder_latency_s=1e-5)
    export = _exporter(url, run_id)

    text = export("--format", "ros2-params")
    params = yaml.safe_load(text)["/**"]["ros__parameters"]["calstation"]
    assert (params["frame_id"], params["child_frame_id"]) == ("lidar", "platform")
    np.testing.assert_allclose(_matrix(params["translation"], params["rotation_xyzw"]),
                               H.as_matrix(), atol=1e-8)
    assert params["range_offset"] == 0.0031 and params["sigma_range_offset"] == 0.0001
    assert params["incidence_bias"] == 0.0004 and params["encoder_latency_s"] == 0.005
    assert "range_scale" not in params and "# range_scale: not estimated" in text
    assert yaml.safe_load(export("--format", "yaml"))["range_offset"] == 0.0031
    tf = export("--format", "tf")
    assert "lidar range offset +3.100 ± 0.100 mm, incidence bias +0.400 ± 0.050 mm at 60°" in tf
    assert "rho = (rho_measured - b) / (1 + k) with b = 0.0031 m" in tf
