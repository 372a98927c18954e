"""Is the host's staging of a scan on a synchronised step's critical path, on CUDA (S8 / S7, B = 1, N = 500, 20 x 20
scan)? A busy-wait of D µs is inserted (``a``) after the model's ``stage`` (the scan staged, the update's graph not yet
launched; the update's head already queued) or (``b``) after ``update()`` returns (before the synchronisation); the
steps take the cases in turn; medians of the synchronised step (µs). A slope of ~1 in ``a`` means the device waits for
the host's staging; 0 means the device's work queued before it (the interval, the moves) still runs when the staging
ends.

    python3 benchmarks/issue32/host_slope.py scripts OUT.json STEPS S7 S8   (from a folder outside the checkout)
"""
import json
import statistics
import sys
import time

import warp as wp

sys.path.insert(0, sys.argv[1])  # scripts/: bench_filter_step's scenario setup
import bench_filter_step as bfs

from warptan.device import quiet_warp

CASES = [("a", 0), ("a", 20), ("a", 40), ("b", 20), ("b", 40)]
WARM = 100


def spin(us: float) -> None:
    end = time.perf_counter() + us * 1e-6
    while time.perf_counter() < end:
        pass


def main():
    quiet_warp()
    out_path, steps = sys.argv[2], int(sys.argv[3])
    res = {}
    for sid in sys.argv[4:]:
        mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
        scans, ipm = bfs.scenario_scans(setup, steps), setup["imu_per_meas"]
        raw_stage, delay = mpf.model.stage, {"a": 0}

        def stage(*a, raw_stage=raw_stage, delay=delay, **k):
            out = raw_stage(*a, **k)
            spin(delay["a"])
            return out
        mpf.model.stage = stage
        times = {c: [] for c in CASES}
        for it in range(steps):
            where, d = CASES[it % len(CASES)]
            delay["a"] = d if where == "a" else 0
            wp.synchronize_device("cuda:0")
            t0 = time.perf_counter()
            mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
            mpf.update(scans[it], sync=False)
            if where == "b":
                spin(d)
            wp.synchronize_device("cuda:0")
            if it >= WARM:
                times[(where, d)].append(1e6 * (time.perf_counter() - t0))
        res[sid] = {f"{where}{d}": statistics.median(v) for (where, d), v in times.items()}
        print(sid, json.dumps({k: round(v, 1) for k, v in res[sid].items()}))
    bfs.write_cuda_results(out_path, sys.argv, __doc__, res)


if __name__ == "__main__":
    main()
