"""Where S7's per-particle likelihood reduction (``reduce_loglik_kernel``, tiled, no modes; one block of 64 lanes per
particle) spends its time on CUDA (session 41): a copy whose lane 0 stamps the GPU's ``%globaltimer`` at its start,
after its own points, after the block sum and after ``acc_store`` replaces it in the filter's launches; medians over
steps of the particles' medians (µs), the kernel's span and the spread of its blocks' starts and ends
(``stamps_reduce_h100.json``: lane 0's 7 points 6.5 µs, the block sum 1.5, the store 1.75; the kernel 10.5 µs).

    python3 stamps_reduce.py SCRIPTS_DIR OUT.json STEPS   (copied outside the checkout)
"""
import json
import os
import statistics
import sys

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])
import bench_filter_step as bfs

import warptan.sensing.measurement as meas
from warptan.device import quiet_warp
from warptan.kernels import likelihood as klik
from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.likelihood import (
    CR_VALID,
    LikParams,
    acc_block_total,
    acc_init,
    acc_point,
    acc_store,
    axis_weights,
    cloud_row,
    gross_miss,
    map_not_world,
    modes_init,
    modes_vec,
    ray_jacobians,
    ray_nominal_gain,
    ray_var,
    row_dir,
)
from warptan.kernels.terrain import is_nan
from warptan.parallel import launch_rows

quiet_warp()
DEV = os.environ.get("DEV", "cuda:0")


@wp.func_native('''
#if defined(__CUDA_ARCH__)
unsigned long long t; asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(t)); return (wp::int64)t;
#else
return 0;
#endif
''')
def gtime() -> wp.int64: ...


@wp.kernel(module="unique", enable_backward=False)
def reduce_stamped(row0: int, n_per: int, residual: wp.array2d(dtype=wp.float32), quat_nb: wp.array(dtype=wp.vec4),
                   normal: wp.array2d(dtype=wp.vec3), vertical: wp.array2d(dtype=wp.float32),
                   cloud: wp.array2d(dtype=cloud_row), att_cov: wp.array(dtype=wp.mat33), params: LikParams,
                   modes: wp.array(dtype=modes_vec), mode_mean: wp.array(dtype=modes_vec),
                   mode_var: wp.array(dtype=modes_vec), err_out: wp.array(dtype=wp.float32),
                   loglik_out: wp.array(dtype=wp.float32), nis_out: wp.array(dtype=wp.float32),
                   n_valid_out: wp.array(dtype=wp.int32), lam_out: wp.array(dtype=wp.mat33),
                   info_out: wp.array(dtype=wp.vec3), post_out: wp.array(dtype=modes_vec),
                   tbuf: wp.array2d(dtype=wp.int64)):
    t, lane = wp.tid()
    stride = wp.block_dim()
    if lane == 0:
        tbuf[t, 0] = gtime()
    b = (row0 + t) // n_per
    mat = quat_to_mat_wxyz(quat_nb[t])
    acc = acc_init()
    macc = modes_init()
    for j in range(lane, residual.shape[1], stride):
        row = cloud[b, j]
        res = residual[t, j]
        if row[CR_VALID] != 0.0:
            acc.n_recv = acc.n_recv + 1
            if not is_nan(res):
                s = normal[t, j]
                jac, jac_pos = ray_jacobians(mat, row, res, s)
                u_down = (mat * row_dir(row))[2]
                var = ray_var(params, s, u_down)
                vert = float(wp.nan)
                if map_not_world(params):
                    vert = vertical[t, j]
                gain = ray_nominal_gain(u_down)
                miss = gross_miss(params, res, var, gain)
                acc_point(acc, params, miss, res, var, gain, vert, axis_weights(row), jac, jac_pos)
    if lane == 0:
        tbuf[t, 1] = gtime()
    acc = acc_block_total(acc)
    if lane == 0:
        tbuf[t, 2] = gtime()
        acc_store(t, acc, macc, params, att_cov[b], err_out, loglik_out, nis_out, n_valid_out, lam_out, info_out)
        tbuf[t, 3] = gtime()


TB = {}


def launch_reduce(self, quat_nb, out, device):
    res, nrm, vert, cloud, n_per = out.residual_m, out.normal, out.vertical_m, self._staged, self.n_per
    att = self._attitude_cov(device, self.n_filters)
    mean, var = self._mode_state(device, res.shape[0], self.n_filters)
    if "t" not in TB:
        TB["t"] = wp.zeros((res.shape[0], 4), dtype=wp.int64, device=device)
    launch_rows(reduce_stamped, res.shape[0],
                lambda a, b: ([0, n_per, res, quat_nb, nrm, vert, cloud, att, self._params, self._modes, mean, var],
                              [out.error_m, out.loglik, out.nis, out.n_valid, out.lam, out.info, out.mode_post,
                               TB["t"]]), device, row_cost=res.shape[1], block_dim=klik.BLOCK_DIM, threads=1)


meas.RaycastModel._launch_reduce = launch_reduce
steps = int(sys.argv[3])
mpf, f, w, setup = bfs.scenario_filter("S7", DEV)
scans, ipm = bfs.scenario_scans(setup, steps), setup["imu_per_meas"]
rows = {"points (lane 0)": [], "block sum": [], "store": [], "lane-0 block": [], "kernel span": [],
        "start spread": [], "end spread": []}
for it in range(steps):
    mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
    mpf.update(scans[it], sync=False)
    if it < 20:
        continue
    t = TB["t"].numpy().astype(np.float64) * 1e-3
    rows["points (lane 0)"].append(np.median(t[:, 1] - t[:, 0]))
    rows["block sum"].append(np.median(t[:, 2] - t[:, 1]))
    rows["store"].append(np.median(t[:, 3] - t[:, 2]))
    rows["lane-0 block"].append(np.median(t[:, 3] - t[:, 0]))
    rows["kernel span"].append(t[:, 3].max() - t[:, 0].min())
    rows["start spread"].append(t[:, 0].max() - t[:, 0].min())
    rows["end spread"].append(t[:, 3].max() - t[:, 3].min())
res = {k: round(float(statistics.median(v)), 3) for k, v in rows.items()}
print("reduce stamps (us, medians over steps of per-particle medians)", json.dumps(res))
json.dump(res, open(sys.argv[2], "w"), indent=1)
