#!/usr/bin/env python3
"""warptan vs what a user would otherwise write: a vectorised NumPy implementation of the same sliding-grid
and ray-cast predictions (the ray cast through trimesh's ray–triangle intersector), on the same inputs and
the same CPU, in one run. Checks that both compute the same errors, then reports median times.

    python scripts/bench_numpy_baseline.py --n 500 --m-side 10 --json baseline.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import warp as wp

import warptan as wt
import warptan.parallel
from warptan.cli import script_inputs
from warptan.meta import run_meta
from warptan.nav.frames import euler_to_quat, quat_to_mat
from warptan.outputs import write_json


def numpy_sliding_error(terrain, pos, quat, points):
    """Eq. 14/16 for N poses × M points, vectorised NumPy (float64): per-particle mean |c_z - ĉ_z|."""
    mats = quat_to_mat(quat)                                   # (N, 3, 3)
    w = pos[:, None, :] + np.einsum("nij,mj->nmi", mats, points)  # (N, M, 3)
    h = terrain.height_at(w[..., 0], w[..., 1])
    w_hat = np.concatenate([w[..., :2], -h[..., None]], axis=-1)
    c_hat = np.einsum("nji,nmj->nmi", mats, w_hat - pos[:, None, :])
    return np.nanmean(np.abs(points[None, :, 2] - c_hat[..., 2]), axis=1)


def numpy_raycast_error(mesh, pos, quat, dirs, ranges):
    """Eq. 15 for N poses × M rays with trimesh's ray–triangle intersector (first hit per ray)."""
    mats = quat_to_mat(quat)
    d = np.einsum("nij,mj->nmi", mats, dirs).reshape(-1, 3)
    o = np.repeat(pos, len(dirs), axis=0)
    loc, idx_ray, _ = mesh.ray.intersects_location(o, d, multiple_hits=False)
    t = np.full(len(o), np.nan)
    t[idx_ray] = np.linalg.norm(loc - o[idx_ray], axis=1)
    res = np.abs(ranges[None, :] - t.reshape(len(pos), len(dirs)))
    return np.linalg.norm(np.nanmean(res[:, :, None] * np.abs(dirs)[None], axis=1), axis=1)


def timed(fn, repeats):
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def compare(terrain, tm, n: int, m_side: int, repeats: int, raycast_repeats: int) -> list[dict]:
    """Time warptan's sliding and ray-cast models against the NumPy/trimesh versions on the same inputs."""
    rng = np.random.default_rng(0)
    truth = np.array([0.0, 0.0, -(terrain.h_max + 600.0)])
    q_true = euler_to_quat(0.02, -0.01, 0.8)
    cloud = wt.PointCloudSensor(wt.ScanPattern.grid(m_side, m_side, 30.0)).measure(terrain, truth, q_true, rng)
    pos = truth + rng.normal(0.0, [100.0, 100.0, 20.0], (n, 3))
    quat = euler_to_quat(rng.normal(0.02, 0.002, n), rng.normal(-0.01, 0.002, n), rng.normal(0.8, 0.01, n))
    p_d = wp.array(pos.astype(np.float32), dtype=wp.vec3, device="cpu")
    q_d = wp.array(quat.astype(np.float32), dtype=wp.vec4, device="cpu")
    pos32, quat32 = p_d.numpy().astype(np.float64), q_d.numpy().astype(np.float64)
    quat32 /= np.linalg.norm(quat32, axis=1, keepdims=True)
    cases = (
        ("sliding", wt.SlidingModel(terrain), lambda: numpy_sliding_error(terrain, pos32, quat32, cloud.points_s),
         repeats, "vectorised NumPy"),
        ("raycast", wt.RaycastModel(terrain, caster=wt.RayCaster("dda")),
         lambda: numpy_raycast_error(tm, pos32, quat32, cloud.dirs_s, cloud.ranges_m), raycast_repeats,
         "trimesh ray-triangle (rtree)"),
    )
    rows = []
    for name, model, ref_fn, reps, impl in cases:
        t_wt = timed(lambda m=model: (m.evaluate(p_d, q_d, cloud), wp.synchronize_device("cpu")), repeats)
        t_np = timed(ref_fn, reps)
        diff = float(np.nanmax(np.abs(model.evaluate(p_d, q_d, cloud).error_m.numpy() - ref_fn())))
        rows.append({"model": name, "N": n, "M": m_side * m_side, "warptan_ms": 1e3 * t_wt, "numpy_ms": 1e3 * t_np,
                     "speedup": t_np / t_wt, "max_abs_error_difference_m": diff, "numpy_impl": impl,
                     "warptan_impl": type(model).__name__, "cpu_threads": wt.parallel.cpu_threads()})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, nargs="+", default=[500])
    parser.add_argument("--m-side", type=int, nargs="+", default=[10, 20])
    parser.add_argument("--terrain", default="synthetic:rugged")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--raycast-repeats", type=int, default=2, help="trimesh is slow: fewer repeats")
    parser.add_argument("--json", dest="json_out")
    args = parser.parse_args(argv)
    terrain = script_inputs("bench_numpy_baseline", ["cpu"], args.terrain)
    tm = terrain.to_trimesh()
    rows = []
    print(f"{'model':8s} {'N':>6s} {'M':>5s} {'warptan ms':>11s} {'numpy ms':>10s} {'speed-up':>9s} "
          f"{'max |Δerr| m':>13s}")
    for m_side in args.m_side:
        for n in args.n:
            for row in compare(terrain, tm, n, m_side, args.repeats, args.raycast_repeats):
                rows.append(row)
                print(f"{row['model']:8s} {n:>6d} {row['M']:>5d} {row['warptan_ms']:11.3f} {row['numpy_ms']:10.1f} "
                      f"{row['speedup']:8.1f}x {row['max_abs_error_difference_m']:13.4f}")
    if args.json_out:
        write_json(args.json_out, {"meta": run_meta("cpu", terrain=terrain.name,
                                                    what="median ms per measurement-model evaluation on the same "
                                                         "inputs, CPU"),
                                   "results": rows})
        print(f"wrote {args.json_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
