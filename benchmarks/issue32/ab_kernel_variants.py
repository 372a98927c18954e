"""Bit-neutral compile variants of the update's CUDA kernels, one filter each, stepped in turn in one process (S7, B =
1, N = 500, 20 x 20 scan): a kernel (``ray``: the ray casts' residual kernel, ``nav``: the nav interval, ``stage`` /
``record``: the stage and record blocks) is swapped for the same Python function compiled with another register cap
(``cuda_max_registers``, 0: the compiler's) and optionally shared-memory spilling, for the filter built and captured
while it was in place. Per variant: the median synchronised step (µs, steps 100.. of each filter), the device time of
the scenario's model (20 launches in a graph, median of 20 replays) and whether its whole history equals the base
filter's (the same bits). Session 39 on an H100 (``ab_kernel_variants_h100.json``): every variant was slower or
level
none kept.

    python3 ab_kernel_variants.py SCRIPTS_DIR OUT.json S7 STEPS SLOT:CAP:SPILL ...   (copied outside the checkout)
"""
import json
import statistics
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])
import bench_filter_step as bfs

from warptan.device import quiet_warp
from warptan.kernels import likelihood as klik
from warptan.kernels import mpf as kmpf
from warptan.kernels import nav as knav
from warptan.kernels import raycast as kray

quiet_warp()
out_path, sid, steps = sys.argv[2], sys.argv[3], int(sys.argv[4])
SLOTS = {"ray": (kray, "raycast_residual_kernel"), "nav": (knav.nav_interval_kernels, True),
         "stage": (kmpf, "stage_block_kernel"), "record": (kmpf, "record_block_kernel"),
         "reduce": (klik.reduce_loglik_kernels, (True, False))}
def get(slot):
    o, k = SLOTS[slot]
    return o[k] if isinstance(o, dict) else getattr(o, k)
def put(slot, kern):
    o, k = SLOTS[slot]
    if isinstance(o, dict):
        o[k] = kern
    else:
        setattr(o, k, kern)
bases = {s: get(s) for s in SLOTS}
variants = {"base": None}
for spec in sys.argv[5:]:
    slot, cap, spill = spec.split(":")
    variants[spec] = (slot, wp.kernel(bases[slot].func, cuda_max_registers=int(cap) or None,
                                      enable_cuda_smem_spilling=bool(int(spill)), module="unique"))
filters = {}
for name, v in variants.items():
    for sl in SLOTS:
        put(sl, bases[sl])
    if v is not None:
        put(*v)
    mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
    scans, ipm = bfs.scenario_scans(setup, steps), setup["imu_per_meas"]
    try:
        t0 = time.perf_counter()
        for it in range(5):
            mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
            mpf.update(scans[it], sync=False)
        wp.synchronize_device("cuda:0")
        with wp.ScopedCapture("cuda:0") as cap:
            for _ in range(20):
                mpf.model.launch(mpf._pos, mpf._quat)
        filters[name] = [mpf, cap.graph, []]
        print("ready", name, round(time.perf_counter() - t0, 1), flush=True)
    except Exception as e:
        print("variant failed", name, repr(e)[:300], flush=True)
variants = {k: v for k, v in variants.items() if k in filters}
for sl in SLOTS:
    put(sl, bases[sl])
for it in range(5, steps):
    for name in variants:
        mpf = filters[name][0]
        wp.synchronize_device("cuda:0")
        t0 = time.perf_counter()
        mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
        mpf.update(scans[it], sync=False)
        wp.synchronize_device("cuda:0")
        if it >= 100:
            filters[name][2].append(1e6 * (time.perf_counter() - t0))
res = {}
h0 = filters["base"][0].history()
for name in variants:
    g = filters[name][1]
    ts = []
    for _ in range(20):
        e0, e1 = wp.Event("cuda:0", enable_timing=True), wp.Event("cuda:0", enable_timing=True)
        wp.get_stream("cuda:0").record_event(e0)
        wp.capture_launch(g)
        wp.get_stream("cuda:0").record_event(e1)
        wp.synchronize_device("cuda:0")
        ts.append(1e3 * wp.get_event_elapsed_time(e0, e1) / 20)
    t = filters[name][2]
    res[name] = {"step_median_us": statistics.median(t), "p25": float(np.percentile(t, 25)),
                 "p75": float(np.percentile(t, 75)), "model_us": statistics.median(ts),
                 "same_history_as_base": bool(np.array_equal(filters[name][0].history(), h0, equal_nan=True))}
print(sid, json.dumps(res))
json.dump(res, open(out_path, "w"), indent=1)
