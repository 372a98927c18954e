#!/usr/bin/env python3
"""Where a whole run's time per measurement update goes on the host (issue 65's GPU cost): S8 (or another scenario)
over its own map and over a world whose map errs by 5 m RMS correlated over 1 km (the learner on), one run each after
a short one that compiles; the loop's period (between consecutive ``update`` calls: the update, the IMU's prediction
and the simulator's sensor, which waits for the device's queue) and the host time of the pieces, per 30 s of flight
(a cost that grew along the flight would show as a trend).

The pieces are timed by wrapping the filter's and the sensor's methods with ``time.perf_counter`` stamps (private
methods: this is a profiler, not an API). It runs with whichever warptan is importable, so an older checkout runs the
same rows (``PYTHONPATH=/path/to/old``):

    python scripts/profile_update_host.py --device cuda:0 --label new --json new.json

A GPU host's speed drifts between runs by a third and more; ``--rounds K`` flies the configurations in turn K times in
one process (``world-off`` too: the same world with the learner off, nothing stated, where the checkout has the
learner), each round's rows side by side. Each row also gives the median update time of the plain updates and of those
that read the revisit memory (``_read_again``) or the learner (``_learn_map_error``), and the update's device time
from the filter's own timers (:class:`warptan.filter.records.StepTimer`: CUDA events around its work, in a graph).
``--kernels`` (CUDA) flies each configuration once more with eager launches and Warp's kernel timing
(``wp.timing_begin``) and gives each kernel's and copy's device time per update (eager launches: the sums are larger
than a graph's, the per-kernel shares are what it shows).
"""

from __future__ import annotations

import argparse
import collections
import inspect
import json
import time

import numpy as np

SEGMENT_S = 30.0
PIECES = ("update", "predict_many", "_stage_scan", "_queue_update", "_queue_head", "_stage_interval", "_next_set",
          "_learn_map_error", "_read_again")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default="S8")
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--duration-s", type=float, default=120.0)
    p.add_argument("--label", default="this checkout")
    p.add_argument("--rounds", type=int, default=1, help="configurations flown in turn this many times")
    p.add_argument("--kernels", action="store_true", help="(CUDA) per-kernel device time, eager launches")
    p.add_argument("--json", dest="json_out")
    args = p.parse_args(argv)
    import warptan.filter.mpf as mpf
    import warptan.sensing.sensors as sensors
    from warptan.meta import run_meta
    from warptan.sim.scenarios import run_scenario

    try:
        from warptan.filter.records import StepTimer
    except ImportError:  # (an older checkout)
        StepTimer = None

    spent: dict[str, list[float]] = collections.defaultdict(list)  # piece -> per update call, (t_start, seconds)

    def wrap(cls, name, key):
        f = getattr(cls, name)

        def timed(*a, **k):
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                spent[key].append((t, time.perf_counter() - t))
        setattr(cls, name, timed)

    for name in PIECES:
        if hasattr(mpf.MarginalizedParticleFilter, name):
            wrap(mpf.MarginalizedParticleFilter, name, name)
    for cls in vars(sensors).values():
        if isinstance(cls, type) and "measure_many" in vars(cls):
            wrap(cls, "measure_many", f"{cls.__name__}.measure_many")

    filters = []  # (the filters a run made: their timers)
    made = mpf.MarginalizedParticleFilter.__init__

    def init(self, *a, **k):
        made(self, *a, **k)
        if StepTimer is not None:
            self.timer = StepTimer()
        filters.append(self)
    mpf.MarginalizedParticleFilter.__init__ = init

    extra = {"bound": False} if "bound" in inspect.signature(run_scenario).parameters else {}
    world = {"world_error_rms_m": 5.0, "world_error_corr_m": 1000.0, "world_seed": 2000}
    configs = [("map=world", {}), ("world", world)]
    if "map_error_learn" in inspect.signature(run_scenario).parameters or hasattr(mpf, "MapErrorLearner"):
        configs.append(("world-off", {**world, "map_error_learn": False}))
    for _config, kw in configs:
        run_scenario(args.scenario, 0, args.device, particles=500, duration_s=3.0, **extra, **kw)
    rows = []
    for rnd, (config, kw) in ((k, c) for k in range(args.rounds) for c in configs):
        spent.clear()
        filters.clear()
        r = run_scenario(args.scenario, 0, args.device, particles=500, duration_s=args.duration_s, **extra, **kw)
        stamps = np.array([t for t, _ in spent["update"]])
        rate = (len(stamps) - 1) / max(r.run.t_s[-1] - r.run.t_s[0], 1e-9)  # updates per flight second
        per = max(round(SEGMENT_S * rate), 1)
        period = np.diff(stamps)
        segments = range(int(np.ceil(len(stamps) / per)))
        row = {"scenario": args.scenario, "config": config, "round": rnd, "wall_s": r.wall_s, "updates": len(stamps),
               "period_median_ms": 1e3 * float(np.median(period)), "update_median_ms": _by_kind(spent, stamps),
               "device_ms": _device_ms(filters),
               "period_ms": [1e3 * float(period[i * per:(i + 1) * per].mean()) for i in segments
                             if len(period[i * per:(i + 1) * per])],
               "host_us_per_update": {}}
        for key, calls in spent.items():
            t0 = np.array([t for t, _ in calls])
            dt = np.array([d for _, d in calls])
            seg = np.searchsorted(stamps, t0, side="right") - 1  # the update each call belongs to
            row["host_us_per_update"][key] = [1e6 * float(dt[(seg // per) == i].sum()) / min(per, len(stamps) - i * per)
                                              for i in segments]
        rows.append(row)
        print(f"{args.scenario} {config} (round {rnd}): wall {r.wall_s:.3f} s, period per {SEGMENT_S:.0f} s (ms) "
              f"{np.round(row['period_ms'], 3)}, median {row['period_median_ms']:.3f}; update median (ms) "
              f"{ {k: round(v, 3) for k, v in row['update_median_ms'].items()} }; device (ms) {row['device_ms']}",
              flush=True)
        for key, values in sorted(row["host_us_per_update"].items(), key=lambda kv: -sum(kv[1])):
            print(f"   {key:32s} " + " ".join(f"{v:7.1f}" for v in values) + "  µs/update")
    if args.kernels and args.device.startswith("cuda"):
        rows += _kernel_rows(args, configs, extra, run_scenario, mpf)
    if args.json_out:
        meta = run_meta((args.device,), what="host time per update of whole runs, per 30 s of flight", label=args.label)
        with open(args.json_out, "w") as f:
            json.dump({"meta": meta, "rows": rows}, f, indent=1)
    return 0


def _by_kind(spent: dict, stamps: np.ndarray) -> dict[str, float]:
    """Median update time (ms) of the plain updates and of those that read the revisit memory or the learner."""
    update = np.array([d for _, d in spent["update"]])
    kinds = {}
    for key in ("_read_again", "_learn_map_error"):
        mark = np.zeros(len(update), dtype=bool)
        if spent.get(key):
            mark[np.searchsorted(stamps, np.array([t for t, _ in spent[key]]), side="right") - 1] = True
            kinds[key] = mark
    plain = ~np.any(list(kinds.values()), axis=0) if kinds else np.ones(len(update), dtype=bool)
    out = {"plain": 1e3 * float(np.median(update[plain]))}
    out.update({key: 1e3 * float(np.median(update[mark])) for key, mark in kinds.items()})
    return out


def _device_ms(filters: list) -> dict[str, float] | None:
    """Median and mean device time (ms) of the run's updates from its filter's timer (None without one)."""
    timer = getattr(filters[0], "timer", None) if filters else None
    if timer is None:
        return None
    device = timer.times()["device"]
    return {"median": float(np.median(device)), "mean": float(np.mean(device))}


def _kernel_rows(args, configs, extra, run_scenario, mpf) -> list[dict]:
    """Each configuration flown once more with eager launches (no graph) under Warp's kernel timing: each kernel's,
    copy's and memset's device time per update (µs) and its launches."""
    import warp as wp

    made = mpf.MarginalizedParticleFilter.__init__

    def eager(self, *a, **k):
        made(self, *a, **{**k, "graph": False})
    mpf.MarginalizedParticleFilter.__init__ = eager
    rows = []
    for config, kw in configs:
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
        r = run_scenario(args.scenario, 0, args.device, particles=500, duration_s=args.duration_s, **extra, **kw)
        results = wp.timing_end()
        updates = len(r.run.t_s) - 1
        per = collections.defaultdict(lambda: [0, 0.0])
        for item in results:
            name = item.name.replace("forward kernel ", "").rsplit("_", 1)[0] if "kernel" in item.name else item.name
            per[name][0] += 1
            per[name][1] += item.elapsed
        kernels = {k: {"launches": n, "us_per_update": 1e3 * t / updates}
                   for k, (n, t) in sorted(per.items(), key=lambda kv: -kv[1][1])}
        rows.append({"scenario": args.scenario, "config": config, "eager_kernels": kernels,
                     "device_us_per_update": sum(v["us_per_update"] for v in kernels.values())})
        print(f"{args.scenario} {config} (eager): {rows[-1]['device_us_per_update']:.1f} µs of device time an update")
        for k, v in list(kernels.items())[:12]:
            print(f"   {k[:60]:60s} {v['launches']:6d} {v['us_per_update']:7.1f} µs/update")
    mpf.MarginalizedParticleFilter.__init__ = made
    return rows


if __name__ == "__main__":
    raise SystemExit(main())
