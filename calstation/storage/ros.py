"""The calibration in ROS terms: frame names, REP-103 axes, tf, URDF and TransformStamped exports.

calstation's frames (DESIGN §2) are right-handed and in metres and radians, so they are valid
REP-103 frames as they are; only their axes differ from the REP-103 body convention (x forward,
y left, z up). ``docs/frames.md`` explains the mapping; here:

- ``lidar`` = L, ``platform`` = P, ``platter`` = D (the frame ids of the recordings);
- ``lidar_link``: L turned so that x is the boresight (+Y_L) and z the scan-plane normal (+Z_L),
  as a ROS ``sensor_msgs/LaserScan`` frame expects (bearing = −α);
- ``turntable_link`` / ``platter_link``: P / D turned so that z is the rotation axis (+X_P, up),
  x = +Y_P and y = +Z_P.

Every export states its quaternion order: (x, y, z, w), scalar last, as ROS and scipy use.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from calstation.engine.frames import Extrinsics, FloatArray
from calstation.errors import CalstationError

QUATERNION_ORDER = "x y z w (scalar last, as ROS and scipy)"

R_L_LIDAR_LINK: FloatArray = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""Rotation of ``lidar_link`` in L: its x = +Y_L (boresight), y = −X_L, z = +Z_L."""
R_P_TURNTABLE_LINK: FloatArray = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
"""Rotation of ``turntable_link`` in P (and of ``platter_link`` in D): x = +Y_P, y = +Z_P,
z = +X_P (the rotation axis, up)."""


_FRAME_ID = re.compile(r"[A-Za-z/][A-Za-z0-9_/\-]*")


@dataclass(frozen=True)
class Frames:
    """The frame ids an export uses for L, P and D."""

    lidar: str = "lidar"
    platform: str = "platform"
    platter: str = "platter"

    def __post_init__(self) -> None:
        names = (self.lidar, self.platform, self.platter)
        for name in names:
            if not _FRAME_ID.fullmatch(name):
                raise CalstationError(
                    f"{name!r} is not a valid frame id (letters, digits, _, / and -, "
                    "starting with a letter or /)"
                )
        if len(set(names)) != 3:
            raise CalstationError(f"the frame ids must differ, got {', '.join(names)}")


@dataclass(frozen=True)
class Transform:
    """The pose of ``child`` in ``parent``: translation (m) and unit quaternion (x, y, z, w)."""

    parent: str
    child: str
    translation: FloatArray
    quaternion_xyzw: FloatArray
    rpy: tuple[float, float, float]
    """Fixed-axis roll, pitch, yaw (rad): R = Rz(yaw)·Ry(pitch)·Rx(roll), as URDF's ``rpy``."""

    def matrix(self) -> FloatArray:
        """The 4×4 homogeneous transform (child points → parent)."""
        return Extrinsics.from_quaternion(self.translation, self.quaternion_xyzw).as_matrix()


def _transform(parent: str, child: str, T: FloatArray) -> Transform:
    e = Extrinsics.from_matrix(T)
    return Transform(parent, child, e.t, e.as_quaternion(), (e.rx, e.ry, e.rz))


def lidar_platform(H: Extrinsics, frames: Frames = Frames(), parent: str = "lidar") -> Transform:
    """H as a transform: ``parent="lidar"`` gives the pose of P in L (T_L_P),
    ``parent="platform"`` its inverse, the pose of L in P (T_P_L)."""
    T = H.as_matrix()
    if parent == "lidar":  # H itself, exactly as stored
        return Transform(
            frames.lidar, frames.platform, H.t, H.as_quaternion(), (H.rx, H.ry, H.rz)
        )
    if parent == "platform":
        return _transform(frames.platform, frames.lidar, np.asarray(np.linalg.inv(T), np.float64))
    raise CalstationError(f"parent must be 'lidar' or 'platform', got {parent!r}")


def rep103_transforms(frames: Frames = Frames()) -> list[Transform]:
    """The fixed transforms from calstation's frames to their REP-103 aligned twins."""
    out = []
    for parent, child, R in (
        (frames.lidar, "lidar_link", R_L_LIDAR_LINK),
        (frames.platform, "turntable_link", R_P_TURNTABLE_LINK),
        (frames.platter, "platter_link", R_P_TURNTABLE_LINK),
    ):
        T = np.eye(4)
        T[:3, :3] = R
        out.append(_transform(parent, child, T))
    return out


def _num(x: float) -> str:
    return f"{float(x):.9g}"


def _publisher(tf: Transform) -> str:
    x, y, z = (_num(v) for v in tf.translation)
    qx, qy, qz, qw = (_num(v) for v in tf.quaternion_xyzw)
    return (
        f"ros2 run tf2_ros static_transform_publisher --x {x} --y {y} --z {z} "
        f"--qx {qx} --qy {qy} --qz {qz} --qw {qw} "
        f"--frame-id {tf.parent} --child-frame-id {tf.child}"
    )


def tf_export(H: Extrinsics, title: str, frames: Frames = Frames()) -> str:
    """``static_transform_publisher`` command lines for both directions (and the fixed REP-103
    frames), each with its meaning in a comment; ``title`` names the calibration."""
    forward = lidar_platform(H, frames, "lidar")
    backward = lidar_platform(H, frames, "platform")
    lines = [
        f"# {title}",
        f"# quaternion order: {QUATERNION_ORDER}; translations in metres",
        f"# T_L_P: pose of {forward.child} (P) in {forward.parent} (L); use this one when the "
        "lidar is the parent in your tf tree",
        _publisher(forward),
        f"# T_P_L, the inverse: pose of {backward.child} (L) in {backward.parent} (P); use this "
        "one when the turntable is the parent",
        _publisher(backward),
        "# ROS 1: rosrun tf2_ros static_transform_publisher x y z qx qy qz qw frame_id "
        "child_frame_id (same numbers)",
        "# optional REP-103 aligned frames (x forward, z up), fixed: see docs/frames.md",
    ]
    lines += [_publisher(t) for t in rep103_transforms(frames)]
    return "\n".join(lines) + "\n"


URDF_FORMS = ("robot", "fragment", "xacro")
"""What :func:`urdf_export` writes: a whole ``<robot>`` file, the elements to paste inside one,
or a xacro macro."""


def _urdf_joint(tf: Transform, indent: str, names: tuple[str, str] | None = None) -> list[str]:
    """The fixed ``<joint>`` of ``tf`` (``names`` replaces its parent and child link names,
    e.g. by xacro parameters)."""
    parent, child = names or (tf.parent, tf.child)
    x, y, z = (_num(v) for v in tf.translation)
    r, p, yw = (_num(v) for v in tf.rpy)
    return [
        f'{indent}<joint name="{parent}_to_{child}" type="fixed">',
        f'{indent}  <parent link="{parent}"/>',
        f'{indent}  <child link="{child}"/>',
        f'{indent}  <origin xyz="{x} {y} {z}" rpy="{r} {p} {yw}"/>',
        f"{indent}</joint>",
    ]


def _urdf_comments(tf: Transform, title: str, frames: Frames) -> list[str]:
    q = " ".join(_num(v) for v in tf.quaternion_xyzw)
    return [
        f"<!-- {title} -->",
        f"<!-- joint origin: pose of {tf.child} in {tf.parent}; rpy = fixed-axis roll, pitch, "
        "yaw (R = Rz(yaw)·Ry(pitch)·Rx(roll)); the same rotation as a quaternion, order "
        f"{QUATERNION_ORDER}: {q} -->",
        f"<!-- the platter turns about +X of {frames.platform} by the encoder angle; to add it: "
        f'<link name="{frames.platter}"/> <joint name="{frames.platform}_to_{frames.platter}" '
        f'type="continuous"> <parent link="{frames.platform}"/> <child link="{frames.platter}"/> '
        '<origin xyz="0 0 0" rpy="0 0 0"/> <axis xyz="1 0 0"/> </joint> -->',
    ]


def urdf_export(
    H: Extrinsics,
    title: str,
    frames: Frames = Frames(),
    parent: str = "lidar",
    form: str = "robot",
) -> str:
    """The calibration in URDF: the two links (L and P) and the fixed ``<joint>`` between them,
    ``parent`` (``lidar`` or ``platform``) its parent. ``form`` (:data:`URDF_FORMS`):
    ``robot``, a complete file (``<robot>`` root) that URDF parsers load; ``fragment``, the
    links and the joint to paste inside your own ``<robot>``; ``xacro``, a macro
    ``calstation_calibration`` that adds the joint between two links you name
    (``parent:=… child:=…``). A comment gives the platter's continuous joint."""
    tf = lidar_platform(H, frames, parent)
    head = _urdf_comments(tf, title, frames)
    links = [f'<link name="{frames.lidar}"/>', f'<link name="{frames.platform}"/>']
    if form == "fragment":
        return "\n".join([*head, *links, *_urdf_joint(tf, "")]) + "\n"
    if form == "robot":
        body = [
            '<?xml version="1.0"?>',
            *head,
            '<robot name="calstation">',
            *(f"  {link}" for link in links),
            *_urdf_joint(tf, "  "),
            "</robot>",
        ]
        return "\n".join(body) + "\n"
    if form == "xacro":
        body = [
            '<?xml version="1.0"?>',
            *head,
            "<!-- use: <xacro:include filename=\"THIS FILE\"/> then "
            f'<xacro:calstation_calibration parent="{tf.parent}" child="{tf.child}"/>, '
            "with your own link names; the links themselves are yours -->",
            '<robot xmlns:xacro="http://www.ros.org/wiki/xacro">',
            f'  <xacro:macro name="calstation_calibration" '
            f'params="parent:={tf.parent} child:={tf.child}">',
            *_urdf_joint(tf, "    ", ("${parent}", "${child}")),
            "  </xacro:macro>",
            "</robot>",
        ]
        return "\n".join(body) + "\n"
    raise CalstationError(f"URDF form must be one of {', '.join(URDF_FORMS)}, got {form!r}")


def ros2_yaml_export(
    H: Extrinsics,
    title: str,
    stamp_ns: int,
    frames: Frames = Frames(),
    parent: str = "lidar",
) -> str:
    """A ``geometry_msgs/msg/TransformStamped`` in YAML (as ``ros2 topic pub`` takes it)."""
    tf = lidar_platform(H, frames, parent)
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    tx, ty, tz = (_num(v) for v in tf.translation)
    qx, qy, qz, qw = (_num(v) for v in tf.quaternion_xyzw)
    return (
        f"# {title}\n"
        "# geometry_msgs/msg/TransformStamped: pose of child_frame_id in header.frame_id;\n"
        f"# quaternion order: {QUATERNION_ORDER}; translation in metres\n"
        "header:\n"
        f"  stamp: {{sec: {sec}, nanosec: {nanosec}}}\n"
        f"  frame_id: {tf.parent}\n"
        f"child_frame_id: {tf.child}\n"
        "transform:\n"
        f"  translation: {{x: {tx}, y: {ty}, z: {tz}}}\n"
        f"  rotation: {{x: {qx}, y: {qy}, z: {qz}, w: {qw}}}\n"
    )


def range_note(fields: Mapping[str, float | None]) -> str:
    """One sentence of the lidar's range model (DESIGN §9; a calibration's range fields) for
    the exports that carry it as a comment: its values with their σ, and how to correct a range
    before using the transform."""
    from calstation.engine.rangemodel import describe

    offset, scale = fields.get("range_offset") or 0.0, fields.get("range_scale") or 0.0
    return (f"lidar {describe(fields) or 'range model not estimated'}: this transform holds "
            "for ranges corrected as rho = (rho_measured - b) / (1 + k) with b = "
            f"{float(offset):.9g} m, k = {float(scale):.9g}")


def ros2_params_export(
    H: Extrinsics,
    title: str,
    frames: Frames = Frames(),
    parent: str = "lidar",
    ranges: Mapping[str, float | None] | None = None,
    encoder_latency_s: float | None = None,
) -> str:
    """A ROS 2 parameter file (``--params-file``) for any node, ``/**``: the transform (pose of
    the child frame in the parent), the lidar's range model (metres, dimensionless) and the
    lidar–encoder time offset (s). A value not estimated is left out (ROS 2 parameters cannot be
    null), named in a comment."""
    tf = lidar_platform(H, frames, parent)
    tx, ty, tz = (_num(v) for v in tf.translation)
    q = ", ".join(_num(v) for v in tf.quaternion_xyzw)

    lines = [
        f"# {title}",
        f"# translation in metres; rotation as a quaternion, order {QUATERNION_ORDER}; the range",
        "# model of DESIGN §9: rho = (rho_measured - range_offset) / (1 + range_scale)",
        "/**:",
        "  ros__parameters:",
        "    calstation:",
        f"      frame_id: {tf.parent}",
        f"      child_frame_id: {tf.child}",
        f"      translation: [{tx}, {ty}, {tz}]",
        f"      rotation_xyzw: [{q}]",
    ]
    values = {**(ranges or {}), "encoder_latency_s": encoder_latency_s}
    for name, v in values.items():
        lines.append(f"      # {name}: not estimated" if v is None
                     else f"      {name}: {_num(float(v))}")
    return "\n".join(lines) + "\n"
