"""In-process A/B of one synchronised S7 / S8 step on CUDA (B = 1, N = 500, 20 x 20 scan) between the code as it is
and an older tree imported as another package (its ``warptan`` renamed ``warptan_old``, and its
``scripts/bench_filter_step.py`` as ``bench_filter_step_old`` with the same renaming): one filter of each, stepped
alternately (the order reversed every other step) so that the host's drift hits both alike; each filter's scans are
its own package's, drawn from the same seed. Their estimates must be bit-identical when the change keeps the bits.

    python3 benchmarks/issue32/ab_two_trees.py scripts OLD_DIR OUT.json [S7 S8]   (from a folder outside the checkout)
"""
import json
import statistics
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])  # scripts/: bench_filter_step's scenario setup
sys.path.insert(0, sys.argv[2])  # the old tree: warptan_old, bench_filter_step_old
import bench_filter_step as bfs_new
import bench_filter_step_old as bfs_old

STEPS, WARMUP = 900, 100
DEV = "cuda:0"


def main():
    out = {}
    for sid in sys.argv[4:] or ("S7", "S8"):
        filters = {}
        for name, mod in (("old", bfs_old), ("new", bfs_new)):
            mpf, f, w, setup = mod.scenario_filter(sid, DEV)
            ipm, truth, sensor, world = setup["imu_per_meas"], setup["truth"], setup["sensor"], setup["world"]
            rng = np.random.default_rng(1)
            scans = [sensor.measure(world, truth.pos_n[(it + 1) * ipm], truth.quat_nb[(it + 1) * ipm], rng)
                     for it in range(STEPS)]
            filters[name] = (mpf, f, w, ipm, scans)
        times = {name: [] for name in filters}
        names = list(filters)
        for it in range(STEPS):
            for name in (names if it % 2 else names[::-1]):
                mpf, f, w, ipm, scans = filters[name]
                k = it * ipm
                wp.synchronize_device(DEV)
                t0 = time.perf_counter()
                mpf.predict_many(f[k:k + ipm], w[k:k + ipm])
                mpf.update(scans[it], sync=False)
                wp.synchronize_device(DEV)
                if it >= WARMUP:
                    times[name].append(1e6 * (time.perf_counter() - t0))
        est = {name: filters[name][0].estimate().nav.pos_n.tolist() for name in filters}
        out[sid] = {name: {"median_us": statistics.median(v), "p25": float(np.percentile(v, 25)),
                           "p75": float(np.percentile(v, 75))} for name, v in times.items()}
        out[sid]["same_estimate"] = est["old"] == est["new"]
        print(sid, json.dumps(out[sid]), flush=True)
    with open(sys.argv[3], "w") as fh:
        json.dump({"steps": STEPS, "warmup": WARMUP, "results": out}, fh, indent=1)


if __name__ == "__main__":
    main()
