"""In-process A/B of S7's ray-casting model on CUDA (B = 1, N = 500, 20 x 20 scan): the model as it is (one thread per
ray, then a block of ``BLOCK_DIM`` lanes per particle reducing the residual arrays) against variants defined here:

* ``band``: the per-ray kernel with the DDA started at the ray's local band (:func:`~warptan.kernels.raycast.
  local_band_entry`, the CPU's form) and the origin check once per particle's ray;
* ``fused64`` / ``fused128`` / ``fused256``: one block per particle (64 / 128 / 256 lanes) casting its rays and
  summing them in registers (no residual, normal or vertical arrays between two kernels; the sums in the reduction's
  lane order at 64 lanes);
* ``r128``: the reduction at 128 lanes.

Per variant: the model's device time (20 launches in a graph between two events, median of 20 replays), the
synchronised step of filters stepped alternately (medians), and whether its estimate after the run is bit-identical
to the model as it is.

    python3 benchmarks/issue32/ab_ray_model.py scripts OUT.json   (from a folder outside the checkout)
"""

import json
import statistics
import sys

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])  # scripts/: bench_filter_step's scenario setup
import bench_filter_step as bfs
from ab_interval_first import alternate  # (this folder)

from warptan.kernels import likelihood as klik
from warptan.kernels import raycast as kray
from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.likelihood import (
    CR_RANGE,
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
    ray_jacobians,
    ray_nominal_gain,
    ray_var,
    row_dir,
)
from warptan.kernels.raycast import cast_unblocked_local, origin_blocked
from warptan.kernels.terrain import HeightGrid, grid_gradient, grid_surface, is_finite, is_nan
from warptan.sensing.measurement import RaycastModel

STEPS, WARMUP = 700, 100

wp.set_module_options({"enable_backward": False})


@wp.kernel(cuda_max_registers=kray.RESIDUAL_MAX_REGISTERS)
def band_residual_kernel(
    grid: HeightGrid,
    mesh: wp.uint64,
    backend: int,
    step_m: float,
    n_bisect: int,
    row0: int,
    n_per: int,
    pos_n: wp.array(dtype=wp.vec3),
    quat_nb: wp.array(dtype=wp.vec4),
    cloud: wp.array2d(dtype=cloud_row),
    residual_out: wp.array2d(dtype=wp.float32),
    normal_out: wp.array2d(dtype=wp.vec3),
    want_vertical: int,
    vertical_out: wp.array2d(dtype=wp.float32),
):
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
    t = float(wp.nan)
    if not origin_blocked(grid, p):
        t = cast_unblocked_local(grid, mesh, backend, p, d, step_m, n_bisect)
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


@wp.kernel
def fused_kernel(
    grid: HeightGrid,
    mesh: wp.uint64,
    backend: int,
    step_m: float,
    n_bisect: int,
    row0: int,
    n_per: int,
    pos_n: wp.array(dtype=wp.vec3),
    quat_nb: wp.array(dtype=wp.vec4),
    cloud: wp.array2d(dtype=cloud_row),
    att_cov: wp.array(dtype=wp.mat33),
    params: LikParams,
    residual_out: wp.array2d(dtype=wp.float32),
    err_out: wp.array(dtype=wp.float32),
    loglik_out: wp.array(dtype=wp.float32),
    nis_out: wp.array(dtype=wp.float32),
    n_valid_out: wp.array(dtype=wp.int32),
    lam_out: wp.array(dtype=wp.mat33),
    info_out: wp.array(dtype=wp.vec3),
):
    t, lane = wp.tid()
    stride = wp.block_dim()
    b = (row0 + t) // n_per
    p = pos_n[t]
    mat = quat_to_mat_wxyz(quat_nb[t])
    blocked = origin_blocked(grid, p)
    gates = map_not_world(params)
    acc = acc_init()
    macc = modes_init()
    for j in range(lane, cloud.shape[1], stride):
        row = cloud[b, j]
        if row[CR_VALID] == 0.0:
            residual_out[t, j] = wp.nan
        else:
            acc.n_recv = acc.n_recv + 1
            d = mat * row_dir(row)
            tr = float(wp.nan)
            if not blocked:
                tr = cast_unblocked_local(grid, mesh, backend, p, d, step_m, n_bisect)
            res = row[CR_RANGE] - tr
            residual_out[t, j] = res
            if not is_nan(res):
                hit = p + tr * d
                grad = grid_gradient(grid, 1, hit[0], hit[1])
                nrm = wp.vec3(grad[0], grad[1], 1.0)
                den = wp.dot(nrm, d)
                s = wp.vec3()
                if is_finite(den) and wp.abs(den) > 1.0e-3:
                    s = nrm / den
                jac, jac_pos = ray_jacobians(mat, row, res, s)
                u_down = d[2]
                var = ray_var(params, s, u_down)
                vert = float(wp.nan)
                if gates:
                    q = p + row[CR_RANGE] * d
                    vert = -q[2] - grid_surface(grid, q[0], q[1])
                gain = ray_nominal_gain(u_down)
                miss = gross_miss(params, res, var, gain)
                acc_point(acc, params, miss, res, var, gain, vert, axis_weights(row), jac, jac_pos)
    acc = acc_block_total(acc)
    if lane == 0:
        acc_store(t, acc, macc, params, att_cov[b], err_out, loglik_out, nis_out, n_valid_out, lam_out, info_out)


ORIGINAL = {"kernel": kray.raycast_residual_kernel, "block": klik.BLOCK_DIM, "launch": RaycastModel._launch}


def fused_launch(block):
    def _launch(self, pos_n, quat_nb, out, device):
        lead = self.caster.launch_args(self.terrain, device)
        att = self._attitude_cov(device, self.n_filters)
        wp.launch_tiled(fused_kernel, dim=[pos_n.shape[0]],
                        inputs=[*lead, 0, self.n_per, pos_n, quat_nb, self._staged, att, self._params],
                        outputs=[out.residual_m, out.error_m, out.loglik, out.nis, out.n_valid, out.lam, out.info],
                        block_dim=block, device=device)
    return _launch


VARIANTS = {
    "base": {},
    "band": {"kernel": band_residual_kernel},
    "fused64": {"launch": fused_launch(64)},
    "fused128": {"launch": fused_launch(128)},
    "fused256": {"launch": fused_launch(256)},
    "r128": {"block": 128},
}


def apply(name):
    v = {**ORIGINAL, **VARIANTS[name]}
    kray.raycast_residual_kernel = v["kernel"]
    klik.BLOCK_DIM = v["block"]
    RaycastModel._launch = v["launch"]


def model_time(mpf, name, reps=20, rounds=20):
    """Device µs of one model launch at the filter's particles (a graph of ``reps`` launches between events)."""
    apply(name)
    m = mpf.model
    wp.capture_begin(device="cuda:0")
    try:
        for _ in range(reps):
            m.launch(mpf._pos, mpf._quat)
    finally:
        graph = wp.capture_end(device="cuda:0")
    wp.capture_launch(graph)
    times = []
    for _ in range(rounds):
        e0, e1 = wp.Event("cuda:0", enable_timing=True), wp.Event("cuda:0", enable_timing=True)
        stream = wp.get_stream("cuda:0")
        stream.record_event(e0)
        wp.capture_launch(graph)
        stream.record_event(e1)
        wp.synchronize_event(e1)
        times.append(1e3 * wp.get_event_elapsed_time(e0, e1) / reps)
    return statistics.median(times)


def main():
    sid = "S7"
    filters = {}
    for name in VARIANTS:
        apply(name)
        filters[name] = bfs.scenario_filter(sid, "cuda:0")
    setup = filters["base"][3]
    ipm, truth, sensor, world = setup["imu_per_meas"], setup["truth"], setup["sensor"], setup["world"]
    rng = np.random.default_rng(1)
    scans = [sensor.measure(world, truth.pos_n[(it + 1) * ipm], truth.quat_nb[(it + 1) * ipm], rng)
             for it in range(STEPS)]

    class Stepper:  # alternate() steps filters[name][0]: wrap each so that its variant is applied first
        def __init__(self, name, mpf):
            self.name, self.mpf = name, mpf

        def predict_many(self, f, w):
            apply(self.name)
            self.mpf.predict_many(f, w)

        def update(self, scan, sync):
            return self.mpf.update(scan, sync=sync)

    wrapped = {name: (Stepper(name, v[0]), *v[1:]) for name, v in filters.items()}
    times = alternate(wrapped, scans, ipm, STEPS, WARMUP, 1e6)
    est = {name: filters[name][0].estimate().nav.pos_n.tolist() for name in VARIANTS}
    out = {"steps": STEPS, "warmup": WARMUP}
    for name, v in times.items():
        mpf = filters[name][0]
        out[name] = {"step_median_us": statistics.median(v), "p25": float(np.percentile(v, 25)),
                     "p75": float(np.percentile(v, 75)), "model_us": model_time(mpf, name),
                     "same_estimate_as_base": est[name] == est["base"],
                     "estimate_diff_m": float(np.abs(np.subtract(est[name], est["base"])).max())}
        print(name, json.dumps(out[name]), flush=True)
    apply("base")
    with open(sys.argv[2], "w") as fh:
        json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
