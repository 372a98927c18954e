#!/usr/bin/env python3
"""Reproduce the paper's scenarios S1–S12 with N seeds, the altitude-observability runs (S8 and S9 without a
barometer), and check the paper's claims (design notes §7) against the numbers.

Writes into --out: results.json / results.md / plots (as ``warptan run``), ``no_baro/`` (the observability
runs), and ``claims.md`` + ``claims.json`` (each claim: holds or not, with the numbers behind it).

    python scripts/reproduce_paper.py --seeds 10 --device cpu --out paper-results
    python scripts/reproduce_paper.py --seeds 10 --batch --out paper-results   # the seeds of a scenario batched
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import warptan as wt
from warptan.cli import count_arg, number_arg
from warptan.meta import run_meta
from warptan.outputs import OutputError, OutputFolder, write_json
from warptan.sensing.likelihood import LIKELIHOODS
from warptan.sim import claims
from warptan.sim.report import write_outputs
from warptan.sim.scenario_config import SCENARIO_IDS
from warptan.sim.scenarios import prepare, run_scenario, run_scenario_batch


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=count_arg, default=10)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="paper-results")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIO_IDS))
    parser.add_argument("--terrain", default=None, help="one DEM for every scenario (default: the scenario's)")
    parser.add_argument("--particles", type=count_arg, default=None)
    parser.add_argument("--duration-s", type=number_arg(0.0, True), default=None)
    parser.add_argument("--paper-rates", action="store_true")
    parser.add_argument("--no-baro-runs", action="store_true", help="skip the altitude-observability runs")
    parser.add_argument("--no-plots", action="store_true")
    parser.add_argument("--batch", action="store_true", help="run the seeds of a scenario as one batched filter")
    parser.add_argument("--surface", choices=("triangles", "bilinear"), default=None,
                        help="what the sliding and altimeter models read (default: the scenario files')")
    parser.add_argument("--closed-loop", action="store_true",
                        help="inject the converged estimate into the INS after every update (default: open loop)")
    parser.add_argument("--no-measurement-update", action="store_true",
                        help="the paper's C = 0: no Kalman update of velocity/attitude/biases from the residuals")
    parser.add_argument("--likelihoods", nargs="+", default=None, choices=sorted(LIKELIHOODS),
                        help="run every scenario with each of these likelihoods, into OUT/<likelihood>/, and write "
                             "OUT/likelihoods.md/.json side by side (default: the scenario files' likelihood, into "
                             "OUT)")
    args = parser.parse_args(argv)
    if args.likelihoods:
        try:  # OUT holds one folder per likelihood: made before any work (a missing OUT used to fail after it)
            Path(args.out).mkdir(parents=True, exist_ok=True)
        except OSError as err:
            print(f"reproduce_paper: error: --out {args.out}: {err.strerror or err}", file=sys.stderr)
            return 2
        rows = {}
        for kind in args.likelihoods:
            code = run_one(args, Path(args.out) / kind, kind)
            if code:
                return code
            with open(Path(args.out) / kind / "results.json") as f:
                rows[kind] = json.load(f)
        write_side_by_side(rows, Path(args.out), args)
        return 0
    return run_one(args, Path(args.out), None)


def write_side_by_side(rows: dict, out: Path, args) -> None:
    """OUT/likelihoods.json and .md: converged RMSE (mean ± 95 % interval) and pooled 3σ coverage per scenario,
    one column group per likelihood."""
    kinds = list(rows)
    table = {}
    for kind, data in rows.items():
        for sid, agg in data["scenarios"].items():
            table.setdefault(sid, {})[kind] = {k: agg[k] for k in ("rmse_converged_mean_m", "rmse_converged_ci95_m",
                                                                  "coverage_3sigma_mean", "seeds")}
    write_json(out / "likelihoods.json", {"meta": run_meta(args.device), "seeds": args.seeds, "device": args.device,
                                          "likelihoods": kinds, "scenarios": table})
    head = "| id | paper RMSE x / y / z (m) | " + " | ".join(
        f"{k}: RMSE after convergence | {k}: 3σ coverage N/E/D" for k in kinds) + " |"
    lines = ["# Paper likelihood vs per-point likelihood", "",
             f"{args.seeds} seeds per scenario, device {args.device}; converged RMSE north / east / down in metres, "
             "mean ± 95 % interval over seeds; 3σ coverage pooled over seeds and epochs after convergence.", "",
             head, "|" + "---|" * (2 + 2 * len(kinds))]
    for sid in sorted(table, key=lambda x: int(x[1:])):
        paper = rows[kinds[0]]["scenarios"][sid].get("paper_rmse_m")
        cells = [sid, " / ".join(f"{v:g}" for v in paper) if paper else ""]
        for k in kinds:
            e = table[sid].get(k)
            if e is None:
                cells += ["", ""]
                continue
            m, h = e["rmse_converged_mean_m"], e["rmse_converged_ci95_m"]
            cells.append(" / ".join("–" if a is None else f"{a:.2f}±{b:.2f}" for a, b in zip(m, h, strict=True)))
            cells.append(" / ".join("–" if c is None else f"{100 * c:.0f}%" for c in e["coverage_3sigma_mean"]))
        lines.append("| " + " | ".join(cells) + " |")
    (out / "likelihoods.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def run_one(args, out: Path, likelihood: str | None) -> int:
    """Every scenario (and the no-barometer runs) with ``likelihood`` (None: the files'), outputs into ``out``."""
    wt.device.quiet_warp()
    overrides = {"particles": args.particles, "duration_s": args.duration_s, "paper_rates": args.paper_rates,
                 "likelihood": likelihood, "surface": args.surface, "closed_loop": True if args.closed_loop else None,
                 "measurement_update": False if args.no_measurement_update else None}
    try:
        wt.resolve_device(args.device)
        for sid in args.scenarios:
            prepare(sid, terrain=args.terrain, **overrides)
        folder = OutputFolder(out)  # checked (and locked) before the work, not after it
    except (ValueError, FileNotFoundError, OutputError) as err:
        print(f"reproduce_paper: error: {err}", file=sys.stderr)
        return 2
    try:
        from tqdm import tqdm
    except ModuleNotFoundError:  # a bare GPU machine

        def tqdm(items, **_):
            return items

    t0 = time.perf_counter()
    seeds = list(range(args.seeds))
    groups = [(sid, seeds if args.batch else [s], {}) for sid in args.scenarios for s in ([0] if args.batch else seeds)]
    if not args.no_baro_runs:
        groups += [(sid, seeds if args.batch else [s], {"use_baro": False}) for sid in ("S8", "S9")
                   for s in ([0] if args.batch else seeds)]
    results, no_baro, terrains = [], {}, {}
    for sid, group, extra in tqdm(groups, unit="batch" if args.batch else "run", dynamic_ncols=True):
        if args.batch:
            runs = run_scenario_batch(sid, group, device=args.device, terrain=args.terrain, **overrides, **extra)
        else:
            runs = [run_scenario(sid, seed=group[0], device=args.device, terrain=args.terrain, **overrides, **extra)]
        for r in runs:
            terrains[r.scenario] = r.truth_terrain
            if extra:
                no_baro.setdefault(sid, []).append(r)
            else:
                results.append(r)
    written = write_outputs(results, folder, terrains, plots=not args.no_plots)
    if no_baro:
        write_outputs([r for runs in no_baro.values() for r in runs], out / "no_baro", terrains,
                      plots=not args.no_plots)
    found = claims.evaluate([r.summary() for r in results], [r.summary() for runs in no_baro.values() for r in runs])
    write_json(out / "claims.json", {"meta": run_meta(args.device), "claims": found})
    lines = ["# The paper's claims, checked", "",
             f"{args.seeds} seeds per scenario, device {args.device}, likelihood "
             f"{likelihood or 'of the scenario files'}; terrains: "
             + ", ".join(sorted({Path(r.terrain).name for r in results})) + ".", "", claims.markdown(found)]
    (out / "claims.md").write_text("\n".join(lines) + "\n")
    print(written["table"])
    print("\n".join(lines[4:]))
    print(f"total {time.perf_counter() - t0:.0f} s; wrote {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
