"""How good must the DEM be? Map-error study: the world is one terrain (default the 30 m San Gabriel tile), the
filter's map is that terrain at coarser posts (block means) and with white noise per post; S7 (ray casting),
S8 (sliding grid) and S9 (radar altimeter) with and without the map-aware σ (``likelihood.map_aware``: the map's
own interpolation error, :meth:`warptan.terrain.grid.Terrain.interpolation_sigma_m`, added to the stated noise).

Each (scenario, spacing, noise, map-aware) row is one batch of ``--seeds`` seeds on one map realisation
(``map_seed`` fixed per row); rows whose map grid is the world's (spacing = the world's posts) are run once (the
map-aware σ changes nothing there). Rows are appended to OUT/study.json as they finish (``--resume`` skips rows
already there), then OUT/study.md and the plots are written from the JSON.

    python scripts/map_error_study.py --seeds 20 --device cuda:0 --out results/map_error
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
from warptan.outputs import write_json
from warptan.sim.report import ci95
from warptan.sim.scenarios import run_scenario_batch

MODELS = {"S7": "ray casting", "S8": "sliding grid", "S9": "altimeter"}


def row_key(row: dict) -> tuple:
    return row["scenario"], row["map_spacing_m"], row["map_noise_m"], row["map_aware"]


def plan(args) -> list[dict]:
    rows = []
    for sid in args.scenarios:
        for spacing in args.spacings:
            for noise in args.noises:
                for aware in (True, False):
                    if spacing <= args.world_spacing and not aware:
                        continue  # the map is on the world's posts: the map-aware σ is the stated noise
                    rows.append({"scenario": sid, "map_spacing_m": spacing, "map_noise_m": noise, "map_aware": aware})
    return rows


def run_row(row: dict, args, seed_base: int) -> dict:
    seeds = list(range(args.seeds))
    t0 = time.perf_counter()
    runs = run_scenario_batch(
        row["scenario"], seeds, device=args.device, terrain=args.terrain, duration_s=args.duration_s,
        map_spacing_m=float(row["map_spacing_m"]) if row["map_spacing_m"] > args.world_spacing else 0.0,
        map_noise_m=float(row["map_noise_m"]), map_aware=row["map_aware"], map_seed=seed_base)
    rmse = np.array([r.rmse_converged for r in runs])
    cov = np.array([r.summary()["coverage_3sigma"] for r in runs])
    horiz = np.hypot(rmse[:, 0], rmse[:, 1])
    mean, half = ci95(rmse)
    hm, hh = ci95(horiz)
    return {**row, "seeds": len(runs), "terrain": runs[0].terrain, "map": runs[0].map,
            "map_sigma_m": runs[0].map_sigma_m, "rmse_converged_mean_m": mean.tolist(),
            "rmse_converged_ci95_m": half.tolist(), "horizontal_rmse_mean_m": float(hm),
            "horizontal_rmse_ci95_m": float(hh), "horizontal_rmse_median_m": float(np.median(horiz)),
            "coverage_3sigma_mean": cov.mean(axis=0).tolist(),
            "respreads": int(sum(r.run.respread.sum() for r in runs)),
            "wall_s": time.perf_counter() - t0}


def write_markdown(data: dict, out: Path) -> None:
    meta, rows = data["meta"], data["rows"]
    lines = ["# Map-error study: how good must the DEM be?", "",
             f"World: `{meta['terrain']}` ({meta['world_spacing_m']:g} m posts). Map: the world at coarser posts "
             "(block means) plus white noise per post (one realisation per row). "
             f"{meta['seeds']} seeds per row, {meta['duration_s']:g} s flights, device {meta['device']}. Converged "
             "horizontal RMSE = hypot(north, east) RMSE after convergence per seed, mean ± 95 % interval; 3σ "
             "coverage pooled over seeds and epochs after convergence. σ_map: the likelihood's map σ (stated noise, "
             "⊕ the map's interpolation error when map-aware).", "",
             "Commands (in order; later ones resumed): " + "; ".join(f"`{c}`" for c in meta.get(
                 "commands", [meta.get("command", "")])), ""]
    for sid in meta["scenarios"]:
        lines += [f"## {sid} ({MODELS.get(sid, '')})", "",
                  "| map posts (m) | map noise (m) | map-aware σ | σ_map (m) | horizontal RMSE (m) "
                  "| RMSE N / E / D (m) | 3σ coverage N / E / D | re-spreads |", "|---|---|---|---|---|---|---|---|"]
        for r in sorted((r for r in rows if r["scenario"] == sid),
                        key=lambda r: (r["map_spacing_m"], r["map_noise_m"], not r["map_aware"])):
            rm = " / ".join(f"{v:.2f}" for v in r["rmse_converged_mean_m"])
            cv = " / ".join(f"{100 * v:.0f}%" for v in r["coverage_3sigma_mean"])
            aware = "yes" if r["map_aware"] else "no"
            if r["map_spacing_m"] <= meta["world_spacing_m"]:
                aware = "(same grid)"
            lines.append(f"| {r['map_spacing_m']:g} | {r['map_noise_m']:g} | {aware} | {r['map_sigma_m']:.2f} | "
                         f"{r['horizontal_rmse_mean_m']:.2f} ± {r['horizontal_rmse_ci95_m']:.2f} | {rm} | {cv} | "
                         f"{r['respreads']} |")
        lines.append("")
    (out / "study.md").write_text("\n".join(lines))


def plot(data: dict, out: Path) -> list[str]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ModuleNotFoundError:
        return []
    meta, rows = data["meta"], data["rows"]
    files = []
    for what, ylabel, fname in (("rmse", "converged horizontal RMSE (m)", "rmse_vs_spacing.png"),
                                ("coverage", "3σ coverage (min of N, E)", "coverage_vs_spacing.png")):
        fig, axes = plt.subplots(1, len(meta["scenarios"]), figsize=(5 * len(meta["scenarios"]), 4), squeeze=False)
        for ax, sid in zip(axes[0], meta["scenarios"], strict=True):
            for noise, colour in zip(meta["noises"], ("C0", "C1", "C2", "C3", "C4", "C5"), strict=False):
                for aware, style in ((True, "-o"), (False, "--x")):
                    sel = sorted((r for r in rows if r["scenario"] == sid and r["map_noise_m"] == noise and
                                  (r["map_aware"] == aware or r["map_spacing_m"] <= meta["world_spacing_m"])),
                                 key=lambda r: r["map_spacing_m"])
                    if not sel:
                        continue
                    x = [r["map_spacing_m"] for r in sel]
                    if what == "rmse":
                        y = [r["horizontal_rmse_mean_m"] for r in sel]
                        err = [r["horizontal_rmse_ci95_m"] for r in sel]
                        ax.errorbar(x, y, yerr=err, fmt=style, color=colour, capsize=3,
                                    label=f"noise {noise:g} m, {'map-aware' if aware else 'stated σ'}")
                    else:
                        y = [min(r["coverage_3sigma_mean"][:2]) for r in sel]
                        ax.plot(x, y, style, color=colour,
                                label=f"noise {noise:g} m, {'map-aware' if aware else 'stated σ'}")
            if what == "rmse" and any(r["horizontal_rmse_mean_m"] > 0 for r in rows if r["scenario"] == sid):
                ax.set_yscale("log")
            else:
                ax.axhline(0.9, color="k", lw=0.8, ls=":")
                ax.set_ylim(0, 1.02)
            ax.set_xscale("log", base=2)
            ax.set_xticks(meta["spacings"], [f"{s:g}" for s in meta["spacings"]])
            ax.set_xlabel("map post spacing (m)")
            ax.set_ylabel(ylabel)
            ax.set_title(f"{sid} ({MODELS.get(sid, '')})")
            ax.grid(True, which="both", alpha=0.3)
        axes[0][0].legend(fontsize=7)
        fig.suptitle(f"World {meta['terrain']}; {meta['seeds']} seeds per point")
        fig.tight_layout()
        fig.savefig(out / fname, dpi=110)
        plt.close(fig)
        files.append(str(out / fname))
    return files


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=count_arg, default=20)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="map-error-study")
    parser.add_argument("--terrain", default="rugged30", help="the world (default: the 30 m San Gabriel tile)")
    parser.add_argument("--scenarios", nargs="+", default=list(MODELS))
    parser.add_argument("--spacings", nargs="+", type=number_arg(0.0, True), default=[30.0, 60.0, 90.0, 180.0])
    parser.add_argument("--noises", nargs="+", type=number_arg(0.0, False), default=[0.0, 1.0, 3.0, 10.0])
    parser.add_argument("--duration-s", type=number_arg(0.0, True), default=120.0)
    parser.add_argument("--resume", action="store_true", help="keep the rows already in OUT/study.json")
    parser.add_argument("--report-only", action="store_true", help="rewrite study.md and the plots from the JSON")
    args = parser.parse_args(argv)
    wt.device.quiet_warp()
    out = Path(args.out)
    try:
        if args.seeds < 1:
            raise ValueError(f"--seeds must be ≥ 1, got {args.seeds}")
        wt.resolve_device(args.device)
        world = wt.Terrain.load(args.terrain)
        out.mkdir(parents=True, exist_ok=True)
    except (ValueError, FileNotFoundError, OSError) as err:
        print(f"map_error_study: error: {err}", file=sys.stderr)
        return 2
    args.world_spacing = max(world.dn, world.de)
    path = out / "study.json"
    data = {"rows": []}
    if (args.resume or args.report_only) and path.exists():
        data = json.loads(path.read_text())
    commands = data.get("meta", {}).get("commands", [])
    data["meta"] = {**run_meta(args.device), "terrain": world.name, "world_spacing_m": args.world_spacing,
                    "seeds": args.seeds,
                    "duration_s": args.duration_s, "device": args.device, "scenarios": args.scenarios,
                    "spacings": args.spacings, "noises": args.noises,
                    "commands": [*commands, "python scripts/map_error_study.py "
                                 + " ".join(argv if argv is not None else sys.argv[1:])]}
    done = {row_key(r) for r in data["rows"]}
    todo = [] if args.report_only else [r for r in plan(args) if row_key(r) not in done]

    def run(row):
        return run_row(row, args, 7000 + 100 * int(row["map_spacing_m"]) + int(10 * row["map_noise_m"]))

    def describe(row):
        return (f"{row['scenario']} posts {row['map_spacing_m']:g} m noise {row['map_noise_m']:g} m aware "
                f"{row['map_aware']}")

    run_rows(todo, run, describe, data, path)
    finish(data, path, out, write_markdown, plot)
    return 0


def run_rows(todo: list[dict], run, describe, data: dict, path: Path) -> None:
    """Run each row, append its result to ``data["rows"]`` and rewrite ``path`` after each (a study resumes from
    there), printing one progress line per row."""
    for k, row in enumerate(todo):
        result = run(row)
        data["rows"].append(result)
        write_json(path, data)
        extra = (f", σ/RMSE {np.round(result['sigma_over_rmse_mean'], 2)}" if "sigma_over_rmse_mean" in result
                 else "")
        print(f"[{k + 1}/{len(todo)}] {describe(row)}: {result['horizontal_rmse_mean_m']:.2f} ± "
              f"{result['horizontal_rmse_ci95_m']:.2f} m, coverage {np.round(result['coverage_3sigma_mean'], 3)}"
              f"{extra} ({result['wall_s']:.0f} s)", flush=True)


def finish(data: dict, path: Path, out: Path, markdown, plots) -> None:
    """The JSON, the Markdown table and the plots of a study."""
    write_json(path, data)
    markdown(data, out)
    files = plots(data, out)
    print(f"wrote {path}, {out / 'study.md'}" + "".join(f", {f}" for f in files))


if __name__ == "__main__":
    raise SystemExit(main())
