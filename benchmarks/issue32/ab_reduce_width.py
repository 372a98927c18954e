"""The block width of the per-particle likelihood reduction on CUDA (``warptan.kernels.likelihood.BLOCK_DIM``, lanes
per particle), one filter per width, stepped in turn in one process (S7, B = 1, N = 500, 20 x 20 scan): the width is
set before each filter is built and captured. Per width: the median synchronised step (µs, steps 100..) and the largest
difference of its history from the first width's (another width sums the points in another order: other bits).
Session 39 on an H100 (``ab_reduce_width_h100.json``): 64 (as it is) 297.8, 32 298.2, 128 300.8 µs
kept 64.

    python3 ab_reduce_width.py SCRIPTS_DIR OUT.json S7 STEPS 64 32 128   (copied outside the checkout)
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

quiet_warp()
out_path, sid, steps = sys.argv[2], sys.argv[3], int(sys.argv[4])
variants = [int(v) for v in sys.argv[5:]]
filters = {}
for v in variants:
    klik.BLOCK_DIM = v
    mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
    scans, ipm = bfs.scenario_scans(setup, steps), setup["imu_per_meas"]
    for it in range(3):
        mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
        mpf.update(scans[it], sync=False)
    wp.synchronize_device("cuda:0")
    filters[v] = [mpf, []]
for it in range(3, steps):
    for v in variants:
        mpf = filters[v][0]
        wp.synchronize_device("cuda:0")
        t0 = time.perf_counter()
        mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
        mpf.update(scans[it], sync=False)
        wp.synchronize_device("cuda:0")
        if it >= 100:
            filters[v][1].append(1e6 * (time.perf_counter() - t0))
res = {}
for v in variants:
    t = filters[v][1]
    res[v] = {"median_us": statistics.median(t), "p25": float(np.percentile(t, 25)), "p75": float(np.percentile(t, 75))}
    h = filters[v][0].history()[:, 0, :]
    res[v]["hist_diff_vs_first"] = float(np.nanmax(np.abs(h - filters[variants[0]][0].history()[:, 0, :])))
print(sid, json.dumps(res))
json.dump(res, open(out_path, "w"), indent=1)
