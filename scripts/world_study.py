"""Honest on real maps? Scenarios over worlds that are not the map (issue 31): the filter's map is the DEM, the
flight sees a world made from it (:class:`warptan.terrain.world.WorldModel`: sub-post relief extrapolated from the DEM's
spectrum, a correlated vertical error of stated RMS and correlation length, clutter), and each estimator is told
only the DEM's stated accuracy.

A row is (scenario, error RMS, correlation length, relief, estimator); its ``--seeds`` seeds are split over
``--worlds`` world realisations (one batch each: a world is shared by the seeds of its batch). Estimators:
``gaussian`` (the per-point likelihood as the scenario has it), ``paper`` (the paper's scalar error), and
``stated`` (the per-point likelihood told the DEM's accuracy: ``likelihood.map_error_rms_m`` and
``map_error_corr_m``, see :class:`warptan.sensing.likelihood.Likelihood`). Rows are appended to OUT/study.json as they
finish (``--resume`` skips rows already there); OUT/study.md is written from the JSON.

    python scripts/world_study.py --seeds 20 --worlds 4 --device cuda:0 --out results/world
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import warptan as wt
from warptan.cli import count_arg, number_arg
from warptan.meta import run_meta
from warptan.sim.report import ci95
from warptan.sim.scenarios import run_scenario_batch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from map_error_study import finish, run_rows

ESTIMATORS = ("gaussian", "paper", "stated")
LOST_M = 50.0
"""A seed whose converged horizontal RMSE exceeds this is lost (it must be flagged by the integrity monitor)."""


def row_key(row: dict) -> tuple:
    return (row["scenario"], row["terrain"], row["error_rms_m"], row["error_corr_m"], str(row["relief"]),
            row["estimator"])


def plan(args) -> list[dict]:
    rows = []
    for terrain in args.terrains:
        for sid in args.scenarios:
            for rms in args.errors:
                for corr in args.corrs if rms else [0.0]:
                    for estimator in args.estimators:
                        if estimator == "stated" and not rms:
                            continue  # nothing stated: the same as gaussian
                        rows.append({"scenario": sid, "terrain": terrain, "error_rms_m": rms, "error_corr_m": corr,
                                     "relief": args.relief, "estimator": estimator})
    return rows


def _keywords(row: dict, args) -> dict:
    kw = {"terrain": row["terrain"], "duration_s": args.duration_s, "world_relief_rms_m": row["relief"],
          "world_error_rms_m": row["error_rms_m"], "world_error_corr_m": row["error_corr_m"]}
    if row["estimator"] == "paper":
        kw["likelihood"] = "paper"
    if row["estimator"] == "stated":
        kw.update(map_error_rms_m=row["error_rms_m"], map_error_corr_m=row["error_corr_m"])
    return kw


def run_row(row: dict, args) -> dict:
    t0 = time.perf_counter()
    runs = []
    groups = np.array_split(np.arange(args.seeds), args.worlds)
    for w, seeds in enumerate(groups):
        runs += run_scenario_batch(row["scenario"], [int(s) for s in seeds], device=args.device,
                                   world_seed=1000 + w, **_keywords(row, args))
    summaries = [r.summary() for r in runs]
    rmse = np.array([r.rmse_converged for r in runs])
    horiz = np.hypot(rmse[:, 0], rmse[:, 1])
    cov = np.array([s["coverage_3sigma"] for s in summaries])
    ratio = np.array([s["sigma_over_rmse_pos"] for s in summaries], dtype=np.float64)
    hm, hh = ci95(horiz)
    mean, half = ci95(rmse)
    flagged = [s["respreads"] > 0 or s["declared_unconverged"] for s in summaries]
    lost = horiz > LOST_M
    return {**row, "seeds": len(runs), "worlds": args.worlds, "world": runs[0].terrain, "map": runs[0].map,
            "horizontal_rmse_mean_m": float(hm), "horizontal_rmse_ci95_m": float(hh),
            "horizontal_rmse_median_m": float(np.median(horiz)), "horizontal_rmse_max_m": float(horiz.max()),
            "rmse_converged_mean_m": mean.tolist(), "rmse_converged_ci95_m": half.tolist(),
            "coverage_3sigma_mean": cov.mean(axis=0).tolist(),
            "sigma_over_rmse_mean": np.nanmean(np.where(np.isfinite(ratio), ratio, np.nan), axis=0).tolist(),
            "seeds_over_5m": int((horiz > 5.0).sum()), "seeds_lost": int(lost.sum()),
            "seeds_lost_unflagged": int(sum(bool(x) and not f for x, f in zip(lost, flagged, strict=True))),
            "respreads": int(sum(s["respreads"] for s in summaries)),
            "seeds_declared_unconverged": int(sum(s["declared_unconverged"] for s in summaries)),
            "map_minus_world_rms_m": float(np.mean([r.truth_terrain.parts.get("map_minus_world_rms_m", 0.0)
                                                    for r in runs if hasattr(r.truth_terrain, "parts")] or [0.0])),
            "wall_s": time.perf_counter() - t0}


def write_markdown(data: dict, out: Path) -> None:
    meta, rows = data["meta"], data["rows"]
    reliefs = sorted({str(r["relief"]) for r in rows})
    sweep = len(reliefs) > 1  # a relief column when the rows differ in it
    relief = "per row (RMS, m)" if sweep else f"`{reliefs[0]}`" if reliefs else "–"
    lines = ["# Honest on real maps: worlds that are not the map", "",
             f"{meta['seeds']} seeds per row over {meta['worlds']} world realisations, {meta['duration_s']:g} s "
             f"flights, device {meta['device']}; sub-post relief "
             f"{relief}. Converged horizontal RMSE = "
             "hypot(north, east) RMSE after convergence per seed, mean ± 95 % interval; 3σ coverage pooled; "
             f"σ/RMSE the mean reported σ over the RMSE per axis; lost: horizontal RMSE > {LOST_M:g} m "
             "(unflagged: without a re-spread, and not declared unconverged: its horizontal 3σ after convergence under "
             "50 m, `warptan.sim.report.UNCONVERGED_3SIGMA_M`).", "",
             "Commands: " + "; ".join(f"`{c}`" for c in meta.get("commands", [])), "",
             "| scenario | terrain | error RMS / corr (m) | estimator | map − world RMS (m) | horizontal RMSE (m) "
             "| RMSE N / E / D (m) | 3σ coverage N / E / D | σ/RMSE N / E / D | > 5 m | lost (unflagged) "
             "| re-spreads |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    if sweep:
        lines[-2] = lines[-2].replace("| estimator |", "| relief (m) | estimator |")
        lines[-1] += "---|"
    for r in sorted(rows, key=lambda r: (r["terrain"], r["scenario"], r["error_rms_m"], r["error_corr_m"],
                                          str(r["relief"]), ESTIMATORS.index(r["estimator"]))):
        rm = " / ".join(f"{v:.2f}" for v in r["rmse_converged_mean_m"])
        cv = " / ".join(f"{100 * v:.0f}%" for v in r["coverage_3sigma_mean"])
        sr = " / ".join("–" if v is None or not np.isfinite(v) else f"{v:.2f}" for v in r["sigma_over_rmse_mean"])
        lines.append(f"| {r['scenario']} | {r['terrain']} | {r['error_rms_m']:g} / {r['error_corr_m']:g} | "
                     f"{str(r['relief']) + ' | ' if sweep else ''}"
                     f"{r['estimator']} | {r['map_minus_world_rms_m']:.2f} | {r['horizontal_rmse_mean_m']:.2f} ± "
                     f"{r['horizontal_rmse_ci95_m']:.2f} | {rm} | {cv} | {sr} | {r['seeds_over_5m']} | "
                     f"{r['seeds_lost']} ({r['seeds_lost_unflagged']}) | {r['respreads']} |")
    (out / "study.md").write_text("\n".join(lines) + "\n")


def plot(data: dict, out: Path) -> list[str]:
    """``dem_accuracy.png``: converged horizontal RMSE and the smallest per-axis 3σ coverage against the map
    error's RMS (one correlation length: the most common), per scenario and estimator — how good must the DEM be."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ModuleNotFoundError:
        return []
    rows = data["rows"]
    corrs = sorted({r["error_corr_m"] for r in rows if r["error_rms_m"]},
                   key=lambda c: -sum(r["error_corr_m"] == c for r in rows))
    if not corrs:
        return []
    corr = corrs[0]
    levels = {}
    for r in rows:
        if r["error_corr_m"] in (corr, 0.0):
            levels.setdefault(r["scenario"], set()).add(r["error_rms_m"])
    scenarios = sorted((s for s, v in levels.items() if len(v) >= 2), key=lambda s: (-len(levels[s]), s))[:4]
    if not scenarios:
        return []
    fig, axes = plt.subplots(2, len(scenarios), figsize=(4.5 * len(scenarios), 7), squeeze=False)
    for col, sid in enumerate(scenarios):
        for estimator, style in zip(ESTIMATORS, ("-o", "--s", ":^"), strict=True):
            sel = sorted((r for r in rows if r["scenario"] == sid and r["estimator"] == estimator
                          and r["error_corr_m"] in (corr, 0.0)), key=lambda r: r["error_rms_m"])
            if len(sel) < 2:
                continue
            x = [r["error_rms_m"] for r in sel]
            axes[0][col].errorbar(x, [r["horizontal_rmse_mean_m"] for r in sel], fmt=style, capsize=3,
                                  yerr=[r["horizontal_rmse_ci95_m"] for r in sel], label=estimator)
            axes[1][col].plot(x, [min(r["coverage_3sigma_mean"]) for r in sel], style, label=estimator)
        axes[0][col].set_title(f"{sid}: map error correlated over {corr:g} m")
        axes[0][col].set_yscale("log")
        axes[0][col].set_ylabel("converged horizontal RMSE (m)")
        axes[1][col].axhline(0.9, color="k", lw=0.8, ls=":")
        axes[1][col].set_ylim(0, 1.02)
        axes[1][col].set_ylabel("3σ coverage, worst axis")
        for ax in axes[:, col]:
            ax.set_xlabel("map error RMS (m)")
            ax.grid(True, alpha=0.3)
        axes[0][col].legend(fontsize=8)
    fig.suptitle(f"How good must the DEM be? {data['meta']['seeds']} seeds per point, sub-post relief "
                 f"{data['meta']['relief']}")
    fig.tight_layout()
    path = out / "dem_accuracy.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [str(path)]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=count_arg, default=20)
    parser.add_argument("--worlds", type=count_arg, default=4, help="world realisations the seeds are split over")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="world-study")
    parser.add_argument("--terrains", nargs="+", default=["rugged"],
                        help="DEMs the worlds are made from (every scenario flies each, S12 included)")
    parser.add_argument("--scenarios", nargs="+", default=["S7", "S8", "S9"])
    parser.add_argument("--errors", nargs="+", type=number_arg(0.0, False), default=[0.0, 2.0, 5.0, 10.0])
    parser.add_argument("--corrs", nargs="+", type=number_arg(0.0, True), default=[1000.0])
    parser.add_argument("--relief", default="auto", help="sub-post relief RMS (m) or 'auto'")
    parser.add_argument("--estimators", nargs="+", choices=ESTIMATORS, default=list(ESTIMATORS))
    parser.add_argument("--duration-s", type=number_arg(0.0, True), default=120.0)
    parser.add_argument("--resume", action="store_true", help="keep the rows already in OUT/study.json")
    args = parser.parse_args(argv)
    if args.relief != "auto":
        args.relief = float(args.relief)
    wt.device.quiet_warp()
    out = Path(args.out)
    try:
        wt.resolve_device(args.device)
        out.mkdir(parents=True, exist_ok=True)
    except (ValueError, OSError) as err:
        print(f"world_study: error: {err}", file=sys.stderr)
        return 2
    path = out / "study.json"
    data = {"rows": []}
    if args.resume and path.exists():
        data = json.loads(path.read_text())
    commands = data.get("meta", {}).get("commands", [])
    data["meta"] = {**run_meta(args.device), "seeds": args.seeds, "worlds": args.worlds, "relief": args.relief,
                    "duration_s": args.duration_s, "device": args.device,
                    "commands": [*commands, "python scripts/world_study.py "
                                 + " ".join(argv if argv is not None else sys.argv[1:])]}
    done = {row_key(r) for r in data["rows"]}
    todo = [r for r in plan(args) if row_key(r) not in done]

    def describe(row):
        return (f"{row['scenario']} {row['terrain']} error {row['error_rms_m']:g}/{row['error_corr_m']:g} "
                f"{row['estimator']}")

    run_rows(todo, lambda row: run_row(row, args), describe, data, path)
    finish(data, path, out, write_markdown, plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
