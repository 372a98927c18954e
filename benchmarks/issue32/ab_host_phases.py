"""In-process A/B of filter switches (attributes set after construction) for one synchronised S8 / S7 step on CUDA
(B = 1, N = 500, 20 x 20 scan: the variants stepped alternately, so that the host's drift hits them alike; their
estimates must be bit-identical), then the host time of each phase of the default filter's step (methods wrapped
with a clock: inclusive times, medians and per-step means).

    python3 benchmarks/issue32/ab_host_phases.py scripts OUT.json S8 S7   (from a folder outside the checkout)
"""
import functools
import inspect
import json
import statistics
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])  # scripts/: bench_filter_step's scenario setup
import bench_filter_step as bfs
from ab_interval_first import alternate  # (this folder)

STEPS, WARM = 500, 100
VARIANTS = {"base": {}, "noahead": {"_run_ahead": False}}


def build(sid, sw):
    mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
    for k, v in sw.items():
        setattr(mpf, k, v)
    return mpf, f, w, setup


def phases(mpf, f, w, scans, ipm, k0):
    cls, mcls = type(mpf), type(mpf.model)
    acc = {}
    saved = []

    def wrap(owner, name, label):
        raw = inspect.getattr_static(owner, name)
        fn = getattr(owner, name)
        saved.append((owner, name, raw))

        @functools.wraps(fn)
        def g(*a, **kw):
            t = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                acc.setdefault(label, []).append(time.perf_counter() - t)
        setattr(owner, name, staticmethod(g) if isinstance(raw, staticmethod) else g)

    for name in ("predict_many", "_buffer", "_advance", "update", "_stage_interval", "_queue_head", "_stage_scan",
                 "_queue_update", "_next_set", "_ensure_history", "_replay", "_record_key", "_head_first"):
        if hasattr(cls, name):
            wrap(cls, name, "mpf." + name)
    for name in ("check", "stage", "_fill", "_ensure_modes", "_buffers", "_meta", "_check_poses", "_m_of"):
        if hasattr(mcls, name):
            wrap(mcls, name, "model." + name)
    wrap(wp, "capture_launch", "wp.capture_launch")
    wrap(wp, "synchronize_device", "wp.synchronize_device")
    n = 0
    try:
        for it in range(len(scans)):
            k = k0 + it * ipm
            wp.synchronize_device("cuda:0")
            mpf.predict_many(f[k:k + ipm], w[k:k + ipm])
            mpf.update(scans[it], sync=False)
            wp.synchronize_device("cuda:0")
            n += 1
    finally:
        for owner, name, fn in reversed(saved):
            setattr(owner, name, fn)
    return {k: {"us_per_step": 1e6 * sum(v) / n, "calls_per_step": len(v) / n, "median_us": 1e6 * statistics.median(v)}
            for k, v in sorted(acc.items(), key=lambda kv: -sum(kv[1]))}


out = {}
for sid in sys.argv[3:]:
    filters = {name: build(sid, sw) for name, sw in VARIANTS.items()}
    setup = filters["base"][3]
    ipm, truth, sensor, world = setup["imu_per_meas"], setup["truth"], setup["sensor"], setup["world"]
    rng = np.random.default_rng(1)
    total = STEPS + 200
    scans = [sensor.measure(world, truth.pos_n[(it + 1) * ipm], truth.quat_nb[(it + 1) * ipm], rng)
             for it in range(total)]
    times = alternate(filters, scans, ipm, STEPS, WARM, 1e6)
    est = {name: filters[name][0].estimate().nav.pos_n.tolist() for name in VARIANTS}
    row = {name: {"median_us": statistics.median(v), "p25": float(np.percentile(v, 25)),
                  "p75": float(np.percentile(v, 75))} for name, v in times.items()}
    row["same_estimate"] = all(est[n] == est["base"] for n in VARIANTS)
    mpf, f, w, _ = filters["base"]
    row["phases_base"] = phases(mpf, f, w, scans[STEPS:], ipm, STEPS * ipm)
    out[sid] = row
    print(sid, json.dumps({k: v for k, v in row.items() if k != "phases_base"}))
    for k, v in list(row["phases_base"].items())[:24]:
        print(f"   {k:28s} {v['us_per_step']:7.1f} us/step  {v['calls_per_step']:.2f} calls  med {v['median_us']:.1f}")
json.dump(out, open(sys.argv[2], "w"), indent=1)
