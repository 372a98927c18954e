"""What a pause before a synchronised step costs it on CUDA (one filter of S7, B = 1, N = 500, 20 x 20 scan; session
41): the step's pause alternates between none, 5 ms and 100 ms (a 10 Hz filter's gap) of the host busy-waiting, the host
sleeping, or the host sleeping while the GPU spins a kernel; per mode the medians of the wall time, the host time until
``update`` returns and the device time between events at the step's ends. ``idle_gap_h100.json``: every pause slows the
next step, whichever of the two idled (S7 318 µs back to back, 428–447 after 5 ms, 559–592 after 100 ms): what
``bench_filter_step.py --paced-s`` reports as the paced step.

    python3 idle_gap.py SCRIPTS_DIR OUT.json S7 STEPS   (copied outside the checkout)
"""
import json
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


@wp.func_native('''
#if defined(__CUDA_ARCH__)
long long s = clock64(); while (clock64() - s < cycles) {}
#endif
''')
def spin(cycles: wp.int64): ...


@wp.kernel
def spin_kernel(cycles: wp.int64):
    spin(cycles)


def busy(s):
    t = time.perf_counter() + s
    while time.perf_counter() < t:
        pass


def gpu_spin(s):
    wp.launch(spin_kernel, dim=1, inputs=[wp.int64(int(s * 1.75e9))], device="cuda:0")
    time.sleep(s)
    wp.synchronize_device("cuda:0")


MODES = {"none": lambda: None, "busy5ms": lambda: busy(0.005), "sleep5ms": lambda: time.sleep(0.005),
         "gpuspin5ms+sleep": lambda: gpu_spin(0.005), "sleep100ms": lambda: time.sleep(0.1),
         "busy100ms": lambda: busy(0.1), "gpuspin100ms+sleep": lambda: gpu_spin(0.1)}
names = list(MODES)
rows = {k: [] for k in names}
stream = wp.get_stream("cuda:0")
gpu_spin(0.001)
for it in range(steps):
    mode = names[it % len(names)]
    wp.synchronize_device("cuda:0")
    MODES[mode]()
    e0, e1 = wp.Event("cuda:0", enable_timing=True), wp.Event("cuda:0", enable_timing=True)
    t0 = time.perf_counter()
    stream.record_event(e0)
    mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
    mpf.update(scans[it], sync=False)
    t1 = time.perf_counter()
    stream.record_event(e1)
    wp.synchronize_device("cuda:0")
    t2 = time.perf_counter()
    if it >= 70:
        rows[mode].append((1e6 * (t2 - t0), 1e6 * (t1 - t0), 1e3 * wp.get_event_elapsed_time(e0, e1)))
res = {}
for k, v in rows.items():
    a = np.array(v)
    res[k] = {"n": len(v), "wall_us": round(float(np.median(a[:, 0])), 1),
              "host_us": round(float(np.median(a[:, 1])), 1), "device_us": round(float(np.median(a[:, 2])), 1),
              "wall_p25_p75": [round(float(x), 1) for x in np.percentile(a[:, 0], [25, 75])]}
    print(sid, k, res[k], flush=True)
json.dump(res, open(out_path, "w"), indent=1)
