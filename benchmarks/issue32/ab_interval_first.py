"""In-process A/B of one synchronised S8 / S7 step on CUDA (B = 1, N = 500, 20 × 20 scan): filters with and without
the lean update's early interval and the scan's pinned uploads, stepped alternately in one process so that the host's
drift (large on a shared machine) hits every variant alike; their estimates must be bit-identical.

    python3 benchmarks/issue32/ab_interval_first.py scripts OUT.json   (from a folder outside the checkout)
"""

import json
import statistics
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])  # scripts/: bench_filter_step's scenario setup
import bench_filter_step as bfs

from warptan.device import upload

VARIANTS = {"base": (False, False), "early": (True, False), "pinned": (False, True), "both": (True, True)}
STEPS, WARMUP = 700, 100


class Pageable:
    """The uploads as before: ``assign`` from pageable memory."""

    def put(self, name, array, values):
        upload(array, values)

    def hold(self, buffers):  # (later code holds the scan's device work for the update's graph: not here)
        pass

    def release(self):
        return []

    def later(self, fn):
        return False


def build(sid, early, pinned):
    mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
    mpf._interval_first = early
    if not pinned:
        setup["model"]._uploads = Pageable()
    return mpf, f, w, setup


def alternate(filters: dict, scans: list, ipm: int, steps: int, warmup: int, unit: float) -> dict:
    """Synchronised steps (``ipm`` IMU samples, then the scan) of every filter in turn, the order reversed every other
    step; each filter's step times after ``warmup`` steps (seconds × ``unit``)."""
    names = list(filters)
    times = {name: [] for name in names}
    for it in range(steps):
        for name in (names if it % 2 else names[::-1]):
            mpf, f, w, _ = filters[name]
            k = it * ipm
            wp.synchronize_device("cuda:0")
            t0 = time.perf_counter()
            mpf.predict_many(f[k:k + ipm], w[k:k + ipm])
            mpf.update(scans[it], sync=False)
            wp.synchronize_device("cuda:0")
            if it >= warmup:
                times[name].append(unit * (time.perf_counter() - t0))
    return times


def main():
    out = {}
    for sid in ("S8", "S7"):
        filters = {name: build(sid, *switches) for name, switches in VARIANTS.items()}
        setup = filters["base"][3]
        ipm, truth, sensor, world = setup["imu_per_meas"], setup["truth"], setup["sensor"], setup["world"]
        rng = np.random.default_rng(1)
        scans = [sensor.measure(world, truth.pos_n[(it + 1) * ipm], truth.quat_nb[(it + 1) * ipm], rng)
                 for it in range(STEPS)]
        times = alternate(filters, scans, ipm, STEPS, WARMUP, 1e3)
        est = {name: filters[name][0].estimate().nav.pos_n.tolist() for name in VARIANTS}
        out[sid] = {name: {"median_ms": statistics.median(v), "p25": float(np.percentile(v, 25)),
                           "p75": float(np.percentile(v, 75))} for name, v in times.items()}
        out[sid]["same_estimate"] = all(est[name] == est["base"] for name in VARIANTS)
        print(sid, json.dumps(out[sid]))
    with open(sys.argv[2], "w") as fh:
        json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
