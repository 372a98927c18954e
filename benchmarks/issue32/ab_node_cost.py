"""In-situ cost of the pieces of S7's CUDA update graph (B = 1, N = 500, 20 x 20 scan; session 41): one filter per
variant, each built and captured with its patch active, stepped in turn in one process. Variants: ``base``;
``dup_partials`` / ``dup_reduce`` / ``dup_ray``: that launch issued twice (idempotent: the same bits), so the step's
increase is the piece's cost in its graph; ``noop``: an empty one-thread node after each candidates' partials (what a
node costs); ``slopes``: the per-ray kernel takes a DDA hit's normal from the slopes of the triangle it hit, as the
CPU's does since session 40 (not kept: CUDA bits change at triangle edges). Per variant: the median synchronised step
(µs; also by the number of tempering stages of the update), the device time of the model alone (20 launches in a
graph) and whether the history equals the base filter's. Artifacts ``ab_node_cost_h100.json`` (three runs).

    python3 ab_node_cost.py SCRIPTS_DIR OUT.json S7 STEPS VARIANT ...   (copied outside the checkout)
"""
import json
import os
import statistics
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])
import bench_filter_step as bfs

import warptan.parallel as par
from warptan.device import quiet_warp
from warptan.kernels import mpf as kmpf
from warptan.kernels import raycast as kray
from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.likelihood import CR_RANGE, CR_VALID, cloud_row, row_dir
from warptan.kernels.terrain import HeightGrid, grid_surface, is_finite, is_nan

quiet_warp()
DEV = os.environ.get("DEV", "cuda:0")


@wp.kernel
def noop_kernel(x: int):
    pass


@wp.kernel(cuda_max_registers=kray.RESIDUAL_MAX_REGISTERS, module="unique")
def ray_slopes_kernel(grid: HeightGrid, mesh: wp.uint64, backend: int, step_m: float, n_bisect: int, row0: int,
                      n_per: int, pos_n: wp.array(dtype=wp.vec3), quat_nb: wp.array(dtype=wp.vec4),
                      cloud: wp.array2d(dtype=cloud_row), residual_out: wp.array2d(dtype=wp.float32),
                      normal_out: wp.array2d(dtype=wp.vec3), want_vertical: int,
                      vertical_out: wp.array2d(dtype=wp.float32)):
    i, j = wp.tid()
    row = cloud[(row0 + i) // n_per, j]
    normal_out[i, j] = wp.vec3()
    if row[CR_VALID] == 0.0:
        residual_out[i, j] = wp.nan
        if want_vertical != 0:
            vertical_out[i, j] = wp.nan
        return
    mat = quat_to_mat_wxyz(quat_nb[i])
    d = mat * row_dir(row)
    p = pos_n[i]
    cast = kray.no_hit()
    if not kray.origin_blocked(grid, p):
        dn = wp.normalize(d)
        band = kray.band_interval(grid, p, dn)
        if band[0] <= band[1]:
            cast = kray.dda_march(grid, p, dn, band[0], band[1])
    t = cast[0]
    residual_out[i, j] = row[CR_RANGE] - t
    if want_vertical != 0:
        q = p + row[CR_RANGE] * d
        vertical_out[i, j] = -q[2] - grid_surface(grid, q[0], q[1])
    if not is_nan(t):
        nrm = wp.vec3(cast[1], cast[2], 1.0)
        den = wp.dot(nrm, d)
        if is_finite(den) and wp.abs(den) > 1.0e-3:
            normal_out[i, j] = nrm / den


out_path, sid, steps = sys.argv[2], sys.argv[3], int(sys.argv[4])
names = ["base", *sys.argv[5:]]
MODE = {"v": "base"}
orig_issue = par._issue
base_ray = kray.raycast_residual_kernel
DUP = {"dup_partials": "temper_partials_kernel", "dup_reduce": "reduce_loglik_kernel",
       "dup_ray": "raycast_residual_kernel"}


def issue(kernel, dim, block_dim, inputs, outputs, device, record, spread=None):
    cmd = orig_issue(kernel, dim, block_dim, inputs, outputs, device, record, spread)
    v = MODE["v"]
    if v in DUP and DUP[v] in kernel.key:
        orig_issue(kernel, dim, block_dim, inputs, outputs, device, record, spread)
    if v == "noop" and "temper_partials_kernel" in kernel.key:
        wp.launch(noop_kernel, dim=1, inputs=[0], device=device)
    return cmd


par._issue = issue
filters = {}
for name in names:
    MODE["v"] = name
    kray.raycast_residual_kernel = ray_slopes_kernel if name == "slopes" else base_ray
    mpf, f, w, setup = bfs.scenario_filter(sid, DEV)
    scans, ipm = bfs.scenario_scans(setup, steps), setup["imu_per_meas"]
    for it in range(5):
        mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
        mpf.update(scans[it], sync=False)
    wp.synchronize_device(DEV)
    with wp.ScopedCapture(DEV) as cap:
        for _ in range(20):
            mpf.model.launch(mpf._pos, mpf._quat)
    filters[name] = [mpf, cap.graph, [], []]
    print("ready", name, flush=True)
for it in range(5, steps):
    for name in names:
        MODE["v"] = name
        kray.raycast_residual_kernel = ray_slopes_kernel if name == "slopes" else base_ray
        mpf = filters[name][0]
        wp.synchronize_device(DEV)
        t0 = time.perf_counter()
        mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
        mpf.update(scans[it], sync=False)
        wp.synchronize_device(DEV)
        if it >= 60:
            filters[name][2].append(1e6 * (time.perf_counter() - t0))
            filters[name][3].append(it)
res = {}
h0 = filters["base"][0].history()
for name in names:
    g = filters[name][1]
    ts = []
    for _ in range(20):
        e0, e1 = wp.Event(DEV, enable_timing=True), wp.Event(DEV, enable_timing=True)
        wp.get_stream(DEV).record_event(e0)
        wp.capture_launch(g)
        wp.get_stream(DEV).record_event(e1)
        wp.synchronize_device(DEV)
        ts.append(1e3 * wp.get_event_elapsed_time(e0, e1) / 20)
    t = filters[name][2]
    h = filters[name][0].history()
    st = h[:, 0, kmpf.H_STAGES][filters[name][3]]
    tt = np.array(t)
    by = {int(k): [round(float(np.median(tt[st == k])), 1), int((st == k).sum())] for k in np.unique(st)}
    res[name] = {"stages_mean": float(st.mean()), "median_us_by_stages": by,
                 "step_median_us": statistics.median(t), "p25": float(np.percentile(t, 25)),
                 "p75": float(np.percentile(t, 75)), "model_us": statistics.median(ts),
                 "same_history_as_base": bool(np.array_equal(h, h0, equal_nan=True)),
                 "max_abs_history_diff": float(np.nanmax(np.abs(h - h0)))}
    print(sid, name, json.dumps(res[name]), flush=True)
json.dump(res, open(out_path, "w"), indent=1)
