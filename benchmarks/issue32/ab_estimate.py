"""What a host call between two synchronised filter steps costs the next step, on CUDA (S8 / S7, B = 1, N = 500,
20 x 20 scan), and what it costs itself: after each step one of ``none``, ``estimate`` (``mpf.estimate()``),
``moments`` and ``nav_numpy`` (the pieces the estimate was made of before its packed read-out: ``mpf.moments()``,
its own two launches and copy up to d777296 and the read-out since, and ``.numpy()`` of the six nominal-INS / P
arrays), ``sleep1ms`` and ``gc`` (``gc.collect()``: a host whose caches were
swept), in turn; medians of the next step's predict, update and whole step (µs), and of each call's own time.

    python3 benchmarks/issue32/ab_estimate.py scripts OUT.json STEPS S8 S7   (from a folder outside the checkout)
"""
import gc
import json
import statistics
import sys
import time

import warp as wp

sys.path.insert(0, sys.argv[1])  # scripts/: bench_filter_step's scenario setup
import bench_filter_step as bfs

from warptan.device import quiet_warp

MODES = ["none", "estimate", "moments", "nav_numpy", "sleep1ms", "gc"]
WARM = 50


def between(mpf, mode: str) -> None:
    if mode == "estimate":
        mpf.estimate()
    elif mode == "moments":
        mpf.moments()
    elif mode == "nav_numpy":
        [v.numpy() for v in mpf._nav.values()]
    elif mode == "sleep1ms":
        time.sleep(0.001)
    elif mode == "gc":
        gc.collect()


def main():
    quiet_warp()
    out_path, steps = sys.argv[2], int(sys.argv[3])
    res = {}
    for sid in sys.argv[4:]:
        mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
        ipm, scans = setup["imu_per_meas"], bfs.scenario_scans(setup, steps)
        after = {m: {"predict": [], "update": [], "step": []} for m in MODES}
        cost = {m: [] for m in MODES}
        prev = "none"
        for it in range(steps):
            k = it * ipm
            wp.synchronize_device("cuda:0")
            t0 = time.perf_counter()
            mpf.predict_many(f[k:k + ipm], w[k:k + ipm])
            t1 = time.perf_counter()
            mpf.update(scans[it], sync=False)
            wp.synchronize_device("cuda:0")
            t2 = time.perf_counter()
            if it >= WARM:
                for name, v in (("predict", t1 - t0), ("update", t2 - t1), ("step", t2 - t0)):
                    after[prev][name].append(1e6 * v)
            prev = MODES[it % len(MODES)]
            t3 = time.perf_counter()
            between(mpf, prev)
            if it >= WARM:
                cost[prev].append(1e6 * (time.perf_counter() - t3))
        res[sid] = {"next_step_us": {m: {k: statistics.median(v) for k, v in d.items()} for m, d in after.items()},
                    "call_us": {m: statistics.median(v) for m, v in cost.items()}}
        print(sid, json.dumps({m: round(d["step"], 1) for m, d in res[sid]["next_step_us"].items()}),
              json.dumps({m: round(v, 1) for m, v in res[sid]["call_us"].items()}))
    bfs.write_cuda_results(out_path, sys.argv, __doc__, res)


if __name__ == "__main__":
    main()
