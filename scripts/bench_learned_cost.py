#!/usr/bin/env python3
"""What learning the map's error in flight costs (issue 65): whole runs of scenarios on one device, the map the world
(learning off: nothing to learn) and over a world whose map errs by 5 m RMS correlated over 1 km (learning on by
default; ``world-off``: the learner off, nothing stated: no map-error modes at all), flight time over the median wall
time of ``--repeats`` runs after a short run that compiles, and the wall time per measurement update.

The script runs with whichever warptan is importable, so an older checkout (before the learner: its ``world`` row is
the filter as it was, told nothing) and this one run the same rows on the same machine one after the other
(``--label`` names each in the JSON):

    python scripts/bench_learned_cost.py --device cpu --label new --json new.json
    PYTHONPATH=/path/to/old python scripts/bench_learned_cost.py --device cpu --label old --json old.json

Runs alternated several times (new, old, new, old, …: a machine's speed drifts between runs) are pooled into one file,
each row's walls from every run of its code and its medians from them:

    python scripts/bench_learned_cost.py --pool new1.json old1.json new2.json old2.json --json cost.json
"""

from __future__ import annotations

import argparse
import inspect
import json
import statistics
import sys

WORLD = {"world_error_rms_m": 5.0, "world_error_corr_m": 1000.0, "world_seed": 2000}


def rows_for(sid: str, device: str, duration_s: float, repeats: int, n: int) -> list[dict]:
    from warptan.sim.scenarios import run_scenario

    extra = {"bound": False} if "bound" in inspect.signature(run_scenario).parameters else {}
    learner = "map_error_learn" in inspect.signature(run_scenario).parameters or _knows_learning()
    configs = [("map=world", {}), ("world", WORLD)] + ([("world-off", {**WORLD, "map_error_learn": False})]
                                                        if learner else [])
    rows = []
    for name, kw in configs:
        run_scenario(sid, 0, device, particles=n, duration_s=3.0, **extra, **kw)
        runs = [run_scenario(sid, 0, device, particles=n, duration_s=duration_s, **extra, **kw)
                for _ in range(repeats)]
        walls = [r.wall_s for r in runs]
        wall = statistics.median(walls)
        updates = len(runs[0].run.t_s) - 1
        rows.append({"scenario": sid, "config": name, "device": device, "particles": n, "flight_s": duration_s,
                     "walls_s": walls, "real_time_factor": duration_s / wall, "ms_per_update": 1e3 * wall / updates,
                     "learned_m": runs[0].run.info.get("map_error_learned_m")})
        print(f"{sid} {name:10s} {device}: RTF {duration_s / wall:6.1f}, {1e3 * wall / updates:6.2f} ms/update",
              flush=True)
    return rows


def pool(paths: list[str]) -> dict:
    """The rows of several runs' files pooled by (code label, scenario, config, device, particles, flight): every
    run's walls, and the real-time factor and time per update from their median (the number of updates a row's
    median wall is divided by is the run's own: ``flight_s / ms_per_update``)."""
    runs, pooled = [], {}
    for path in paths:
        with open(path) as f:
            data = json.load(f)
        meta = data["meta"]
        runs.append({**meta, "file": path})
        for row in data["rows"]:
            key = (meta.get("label"), row["scenario"], row["config"], row["device"], row["particles"], row["flight_s"])
            updates = round(1e3 * statistics.median(row["walls_s"]) / row["ms_per_update"])
            have = pooled.setdefault(key, {**row, "code": meta.get("label"), "walls_s": [], "runs": 0,
                                           "updates": updates})
            have["walls_s"] += row["walls_s"]
            have["runs"] += 1
    rows = []
    for row in pooled.values():
        wall = statistics.median(row["walls_s"])
        rows.append({**row, "real_time_factor": row["flight_s"] / wall, "ms_per_update": 1e3 * wall / row["updates"]})
    labels = sorted({str(r.get("label")) for r in runs})
    return {"meta": {**runs[0], "label": " and ".join(labels) + f", {len(runs)} runs alternated", "runs": runs},
            "rows": rows}


def _knows_learning() -> bool:
    import importlib

    for name in ("warptan.sensing.learner", "warptan.sensing.likelihood"):  # (where it lives; where it lived)
        try:
            if hasattr(importlib.import_module(name), "MapErrorLearner"):
                return True
        except ImportError:
            continue
    return False


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", nargs="+", default=["S8", "S7"])
    p.add_argument("--device", default="cpu")
    p.add_argument("--duration-s", type=float, default=30.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--n", type=int, default=500)
    p.add_argument("--label", default="this checkout")
    p.add_argument("--json", dest="json_out")
    p.add_argument("--pool", nargs="+", metavar="JSON", help="pool the rows of these runs' files into --json")
    args = p.parse_args(argv)
    if args.pool:
        if not args.json_out:
            p.error("--pool needs --json")
        with open(args.json_out, "w") as f:
            json.dump(pool(args.pool), f, indent=1)
        return 0
    from warptan.meta import run_meta

    rows = [r for sid in args.scenarios for r in rows_for(sid, args.device, args.duration_s, args.repeats, args.n)]
    if args.json_out:
        meta = run_meta((args.device,), what="whole scenario runs: real_time_factor = flight_s / median(walls_s), "
                        "ms_per_update = median wall / updates; world: 5 m RMS over 1 km, world seed 2000",
                        label=args.label)
        with open(args.json_out, "w") as f:
            json.dump({"meta": meta, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
