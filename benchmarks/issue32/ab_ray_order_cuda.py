"""The CUDA per-ray kernel with its threads' rays ordered by their angle off the sensor's axis, as the CPU's SIMD lanes
are (session 41; not kept): one S7 filter each (B = 1, N = 500, 20 x 20 scan) with the kernel as it is (``base``), its
rays fully sorted by the squared horizontal part of their sensor-frame direction (``sorted``) or in 16 bands of it
(``bands16``, the CPU's order), stepped in turn; per variant the median synchronised step (µs), the model's device time
(20 launches in a graph) and whether the history equals the base filter's. ``ab_ray_order_cuda_h100.json``: the same
bits, no gain (model 38.0 -> 41.8 / 38.6 µs): a warp's rays diverge by the terrain more than by their angle.

    python3 ab_ray_order_cuda.py SCRIPTS_DIR OUT.json STEPS   (copied outside the checkout)
"""
import json
import statistics
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])
import bench_filter_step as bfs

import warptan.sensing.measurement as meas
from warptan.device import quiet_warp
from warptan.kernels import raycast as kray
from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.likelihood import CR_RANGE, CR_VALID, cloud_row, row_dir
from warptan.kernels.terrain import HeightGrid, grid_gradient, grid_surface, is_finite, is_nan
from warptan.parallel import launch_rows, rows_of

quiet_warp()


@wp.kernel(cuda_max_registers=kray.RESIDUAL_MAX_REGISTERS, module="unique")
def ray_ordered_kernel(grid: HeightGrid, mesh: wp.uint64, backend: int, step_m: float, n_bisect: int, row0: int,
                       n_per: int, pos_n: wp.array(dtype=wp.vec3), quat_nb: wp.array(dtype=wp.vec4),
                       cloud: wp.array2d(dtype=cloud_row), residual_out: wp.array2d(dtype=wp.float32),
                       normal_out: wp.array2d(dtype=wp.vec3), want_vertical: int,
                       vertical_out: wp.array2d(dtype=wp.float32), order: wp.array2d(dtype=wp.int32)):
    i, jj = wp.tid()
    b = (row0 + i) // n_per
    j = order[wp.min(b, order.shape[0] - 1), jj]
    row = cloud[b, j]
    normal_out[i, j] = wp.vec3()
    if row[CR_VALID] == 0.0:
        residual_out[i, j] = wp.nan
        if want_vertical != 0:
            vertical_out[i, j] = wp.nan
        return
    mat = quat_to_mat_wxyz(quat_nb[i])
    d_s = row_dir(row)
    d = mat * d_s
    p = pos_n[i]
    t = kray.cast_ray(grid, mesh, backend, p, d, step_m, n_bisect)
    residual_out[i, j] = row[CR_RANGE] - t
    if want_vertical != 0:
        q = p + row[CR_RANGE] * d
        vertical_out[i, j] = -q[2] - grid_surface(grid, q[0], q[1])
    if not is_nan(t):
        hit = p + t * d
        grad = grid_gradient(grid, 1, hit[0], hit[1])
        nrm = wp.vec3(grad[0], grad[1], 1.0)
        den = wp.dot(nrm, d)
        if is_finite(den) and wp.abs(den) > 1.0e-3:
            normal_out[i, j] = nrm / den


ORDERS = {}
MODE = {"v": "base"}
plain = meas.RaycastModel._launch_residuals


def ordered(self, pos_n, quat_nb, out, device):
    if MODE["v"] == "base":
        return plain(self, pos_n, quat_nb, out, device)
    dirs = self._host["dirs"][0]  # the pattern's directions (sensor frame), as staged
    key = (id(self), MODE["v"])
    if key not in ORDERS:
        h2 = dirs[:, 0].astype(np.float64) ** 2 + dirs[:, 1].astype(np.float64) ** 2
        if MODE["v"] == "sorted":
            o = np.argsort(h2, kind="stable")
        else:  # 16 bands, stable
            o = np.argsort(np.minimum((h2 * 16).astype(int), 15), kind="stable")
        ORDERS[key] = wp.array(o[None].astype(np.int32), dtype=wp.int32, device=device)
    lead = self.caster.launch_args(self.terrain, device)
    res, nrm, vert, cloud, n_per = out.residual_m, out.normal, out.vertical_m, self._staged, self.n_per
    launch_rows(ray_ordered_kernel, res.shape[0],
                lambda a, b: ([*lead, a or 0, n_per, rows_of(pos_n, a, b), rows_of(quat_nb, a, b), cloud],
                              [rows_of(res, a, b), rows_of(nrm, a, b), int(self._gates_misses()),
                               rows_of(vert, a, b), ORDERS[key]]),
                device, cols=res.shape[1], row_cost=20)


meas.RaycastModel._launch_residuals = ordered
out_path, steps = sys.argv[2], int(sys.argv[3])
names = ["base", "sorted", "bands16"]
filters = {}
for name in names:
    MODE["v"] = name
    mpf, f, w, setup = bfs.scenario_filter("S7", "cuda:0")
    scans, ipm = bfs.scenario_scans(setup, steps), setup["imu_per_meas"]
    for it in range(5):
        mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
        mpf.update(scans[it], sync=False)
    wp.synchronize_device("cuda:0")
    with wp.ScopedCapture("cuda:0") as cap:
        for _ in range(20):
            mpf.model.launch(mpf._pos, mpf._quat)
    filters[name] = [mpf, cap.graph, []]
    print("ready", name, flush=True)
for it in range(5, steps):
    for name in (names if it % 2 else names[::-1]):
        MODE["v"] = name
        mpf = filters[name][0]
        wp.synchronize_device("cuda:0")
        t0 = time.perf_counter()
        mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
        mpf.update(scans[it], sync=False)
        wp.synchronize_device("cuda:0")
        if it >= 60:
            filters[name][2].append(1e6 * (time.perf_counter() - t0))
res = {}
h0 = filters["base"][0].history()
for name in names:
    MODE["v"] = name
    ts = []
    for _ in range(20):
        e0, e1 = wp.Event("cuda:0", enable_timing=True), wp.Event("cuda:0", enable_timing=True)
        wp.get_stream("cuda:0").record_event(e0)
        wp.capture_launch(filters[name][1])
        wp.get_stream("cuda:0").record_event(e1)
        wp.synchronize_device("cuda:0")
        ts.append(1e3 * wp.get_event_elapsed_time(e0, e1) / 20)
    t = filters[name][2]
    h = filters[name][0].history()
    res[name] = {"step_median_us": statistics.median(t), "p25": float(np.percentile(t, 25)),
                 "p75": float(np.percentile(t, 75)), "model_us": statistics.median(ts),
                 "same_history_as_base": bool(np.array_equal(h, h0, equal_nan=True))}
    print(name, json.dumps(res[name]), flush=True)
json.dump(res, open(out_path, "w"), indent=1)
