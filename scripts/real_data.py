"""Import real ROS bags of a tilting 2D lidar, reconstruct them with the mount's nominal geometry
and measure them: the figures and the picture of docs/real-data.md.

    python scripts/real_data.py --bag room_240.bag --bag first_scan.bag ... \
        [--png docs/real-data.png] [--json out.json]

The bags are the public recordings of a tilting Hokuyo (URG-04LX class) on a stepper stand
described in docs/real-data.md: one topic ``/slice`` bundling a ``sensor_msgs/LaserScan
laserScan`` with the tilt in degrees (``tiltAngle`` or ``stepAngle``). Each bag is imported
exactly as ``calstation import rosbag BAG --scan /slice:laserScan --angle /slice:FIELD
--angle-unit deg --counts-per-rev 4800 --direction -1`` does, reconstructed with the nominal H
below, checked point for point against the authors' own reconstruction formula, and measured:
the largest planes (RANSAC, then a least-squares refit) against the datasheet noise, mixed
pixels, timing and angle quantisation. Nothing of the bags is written to the repository.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

TILT_RADIUS_M = 0.08
"""The authors' TILT_RADIUS: the optical centre is this far from the tilt axis along the
scan-plane normal."""
STEP_DEG = 360.0 / 4800
"""One step of the stand's stepper (open loop, no encoder)."""
NOMINAL_H = {"tx": 0.0, "ty": 0.0, "tz": -TILT_RADIUS_M, "rx": 0.0, "ry": 0.0, "rz": math.pi}
"""The nominal geometry as a calstation H (docs/real-data.md derives it)."""


def datasheet_sigma(r: np.ndarray) -> np.ndarray:
    """URG-04LX-UG01 accuracy: ±30 mm to 1 m, ±3 % of the distance beyond (m)."""
    return np.where(r < 1.0, 0.030, 0.03 * r)


def import_bag(bag: Path, out: Path) -> tuple[Any, Any, str]:
    """The bag imported as ``calstation import rosbag`` does; (result, recording, angle field)."""
    from rosbags.highlevel import AnyReader

    from calstation.recordings.imported import write_imported
    from calstation.recordings.reader import read_recording
    from calstation.recordings.rosbag import TopicSpec, read_rosbag

    with AnyReader([bag]) as reader:
        msgtype = reader.connections[0].msgtype
    field = "tiltAngle" if msgtype.endswith("PointCloudSliceMsg") else "stepAngle"
    scan = read_rosbag(bag, TopicSpec("/slice", "laserScan"), TopicSpec("/slice", field),
                       angle_unit="deg")
    result = write_imported(scan, out, counts_per_revolution=4800, direction=-1)
    return result, read_recording(out), field


def authors_points(bag: Path, field: str, snap: bool
                   ) -> tuple[np.ndarray, list[float], dict[str, Any]]:
    """The authors' reconstruction (point_cloud_from_slice_node.py) of every valid return, in
    their base frame B (x forward, y left, z up, origin on the tilt axis), with the raw angles
    and timing figures; ``snap`` puts the logged angle (rounded to 0.01°) on the stepper's
    0.075° grid first, as the import does."""
    from rosbags.highlevel import AnyReader

    pts, angles, hdr_minus_bag, scan_times, spans = [], [], [], [], []
    with AnyReader([bag]) as reader:
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            ls = msg.laserScan
            deg = float(getattr(msg, field))
            theta = math.radians(round(deg / STEP_DEG) * STEP_DEG if snap else deg)
            angles.append(float(getattr(msg, field)))
            r = np.asarray(ls.ranges, np.float64)
            beta = ls.angle_min + np.arange(len(r)) * ls.angle_increment
            ok = np.isfinite(r) & (r >= ls.range_min) & (r <= ls.range_max)
            xs, ys = r[ok] * np.cos(beta[ok]), r[ok] * np.sin(beta[ok])
            pts.append(np.column_stack([
                xs * math.cos(-theta) + TILT_RADIUS_M * math.sin(theta),
                ys,
                xs * math.sin(-theta) + TILT_RADIUS_M * math.cos(theta),
            ]))
            stamp = ls.header.stamp.sec * 10**9 + ls.header.stamp.nanosec
            hdr_minus_bag.append((stamp - t) * 1e-9)
            scan_times.append(float(ls.scan_time))
            spans.append(float(ls.time_increment) * len(r))
    return np.concatenate(pts), angles, {
        "header_minus_receive_s": hdr_minus_bag, "scan_time_s": scan_times,
        "line_span_s": spans,
    }


def fit_planes(points: np.ndarray, count: int, threshold: float = 0.03
               ) -> list[dict[str, Any]]:
    """The ``count`` largest planes: RANSAC (seeded, so the figures repeat), then a
    least-squares refit on the points within ``threshold``; planes that contain the tilt axis
    (x of D, made of the ±90° beams, whose points do not move when tilting) are skipped."""
    rng = np.random.default_rng(0)
    rest = points
    planes: list[dict[str, Any]] = []
    tries = 0
    while len(planes) < count and len(rest) > 1000 and tries < 4 * count:
        tries += 1
        sample = rest[rng.choice(len(rest), min(len(rest), 40000), replace=False)]
        best, best_n, best_d = -1, np.zeros(3), 0.0
        for _ in range(1500):
            a, b, c = sample[rng.choice(len(sample), 3, replace=False)]
            n = np.cross(b - a, c - a)
            if np.linalg.norm(n) < 1e-9:
                continue
            n = n / np.linalg.norm(n)
            d = float(n @ a)
            k = int(np.count_nonzero(np.abs(sample @ n - d) < threshold))
            if k > best:
                best, best_n, best_d = k, n, d
        n, d = best_n, best_d
        mask = np.abs(rest @ n - d) < threshold
        inl = rest[mask]
        rest = rest[~mask]
        if abs(n[0]) < 0.2 and abs(d) < 0.1:
            continue  # contains the tilt axis: not a surface of the scene
        centre = inl.mean(axis=0)
        _, _, vt = np.linalg.svd(inl - centre, full_matrices=False)
        normal = vt[2]
        res = (inl - centre) @ normal
        mad = 1.4826 * np.median(np.abs(res - np.median(res)))
        planes.append({"points": len(inl), "normal": normal.tolist(),
                       "distance_m": float(centre @ normal), "rms_m": float(np.sqrt(np.mean(
                           res**2))), "robust_sigma_m": float(mad), "residuals": res,
                       "inliers": inl})
    return planes


def mixed_pixels(rec: Any, jump: float = 0.15, margin: float = 0.03) -> tuple[int, int]:
    """Returns that lie between their two neighbours across a depth jump of more than ``jump``
    (and more than ``margin`` from both): the mixed pixels' signature; and the jumps seen."""
    bounds = rec.line_bounds()
    mixed = jumps = 0
    for i in range(rec.n_lines):
        r = rec.range_m[bounds[i]:bounds[i + 1]]
        v = rec.valid[bounds[i]:bounds[i + 1]]
        a, b, c = r[:-2], r[1:-1], r[2:]
        ok = v[:-2] & v[1:-1] & v[2:]
        with np.errstate(invalid="ignore"):
            big = ok & (np.abs(c - a) > jump)
        lo, hi = np.minimum(a, c), np.maximum(a, c)
        mixed += int(np.count_nonzero(big & (b > lo + margin) & (b < hi - margin)))
        jumps += int(np.count_nonzero(big))
    return mixed, jumps


def measure(bag: Path, tmp: Path, planes: int) -> dict[str, Any]:
    """Everything docs/real-data.md reports about one bag."""
    from calstation.engine.frames import Extrinsics
    from calstation.engine.reconstruct import reconstruct

    result, rec, field = import_bag(bag, tmp / f"{bag.stem}.mcap")
    H = Extrinsics.from_dict(NOMINAL_H)
    p_D = reconstruct(rec, H)
    # D's axes in the authors' base frame B: x_D = y_B (the tilt axis), y_D = −x_B, z_D = z_B
    theirs, angles, timing = authors_points(bag, field, snap=True)
    agreement = float(np.max(np.linalg.norm(
        p_D - np.column_stack([theirs[:, 1], -theirs[:, 0], theirs[:, 2]]), axis=1)))
    logged, _, _ = authors_points(bag, field, snap=False)
    rounding = float(np.max(np.linalg.norm(theirs - logged, axis=1)))
    p_L, _ = rec.points_lidar()
    ranges = np.linalg.norm(p_L, axis=1)
    found = fit_planes(p_D, planes)
    for plane in found:
        r = np.linalg.norm(plane["inliers"] - [0.0, 0.0, 0.0], axis=1)  # ≈ range (8 cm off)
        plane["median_range_m"] = float(np.median(r))
        plane["datasheet_m"] = float(np.median(datasheet_sigma(r)))
    a = np.asarray(angles)
    steps = a / STEP_DEG
    mixed, jumps = mixed_pixels(rec)
    dt = np.diff(rec.line_timestamp_ns) * 1e-9
    return {
        "bag": bag.name, "angle_field": field, "lines": result.lines, "points": result.points,
        "valid": result.valid, "notes": result.notes,
        "agreement_with_authors_m": agreement, "rounding_effect_m": rounding,
        "tilt_deg": [float(a.min()), float(a.max())],
        "angle_off_step_deg": float(np.max(np.abs(steps - np.round(steps))) * STEP_DEG),
        "angle_changes": int(np.count_nonzero(np.diff(a))),
        "line_interval_s": [float(np.percentile(dt, q)) for q in (5, 50, 95)],
        "header_minus_receive_s": [float(np.percentile(timing["header_minus_receive_s"], q))
                                   for q in (5, 50, 95)],
        "line_span_s": float(np.median(timing["line_span_s"])),
        "scan_time_s": float(np.median(timing["scan_time_s"])),
        "range_m": [float(np.percentile(ranges, q)) for q in (5, 50, 95)],
        "mixed_pixels": mixed, "depth_jumps": jumps,
        "planes": found,
        "cloud": p_D,
    }


def figure(results: list[dict[str, Any]], png: Path) -> None:
    """The picture: the first bag's scene in D (two views, its planes coloured) and every plane's
    residuals against the datasheet."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    big = results[0]  # the first bag given: its scene is drawn
    fig = plt.figure(figsize=(13, 4.6))
    ax1 = fig.add_subplot(1, 3, 1)
    ax2 = fig.add_subplot(1, 3, 2)
    ax3 = fig.add_subplot(1, 3, 3)
    cloud = big["cloud"][:: max(1, len(big["cloud"]) // 60000)]
    ax1.scatter(cloud[:, 1], cloud[:, 0], c=cloud[:, 2], s=0.3, cmap="viridis")
    ax1.set(title=f"{big['bag']}: top view of D (colour: height)", xlabel="y_D [m]",
            ylabel="x_D = tilt axis [m]", aspect="equal")
    ax2.scatter(cloud[:, 1], cloud[:, 2], c="0.75", s=0.2)
    for k, plane in enumerate(big["planes"]):
        q = plane["inliers"][:: max(1, len(plane["inliers"]) // 8000)]
        ax2.scatter(q[:, 1], q[:, 2], s=0.4, color=f"C{k}",
                    label=f"plane {k + 1}: {plane['rms_m'] * 1e3:.1f} mm RMS")
    ax2.set(title="side view, largest planes", xlabel="y_D [m]", ylabel="z_D (up) [m]",
            aspect="equal")
    ax2.legend(markerscale=12, fontsize=7, loc="lower left")
    bins = np.linspace(-0.06, 0.06, 61)
    for r in results:
        res = np.concatenate([p["residuals"] for p in r["planes"]]) if r["planes"] else []
        ax3.hist(np.asarray(res) * 1e3, bins=bins * 1e3, histtype="step", density=True,
                 label=r["bag"])
    ax3.axvspan(-30, 30, color="tab:red", alpha=0.08, label="datasheet ±30 mm (< 1 m)")
    ax3.set(title="residuals to the largest planes", xlabel="signed distance [mm]",
            ylabel="density")
    ax3.legend(fontsize=7)
    fig.suptitle("Real data: a tilting Hokuyo (URG-04LX class) imported with calstation import "
                 "rosbag, reconstructed with the nominal H", fontsize=10)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", type=Path, action="append", required=True)
    parser.add_argument("--planes", type=int, default=4, help="largest planes per bag")
    parser.add_argument("--png", type=Path, default=None)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for bag in args.bag:
            results.append(measure(bag, Path(tmp), args.planes))
    for r in results:
        print(f"\n{r['bag']}: {r['lines']} lines, {r['points']} points ({r['valid']} valid); "
              f"tilt {r['tilt_deg'][0]:.2f}..{r['tilt_deg'][1]:.2f}°; calstation vs the "
              f"authors' formula: {r['agreement_with_authors_m']:.2e} m (their logged angles, "
              f"rounded to 0.01°, move points by up to {r['rounding_effect_m'] * 1e3:.2f} mm)")
        print(f"  angle off the 0.075° step grid: ≤ {r['angle_off_step_deg']:.4f}°; "
              f"{r['angle_changes']} changes in {r['lines']} lines")
        interval = ", ".join(f"{v * 1e3:.1f}" for v in r["line_interval_s"])
        print(f"  line interval p5/50/95: {interval} ms; header − receive p5/50/95: "
              f"{', '.join(f'{v * 1e3:.1f}' for v in r['header_minus_receive_s'])} ms; "
              f"line span {r['line_span_s'] * 1e3:.1f} ms of scan_time "
              f"{r['scan_time_s'] * 1e3:.0f} ms")
        print(f"  range p5/50/95: {', '.join(f'{v:.2f}' for v in r['range_m'])} m; "
              f"mixed pixels {r['mixed_pixels']} at {r['depth_jumps']} depth jumps")
        for k, p in enumerate(r["planes"]):
            normal = ", ".join(f"{v:+.2f}" for v in p["normal"])
            print(f"  plane {k + 1}: {p['points']} pts, n=({normal}) d={p['distance_m']:+.3f} m, "
                  f"median range {p['median_range_m']:.2f} m: "
                  f"RMS {p['rms_m'] * 1e3:.1f} mm, robust σ {p['robust_sigma_m'] * 1e3:.1f} mm, "
                  f"datasheet ±{p['datasheet_m'] * 1e3:.0f} mm")
        for note in r["notes"]:
            print(f"  note: {note}")
    if args.png is not None:
        figure(results, args.png)
        print(f"\nwrote {args.png}")
    if args.json is not None:
        slim = [{k: v for k, v in r.items() if k != "cloud"} for r in results]
        for r in slim:
            r["planes"] = [{k: v for k, v in p.items() if k not in ("residuals", "inliers")}
                           for p in r["planes"]]
        args.json.write_text(json.dumps(slim, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
