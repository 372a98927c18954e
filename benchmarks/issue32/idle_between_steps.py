"""What the host does between two synchronised steps changes the next step (one filter of S7 / S8 on CUDA, B = 1;
session 41): before each step, alternately nothing, ``estimate()``, ``estimate()`` and ``gc.collect()``, ``estimate()``
with the collector off during the step, 0.5 ms sleeping or busy-waiting, 5 ms sleeping; medians of the step's wall time
per mode (``idle_between_steps_h100.json``).

    python3 idle_between_steps.py SCRIPTS_DIR OUT.json S7 STEPS   (copied outside the checkout)
"""
import gc
import json
import statistics
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])
import bench_filter_step as bfs

from warptan.device import quiet_warp

quiet_warp()
out_path, sid, steps = sys.argv[2], sys.argv[3], int(sys.argv[4])
mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
scans, ipm = bfs.scenario_scans(setup, steps), setup["imu_per_meas"]


def busy(s):
    t = time.perf_counter() + s
    while time.perf_counter() < t:
        pass


MODES = {
    "none": lambda: None,
    "estimate": lambda: mpf.estimate(),
    "estimate+gc": lambda: (mpf.estimate(), gc.collect()),
    "estimate,gc-off": lambda: mpf.estimate(),
    "sleep0.5ms": lambda: time.sleep(0.0005),
    "busy0.5ms": lambda: busy(0.0005),
    "sleep5ms": lambda: time.sleep(0.005),
}
names = list(MODES)
times = {k: [] for k in names}
for it in range(steps):
    mode = names[it % len(names)]
    wp.synchronize_device("cuda:0")
    MODES[mode]()
    wp.synchronize_device("cuda:0")
    if mode == "estimate,gc-off":
        gc.disable()
    t0 = time.perf_counter()
    mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
    mpf.update(scans[it], sync=False)
    wp.synchronize_device("cuda:0")
    t = 1e6 * (time.perf_counter() - t0)
    gc.enable()
    if it >= 70:
        times[mode].append(t)
res = {k: {"median_us": round(statistics.median(v), 1), "p25": round(float(np.percentile(v, 25)), 1),
           "p75": round(float(np.percentile(v, 75)), 1), "n": len(v)} for k, v in times.items()}
for k, v in res.items():
    print(sid, k, v, flush=True)
json.dump(res, open(out_path, "w"), indent=1)
