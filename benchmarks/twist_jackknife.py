"""The cube twist's jackknife σ by Gauss–Newton steps against the same σ by full refits, over
the capability sweep's conditions (docs/performance.md).

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python benchmarks/twist_jackknife.py [--scenes 24]
        [--out DIR]

Each scene is one of the 24 conditions of ``ry_sweep.py`` (range noise 0.5, 1, 2 mm × line
rate 180, 1000 lines/s × background × spin-target placement, the scenario cycling through the
paper's nine and 0.9 m / 40°), its cube scanned 8 turns at 180 lines/s or 2 at 1000 lines/s.
On its first turn and on all of them, under the true H and under the true H with ry 0.1° off,
the side faces are found as the cube check finds them and the twist's σ is computed twice: by
:func:`calstation.engine.twist._linearised_twist` (every group's planes and the full fit's
linearised in the correction by two evaluations, then Gauss–Newton steps; again at the twist
found when it is beyond ``RELINEARISE_DEG``) and by the reference below, which fits the twist
by TRF and refits it without each group by TRF from that solution (what the cube check did
before). It prints each ratio, how far the linearised twist lies from TRF's (in σ), their
extremes, and the time of both.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import ry_sweep

from calstation.engine import twist
from calstation.engine.frames import Extrinsics, FloatArray


def refit_sigma(faces: list[tuple[FloatArray, FloatArray]], H: Extrinsics, x: float,
                f_scale: float, noise: float) -> tuple[float, int]:
    """The jackknife σ (rad) by full refits: the twist fitted by TRF (15 evaluations at most,
    from ``x``) without each group of :func:`twist._line_groups`; and how many refits stopped
    at a correction of exactly zero (from a start within about 0.01° of it TRF's first trust
    region is the size of the start, and such a refit stops short of its group's minimum)."""
    labels = twist._line_groups(faces)
    estimates = []
    for g in range(twist.JACKKNIFE_GROUPS):
        keep = [lab != g for lab in labels]
        flat = twist.FaceFlatness([p[k] for (p, _), k in zip(faces, keep, strict=True)],
                                  [f[k] for (_, f), k in zip(faces, keep, strict=True)], noise)
        estimates.append(float(twist._fit_twist(flat, H, x, f_scale, max_nfev=15).x[0]))
    e = np.asarray(estimates)
    k = twist.JACKKNIFE_GROUPS
    return (float(math.sqrt((k - 1) / k * np.sum((e - e.mean()) ** 2))),
            int(np.count_nonzero(np.abs(e) < 1e-15)))


def side_faces(scan: object, H: Extrinsics, edge: float,
               radius: float) -> list[tuple[FloatArray, FloatArray]]:
    """The side faces' returns and platter angles as the cube check passes them to the twist."""
    from calstation.engine.cube import _face_dimensions
    from calstation.engine.cubecloud import cube_cloud

    cloud = cube_cloud(scan.p_L, scan.phi, H, edge, radius, None)  # type: ignore[attr-defined]
    dims = _face_dimensions(cloud, edge, radius)
    sides = [dims.faces[n].members for n in ("1-", "1+", "2-", "2+") if n in dims.faces]
    return twist._twist_faces([cloud.p_L[cloud.idx[m]] for m in sides],
                              [cloud.phi[cloud.idx[m]] for m in sides])


def compare(faces: list[tuple[FloatArray, FloatArray]], H: Extrinsics) -> dict[str, float]:
    """Both σ of the twist under H, and their times."""
    faces_L, faces_phi = [p for p, _ in faces], [f for _, f in faces]
    noise = twist.face_range_noise(faces_L, faces_phi, H)
    f_scale = max(0.002, twist.FSCALE_NOISE * noise)
    t0 = time.perf_counter()
    grouped = twist._GroupedFaces(faces, twist._line_groups(faces), noise)
    found, gn = twist._linearised_twist(grouped, H, f_scale)
    t1 = time.perf_counter()
    flat = twist.FaceFlatness(faces_L, faces_phi, noise)
    x = float(twist._fit_twist(flat, H, 0.0, f_scale, max_nfev=50).x[0])
    ref, stuck = refit_sigma(faces, H, x, f_scale, noise)
    t2 = time.perf_counter()
    return {"twist_deg": math.degrees(x), "gn_deg": math.degrees(gn),
            "refit_deg": math.degrees(ref), "ratio": gn / ref, "shift": (found - x) / ref,
            "stuck": stuck, "gn_s": t1 - t0, "refit_s": t2 - t1,
            "returns": sum(p.shape[0] for p in faces_L)}


def scene(k: int, out: Path) -> list[dict[str, float]]:
    """Scene ``k`` simulated once; both σ on its first turn and on all of its turns."""
    from calstation_sim import simulate_run

    from calstation.engine.spinscan import from_recording
    from calstation.recordings.reader import read_recording

    cond = ry_sweep._condition(k)
    most = 8 if cond["line_rate"] < 500 else 2
    loaded = ry_sweep.sim_recipe(
        cond["noise"], cond["background"], cond["offset"], cond["line_rate"], cond["scenario"],
        900 + k, steps={"cube_scan": {"revolutions": most + 0.05, "max_revolutions": most + 0.05}})
    recipe = loaded.recipe
    paths = simulate_run(loaded, out / f"scene{k}", progress=False)
    rows = []
    try:
        cube = read_recording(paths["cube"])
        truth = cube.truth
        assert truth is not None
        for turns in (1, most):
            scan = from_recording(cube.first_turns(turns))
            for off in (0.0, 0.1):
                H = truth.with_(ry=truth.ry + math.radians(off))
                faces = side_faces(scan, H, recipe.fixtures.qa_cube.edge,
                                   recipe.fixtures.platter.radius)
                row = {"k": k, "noise_mm": cond["noise"] * 1e3, "rate": cond["line_rate"],
                       "turns": turns, "ry_off_deg": off, **compare(faces, H)}
                print(f"scene {k}: {row['noise_mm']:.1f} mm, {row['rate']:.0f} lines/s, "
                      f"{turns} turn(s), ry {off:+.1f}° off, {row['returns']} returns: twist "
                      f"{row['twist_deg']:+.4f}° (linearised {row['shift']:+.4f}σ from it), "
                      f"σ {row['gn_deg']:.5f}° (Gauss–Newton) / "
                      f"{row['refit_deg']:.5f}° (refits, {row['stuck']} stopped at zero), ratio "
                      f"{row['ratio']:.4f}; "
                      f"{row['gn_s']:.3f} s / {row['refit_s']:.3f} s", flush=True)
                rows.append(row)
    finally:
        for path in paths.values():
            Path(path).unlink(missing_ok=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--out", type=Path, default=ry_sweep.REPO / "out" / "twist-jackknife")
    args = ap.parse_args()
    rows = [r for k in range(args.first, args.first + args.scenes) for r in scene(k, args.out)]
    ratios = [r["ratio"] for r in rows]
    sound = [r["ratio"] for r in rows if r["stuck"] == 0]
    print(f"\n{len(rows)} twist σ: Gauss–Newton ÷ refits median {statistics.median(ratios):.4f}, "
          f"min {min(ratios):.4f}, max {max(ratios):.4f}; within ±5 %: "
          f"{sum(abs(x - 1) <= 0.05 for x in ratios)}/{len(ratios)}, and of those whose refits "
          f"all moved {sum(abs(x - 1) <= 0.05 for x in sound)}/{len(sound)}; the linearised twist "
          f"within {max(abs(r['shift']) for r in rows):.4f}σ of TRF's; time "
          f"{sum(r['gn_s'] for r in rows):.1f} s against {sum(r['refit_s'] for r in rows):.1f} s")


if __name__ == "__main__":
    main()
