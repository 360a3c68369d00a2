"""Draw docs/frames.svg: calstation's frames L, P, D and their REP-103 aligned twins.

The station of DESIGN §2's example: the lidar 1.0 m from the platter centre, looking down at
45°, its scan plane through the rotation axis (t = (0, 1, 0), rz = −45°). Everything is drawn
in the turntable's REP-103 frame (z up), so the platter lies flat.

    .venv/bin/python scripts/frames_figure.py [--out docs/frames.svg]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from calstation.engine.frames import Extrinsics
from calstation.storage import ros

H = Extrinsics(ty=1.0, rz=np.radians(-45.0))
PLATTER_RADIUS = 0.2925
AXIS = 0.25
COLOURS = ("tab:red", "tab:green", "tab:blue")


def _to_view(T_P_x: np.ndarray) -> np.ndarray:
    """A pose in P → the same pose in the drawing frame (turntable_link, z up)."""
    T = np.eye(4)
    T[:3, :3] = ros.R_P_TURNTABLE_LINK
    return np.linalg.inv(T) @ T_P_x


def _axes(ax: plt.Axes, T: np.ndarray, names: tuple[str, str, str], style: str = "-") -> None:
    o = T[:3, 3]
    for i, (name, colour) in enumerate(zip(names, COLOURS, strict=True)):
        d = T[:3, i] * AXIS
        ax.plot(*zip(o, o + d, strict=True), style, color=colour, lw=2)
        ax.text(*(o + 1.15 * d), name, color=colour, fontsize=8, ha="center")


def _scene(ax: plt.Axes, T_P_L: np.ndarray) -> None:
    a = np.linspace(0, 2 * np.pi, 100)
    ax.plot(PLATTER_RADIUS * np.cos(a), PLATTER_RADIUS * np.sin(a), 0 * a, color="0.5")
    ax.text(0.0, -PLATTER_RADIUS, -0.08, "platter", color="0.4", fontsize=8)
    ax.plot([0, 0], [0, 0], [-0.05, 0.45], ":", color="0.4")  # the rotation axis
    # the scan plane: a fan of ±36° in L's z = 0 plane, 1.3 m long
    fan = np.radians(np.linspace(-36, 36, 9))
    T_view_L = _to_view(T_P_L)
    o = T_view_L[:3, 3]
    for alpha in (fan[0], 0.0, fan[-1]):
        p_L = np.array([1.3 * np.sin(alpha), 1.3 * np.cos(alpha), 0.0, 1.0])
        p = (T_view_L @ p_L)[:3]
        ax.plot(*zip(o, p, strict=True), "--", color="0.7", lw=0.8)
    ax.text(*(o + np.array([0.0, 0.0, 0.08])), "lidar", fontsize=9)


def _finish(ax: plt.Axes, title: str) -> None:
    ax.set_title(title, fontsize=10)
    ax.set_xlim(-0.6, 0.6)
    ax.set_ylim(-1.0, 0.3)
    ax.set_zlim(-0.3, 0.9)
    ax.set_box_aspect((1.2, 1.3, 1.2))
    ax.view_init(elev=18, azim=-35)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_zticks([])


def main() -> None:
    """Draw the figure."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("docs/frames.svg"))
    args = ap.parse_args()
    plt.switch_backend("Agg")
    plt.rcParams["svg.hashsalt"] = "calstation"  # the same SVG on every run
    T_P_L = np.linalg.inv(H.as_matrix())
    rep = {(t.parent, t.child): t.matrix() for t in ros.rep103_transforms()}
    fig = plt.figure(figsize=(10, 5))
    left = fig.add_subplot(1, 2, 1, projection="3d")
    _scene(left, T_P_L)
    _axes(left, _to_view(T_P_L), ("X_L", "Y_L (boresight)", "Z_L"))
    _axes(left, _to_view(np.eye(4)), ("X_P (axis, up)", "Y_P", "Z_P"))
    _finish(left, "calstation: L (lidar), P (platform)\nD turns with the platter about X_P")
    right = fig.add_subplot(1, 2, 2, projection="3d")
    _scene(right, T_P_L)
    _axes(right, _to_view(T_P_L @ rep[("lidar", "lidar_link")]), ("x (boresight)", "y", "z"))
    _axes(right, _to_view(rep[("platform", "turntable_link")]), ("x", "y", "z (axis, up)"))
    _finish(
        right, "REP-103: lidar_link, turntable_link\nplatter_link turns with the platter about z"
    )
    fig.text(0.5, 0.02, "lidar 1.0 m from the platter centre, pitched down 45° "
             "(t = (0, 1, 0) m, rz = −45°); red x, green y, blue z", ha="center", fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, metadata={"Date": None})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
