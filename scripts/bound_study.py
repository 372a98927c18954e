"""The filter against the best possible on the same flights: each scenario's seeds as one batch, the horizontal mean
squared error after convergence against the flight's posterior Cramér–Rao bound (:mod:`warptan.filter.bound`), and
whether the filter is ever better than the bound by more than twice its Monte-Carlo standard error (it must not be).

With ``--world-error-m`` (and ``--world-corr-m``, ``--world-bias-m``) the world carries a correlated error the map
lacks (world seed 2000), the filter told it (``--told``) or learning it; each row then has the exact floor too
(:func:`warptan.filter.floor.exact_pcrb`, the error field in the state) beside the fast per-scan bound, and the
check is against the floor. ``--world-refine 1`` builds that world on the map's own posts: its only difference from
the map is then the error field, which the floor holds exactly; at the scenarios' default (3) the world's finer
triangles also differ from the map's by 0.1–0.8 m over the rugged tile's scans (correlated over a post), which the
floor leaves out and the filter's white map error counts, so the floor is optimistic there. The floor bounds the
error averaged over the field's realisations; the seeds of one world share one field, whose own error is common to
them: ``--worlds K`` splits the seeds over K realisations (world seeds 2000 …) and gives each world's RMSE too.

    python scripts/bound_study.py --scenarios all --seeds 20 --device cuda:0 --json results/bound/bound_study.json
    python scripts/bound_study.py --scenarios S8 S1 --world-error-m 5 --world-corr-m 1000 --told --json out.json

Rows of several runs (one per scenario and map error, say) merge into one file, each row keeping its run's ``meta``,
and a merged file with exact floors draws "how close to the floor" (each scenario's RMSE over the floor against the
error's correlation length, one line per RMS):

    python scripts/bound_study.py --merge S8_e5_L1000.json S8_e2_L300.json ... --json floor_study.json
    python scripts/bound_study.py --plot floor_study.json --png floor_study.png
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from warptan.cli import count_arg
from warptan.device import quiet_warp
from warptan.meta import run_meta


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", nargs="+", default=["all"])
    parser.add_argument("--seeds", type=count_arg, default=20)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--duration-s", type=float, default=None)
    parser.add_argument("--particles", type=count_arg, default=None)
    parser.add_argument("--world-error-m", type=float, default=0.0)
    parser.add_argument("--world-corr-m", type=float, default=1000.0)
    parser.add_argument("--world-bias-m", type=float, default=0.0)
    parser.add_argument("--world-refine", type=count_arg, default=None,
                        help="the world's post refinement over the map (1: the map's own posts; default: the "
                             "scenario's)")
    parser.add_argument("--worlds", type=count_arg, default=1,
                        help="with --world-error-m: the seeds split over this many realisations of the world's error "
                             "(world seeds 2000, 2001, …); one world makes every seed's error that one field's")
    parser.add_argument("--told", action="store_true",
                        help="state the world's error to the filter (its RMS, or the bias where larger, over its "
                             "correlation length: the statement has no separate bias)")
    parser.add_argument("--json", dest="json_out")
    parser.add_argument("--merge", nargs="+", metavar="JSON", help="merge these runs' rows into --json (no run)")
    parser.add_argument("--plot", metavar="JSON", help="draw a merged file's exact-floor rows into --png (no run)")
    parser.add_argument("--png")
    args = parser.parse_args(argv)
    if args.merge:
        if not args.json_out:
            parser.error("--merge needs --json")
        return merge(args.merge, args.json_out)
    if args.plot:
        if not args.png:
            parser.error("--plot needs --png")
        return plot(args.plot, args.png)
    world = {}
    if args.world_error_m > 0.0 or args.world_bias_m != 0.0:
        world = {"world_error_rms_m": args.world_error_m, "world_error_corr_m": args.world_corr_m,
                 "world_bias_m": args.world_bias_m, "world_seed": 2000}
        if args.world_refine is not None:
            world["world_refine"] = args.world_refine
        if args.told:
            world.update(map_error_rms_m=max(args.world_error_m, abs(args.world_bias_m)),
                         map_error_corr_m=args.world_corr_m)
    quiet_warp()
    from warptan.sim.scenario_config import SCENARIO_IDS
    from warptan.sim.scenarios import run_scenario_batch

    ids = list(SCENARIO_IDS) if args.scenarios == ["all"] else args.scenarios
    rows = []
    worlds = args.worlds if world else 1
    if worlds > args.seeds:
        parser.error(f"--worlds {worlds} needs at least as many --seeds, got {args.seeds}")
    for sid in ids:
        t0 = time.perf_counter()
        runs, per_world = [], []
        for w, seeds in enumerate(np.array_split(np.arange(args.seeds), worlds)):
            kw = {**world, "world_seed": 2000 + w} if world else world
            batch = run_scenario_batch(sid, [int(x) for x in seeds], args.device, duration_s=args.duration_s,
                                       particles=args.particles, bound="exact" if world else True, **kw)
            runs += batch
            per_world.append(len(batch))
        first = runs[0]
        sel = first.run.t_s >= first.config.filter.converged_after_s
        mse = np.array([float((r.run.error[sel, :2] ** 2).sum(axis=1).mean()) for r in runs])
        fast = first.pcrb_converged_m ** 2
        bound2 = first.floor_converged_m ** 2 if world else fast
        se = float(mse.std(ddof=1) / math.sqrt(len(mse))) if len(mse) > 1 else math.nan
        row = {"scenario": sid, "seeds": args.seeds, "model": first.config.sensor.model,
               "rmse_horizontal_converged_m": math.sqrt(mse.mean()), "mse_se_m2": se,
               "bound_converged_m": math.sqrt(bound2), "rmse_over_bound": math.sqrt(mse.mean() / bound2),
               "fast_bound_converged_m": math.sqrt(fast), "bound": "exact floor" if world else "fast PCRB",
               "world": world,
               "below_bound_beyond_mc_error": bool(mse.mean() < bound2 - 2.0 * se),
               "per_seed_rmse_horizontal_m": np.sqrt(mse).tolist(), "wall_s": time.perf_counter() - t0}
        if worlds > 1:  # (each world's seeds in turn, world seeds 2000 on)
            row["worlds"] = worlds
            row["rmse_horizontal_per_world_m"] = [float(np.sqrt(part.mean()))
                                                  for part in np.split(mse, np.cumsum(per_world)[:-1])]
        rows.append(row)
        print(f"{sid}: horizontal RMSE {row['rmse_horizontal_converged_m']:.3g} m, bound "
              f"{row['bound_converged_m']:.3g} m, ratio {row['rmse_over_bound']:.2f}"
              + ("  BELOW THE BOUND" if row["below_bound_beyond_mc_error"] else ""), flush=True)
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"meta": run_meta([args.device], what=__doc__.split("\n\n")[0]), "rows": rows}, fh, indent=1)
        print(f"wrote {args.json_out}")
    return 1 if any(r["below_bound_beyond_mc_error"] for r in rows) else 0


DIVERGED_M = 100.0
"""A cell whose converged horizontal RMSE exceeds this (m) is named on the picture with its RMSE."""


def _sid_key(sid: str) -> int:
    return int(sid[1:])


def merge(paths: list[str], out: str) -> int:
    """The rows of ``paths`` in one file: each row keeps its run's ``meta`` (commit, machine, command; a merged
    file's rows their own), a later file's row replacing an earlier one of the same scenario, world and number of
    worlds; the file's ``meta`` is the first run's with ``runs``, every run's."""
    cells, metas = {}, []
    for path in paths:
        with open(path) as fh:
            data = json.load(fh)
        metas += data["meta"].get("runs", [data["meta"]])
        for r in data["rows"]:
            key = (r["scenario"], json.dumps(r["world"], sort_keys=True), r.get("worlds", 1))
            cells[key] = {**r, "meta": r.get("meta", data["meta"])}
    rows = list(cells.values())
    rows.sort(key=lambda r: (_sid_key(r["scenario"]), r["world"].get("world_error_rms_m", 0.0),
                             r["world"].get("world_error_corr_m", 0.0)))
    with open(out, "w") as fh:
        json.dump({"meta": {**metas[0], "runs": metas}, "rows": rows}, fh, indent=1)
    print(f"wrote {out}: {len(rows)} rows from {len(paths)} runs")
    return 0


def plot(path: str, png: str) -> int:
    """Each scenario's converged horizontal RMSE over the exact floor against the map error's correlation length, one
    line per RMS, with the issue's 2× mark; a second panel the fast per-scan bound over the floor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(path) as fh:
        rows = [r for r in json.load(fh)["rows"] if r.get("bound") == "exact floor"]
    scenarios = sorted({r["scenario"] for r in rows}, key=_sid_key)
    rms_levels = sorted({r["world"]["world_error_rms_m"] for r in rows})
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.5), gridspec_kw={"width_ratios": [2, 1]})
    colours = plt.get_cmap("tab10")
    styles = dict(zip(rms_levels, ("-", "--", ":", "-."), strict=False))
    for i, sid in enumerate(scenarios):
        label = sid
        for rms in rms_levels:
            line = sorted((r["world"]["world_error_corr_m"], r["rmse_over_bound"], r["fast_bound_converged_m"]
                           / r["bound_converged_m"]) for r in rows
                          if r["scenario"] == sid and r["world"]["world_error_rms_m"] == rms)
            if not line:
                continue
            corr, ratio, fast = np.array(line).T
            ax.plot(corr / 1e3, ratio, styles[rms], marker="o", color=colours(i), label=label)
            label = None
            bx.plot(corr / 1e3, fast, styles[rms], marker="o", color=colours(i))
    for r in rows:  # a cell far off the scale of the rest: its RMSE written beside it
        if r["rmse_horizontal_converged_m"] > DIVERGED_M:
            ax.annotate(f"{r['scenario']} at {r['world']['world_error_rms_m']:g} m: "
                        f"{r['rmse_horizontal_converged_m'] / 1e3:.1f} km RMSE (diverged)",
                        (r["world"]["world_error_corr_m"] / 1e3, r["rmse_over_bound"]), xytext=(8, -4),
                        textcoords="offset points", fontsize=7)
    for rms in rms_levels:
        ax.plot([], [], styles[rms], color="grey", label=f"{rms:g} m RMS")
    ax.axhline(2.0, color="k", lw=1)
    ax.text(1.0, 2.15, "2× the floor", fontsize=8)
    bx.axhline(1.0, color="k", lw=1)
    for a in (ax, bx):
        a.set_xscale("log")
        a.set_xticks([0.3, 1.0, 3.0], ["0.3", "1", "3"])
        a.minorticks_off()
        a.set_xlabel("map error's correlation length (km)")
        a.grid(True, which="both", alpha=0.3)
    ax.set_yscale("log")
    ax.set_ylabel("filter's horizontal RMSE / exact floor")
    ax.set_title("How close to the floor (told the error; one world, 20 seeds a cell)", fontsize=10)
    bx.set_ylabel("fast per-scan bound / exact floor")
    bx.set_title("The fast bound against the floor", fontsize=10)
    ax.legend(fontsize=7, ncol=3, loc="lower left")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    print(f"wrote {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
