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
    p.add_argument("--json", dest="json_out")
    args = p.parse_args(argv)
    import warptan.filter.mpf as mpf
    import warptan.sensing.sensors as sensors
    from warptan.meta import run_meta
    from warptan.sim.scenarios import run_scenario

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

    extra = {"bound": False} if "bound" in inspect.signature(run_scenario).parameters else {}
    world = {"world_error_rms_m": 5.0, "world_error_corr_m": 1000.0, "world_seed": 2000}
    rows = []
    for config, kw in (("map=world", {}), ("world", world)):
        run_scenario(args.scenario, 0, args.device, particles=500, duration_s=3.0, **extra, **kw)
        spent.clear()
        r = run_scenario(args.scenario, 0, args.device, particles=500, duration_s=args.duration_s, **extra, **kw)
        stamps = np.array([t for t, _ in spent["update"]])
        rate = (len(stamps) - 1) / max(r.run.t_s[-1] - r.run.t_s[0], 1e-9)  # updates per flight second
        per = max(round(SEGMENT_S * rate), 1)
        period = np.diff(stamps)
        segments = range(int(np.ceil(len(stamps) / per)))
        row = {"scenario": args.scenario, "config": config, "wall_s": r.wall_s, "updates": len(stamps),
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
        print(f"{args.scenario} {config}: period per {SEGMENT_S:.0f} s (ms) {np.round(row['period_ms'], 3)}",
              flush=True)
        for key, values in sorted(row["host_us_per_update"].items(), key=lambda kv: -sum(kv[1])):
            print(f"   {key:32s} " + " ".join(f"{v:7.1f}" for v in values) + "  µs/update")
    if args.json_out:
        meta = run_meta((args.device,), what="host time per update of whole runs, per 30 s of flight", label=args.label)
        with open(args.json_out, "w") as f:
            json.dump({"meta": meta, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
