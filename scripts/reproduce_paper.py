#!/usr/bin/env python3
"""Reproduce the paper's scenarios S1–S12 with N seeds, the altitude-observability runs (S8 and S9 without a
barometer), and check the paper's claims (SPEC §7) against the numbers.

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

import numpy as np

import warptan as wt
from warptan.measurement import LIKELIHOODS
from warptan.report import ci95, write_outputs
from warptan.scenarios import SCENARIO_IDS, prepare, run_scenario, run_scenario_batch


def horiz(agg, sid, key="rmse_mean_m"):
    return float(np.hypot(*agg[sid][key][:2]))


def horiz_ci(results, sid, attr="rmse"):
    vals = [np.hypot(*getattr(r, attr)[:2]) for r in results if r.scenario == sid]
    mean, half = ci95(np.array(vals)[:, None])
    return float(mean[0]), float(half[0])


def claims(agg, results, no_baro) -> list[dict]:
    """Evaluate SPEC §7's claims; each entry: claim, holds (bool or None when not run), evidence."""
    out = []

    def have(*ids):
        return all(i in agg for i in ids)

    def fmt(sid):
        m, h = horiz_ci(results, sid)
        return f"{sid} {m:.1f}±{h:.1f} m"

    def add(claim, ids, holds, evidence):
        out.append({"claim": claim, "scenarios": ids, "holds": bool(holds) if have(*ids) else None,
                    "evidence": evidence if have(*ids) else "not run"})

    pairs = [("S7", "S9"), ("S8", "S9"), ("S10", "S12"), ("S11", "S12")]
    ok = [have(a, b) and horiz(agg, a) < horiz(agg, b) for a, b in pairs]
    add("point cloud beats the altimeter horizontally on rugged and flat terrain (horizontal RMSE)",
        ["S7", "S8", "S9", "S10", "S11", "S12"], all(ok),
        "; ".join(f"{fmt(a)} vs {fmt(b)}" for a, b in pairs if have(a, b)))
    pairs = [("S7", "S10"), ("S8", "S11"), ("S9", "S12")]
    ok = [have(a, b) and horiz(agg, a) < horiz(agg, b) for a, b in pairs]
    add("flat terrain is worse than rugged (same model)", ["S7", "S8", "S9", "S10", "S11", "S12"], all(ok),
        "; ".join(f"rugged {fmt(a)} vs flat {fmt(b)}" for a, b in pairs if have(a, b)))
    add("the navigation IMU is better than the low-end tactical one (S1 vs S2)", ["S1", "S2"],
        have("S1", "S2") and horiz(agg, "S1") < horiz(agg, "S2"), f"{fmt('S1')} vs {fmt('S2')}" if have("S1", "S2")
        else "")
    pairs = [("S3", "S4"), ("S7", "S8")]
    ratios = [horiz(agg, a) / horiz(agg, b) for a, b in pairs if have(a, b)]
    add("raycast and sliding are close at high altitude (horizontal RMSE within a factor 1.5)",
        ["S3", "S4", "S7", "S8"], bool(ratios) and all(1 / 1.5 <= r <= 1.5 for r in ratios),
        "; ".join(f"{fmt(a)} vs {fmt(b)} (ratio {horiz(agg, a) / horiz(agg, b):.2f})" for a, b in pairs if have(a, b)))
    add("raycast is better than sliding at low altitude / 60° bank (S5 vs S6)", ["S5", "S6"],
        have("S5", "S6") and horiz(agg, "S5") < horiz(agg, "S6"), f"{fmt('S5')} vs {fmt('S6')}" if have("S5", "S6")
        else "")
    if no_baro:
        z = {sid: ci95([[r.rmse[2]] for r in runs]) for sid, runs in no_baro.items()}
        zf = {sid: float(np.median([abs(r.run.error[-1, 2]) for r in runs])) for sid, runs in no_baro.items()}
        ins = {sid: float(np.median([abs(r.run.ins_pos[-1, 2] - r.run.truth_pos[-1, 2]) for r in runs]))
               for sid, runs in no_baro.items()}
        holds = "S8" in z and "S9" in z and z["S8"][0][0] < 0.5 * z["S9"][0][0] and z["S8"][0][0] < 5.0
        out.append({"claim": "altitude is observable from the point cloud without a barometer (S8 vs S9, no baro)",
                    "scenarios": ["S8", "S9"], "holds": bool(holds),
                    "evidence": "; ".join(f"{sid} no baro: vertical RMSE {z[sid][0][0]:.2f}±{z[sid][1][0]:.2f} m, "
                                          f"median final |dz| {zf[sid]:.2f} m (INS alone {ins[sid]:.1f} m)"
                                          for sid in sorted(z))})
    if have("S7", "S8"):
        ray, slide = agg["S7"]["update_ms_median"], agg["S8"]["update_ms_median"]
        add("sliding is much cheaper than raycasting (median measurement update, S7 vs S8, this device)",
            ["S7", "S8"], ray > 2 * slide, f"raycast (dda) {ray:.2f} ms vs sliding {slide:.2f} ms per update "
            f"(whole update incl. weights and resampling; kernel-only ratios are in benchmarks/)")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="paper-results")
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIO_IDS))
    parser.add_argument("--terrain", default=None, help="one DEM for every scenario (default: the scenario's)")
    parser.add_argument("--particles", type=int, default=None)
    parser.add_argument("--duration-s", type=float, default=None)
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
    with open(out / "likelihoods.json", "w") as f:
        json.dump({"seeds": args.seeds, "device": args.device, "likelihoods": kinds, "scenarios": table}, f, indent=1)
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
            cells.append(" / ".join(f"{a:.2f}±{b:.2f}" for a, b in zip(m, h, strict=True)))
            cells.append(" / ".join(f"{100 * c:.0f}%" for c in e["coverage_3sigma_mean"]))
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
    except (ValueError, FileNotFoundError) as err:
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
    written = write_outputs(results, out, terrains, plots=not args.no_plots)
    if no_baro:
        write_outputs([r for runs in no_baro.values() for r in runs], out / "no_baro", terrains,
                      plots=not args.no_plots)
    found = claims(written["aggregate"], results, no_baro)
    with open(out / "claims.json", "w") as f:
        json.dump(found, f, indent=1)
    lines = ["# The paper's claims, checked", "",
             f"{args.seeds} seeds per scenario, device {args.device}, likelihood "
             f"{likelihood or 'of the scenario files'}; terrains: "
             + ", ".join(sorted({Path(r.terrain).name for r in results})) + ".", ""]
    for c in found:
        verdict = {True: "holds", False: "does not hold", None: "not run"}[c["holds"]]
        lines.append(f"- **{verdict}** — {c['claim']}: {c['evidence']}")
    (out / "claims.md").write_text("\n".join(lines) + "\n")
    print(written["table"])
    print("\n".join(lines[4:]))
    print(f"total {time.perf_counter() - t0:.0f} s; wrote {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
