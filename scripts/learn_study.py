"""Honest without being told? Scenarios over several families of worlds that are not the map (issue 65), the filter
told nothing and learning the map's error in flight (``learn``, the default), told nothing with the learner off
(``off``: the filter as it was before the learner), and told the world's true error as a prior (``told``).

Families (each its own generator settings of :class:`warptan.terrain.world.WorldModel`, one realisation per seed:
``world_seed = 2000 + seed``): ``long`` 5 m correlated over 1 km with the map's sub-post relief extrapolated; ``short``
2 m over 300 m; ``biased`` 10 m over 3 km and a 5 m bias; ``smoothed`` 3 m of relief under the map's posts only (a
smoothed product); ``clutter`` 3 m over 1 km and 8 m canopy over 20 % of the ground. Seeds run one by one (the learner
runs in a filter of one flight) over ``--worlds`` realisations of each family (seed k flies world ``2000 + k * worlds //
seeds``). Rows are appended to OUT/study.json as they finish (``--resume`` skips them);
OUT/study.md is written from the JSON.

    python scripts/learn_study.py --seeds 20 --scenarios S8 S7 --modes learn off told --out results/learned
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from warptan.meta import run_meta
from warptan.sim.replay import replay
from warptan.sim.report import ci95, declared_unconverged
from warptan.sim.scenarios import run_scenario

FAMILIES = {
    "long": {"world_error_rms_m": 5.0, "world_error_corr_m": 1000.0, "world_relief_rms_m": "auto"},
    "short": {"world_error_rms_m": 2.0, "world_error_corr_m": 300.0},
    "biased": {"world_error_rms_m": 10.0, "world_error_corr_m": 3000.0, "world_bias_m": 5.0},
    "smoothed": {"world_relief_rms_m": 3.0, "world_relief_slope": 3.0},
    "clutter": {"world_error_rms_m": 3.0, "world_error_corr_m": 1000.0, "world_clutter_height_m": 8.0,
                "world_clutter_fraction": 0.2},
    "exact": {},
    "posts": {"world_error_rms_m": 5.0, "world_error_corr_m": 1000.0, "world_refine": 1},
}
"""World generator settings per family; ``exact``: the map is the world (a statement there is over-stated); ``posts``:
the world on the map's own posts (nothing between them the map lacks) with a smooth error."""
MISSTATED = {"rms-half": (0.5, 1.0), "rms-double": (2.0, 1.0), "corr-third": (1.0, 1.0 / 3.0),
             "corr-triple": (1.0, 3.0)}
"""Misstated modes: (factor on the RMS, factor on the correlation length) of the family's own error."""
MODES = ("learn", "off", "told", *MISSTATED, "replay-told")
REPLAYED = ("replay-told",)
"""Modes that fly the scenario, export its flight log and replay that log (``warptan.sim.replay.replay``) told
:data:`EXACT_STATEMENT`, the user guide's sequence: over the ``exact`` family a replay over the log's own DEM, a map
better than stated (run over that family only)."""
LOST_M = 50.0
"""A seed whose converged horizontal RMSE exceeds this is lost; ``lost_unflagged`` counts those that did not declare
themselves unconverged (``warptan.sim.report.declared_unconverged``: their horizontal 3σ over 50 m)."""
EXACT_STATEMENT = (5.0, 1000.0)
"""What ``told`` states over the ``exact`` family (a map better than stated)."""


def mode_keywords(mode: str, family: str) -> dict:
    """The likelihood's keywords of a mode over a family: ``off`` the learner off, ``told`` the family's own error
    (``smoothed``: 3 m / 300 m; ``exact``: :data:`EXACT_STATEMENT`) as the learner's prior, a :data:`MISSTATED` mode
    that statement scaled."""
    if mode == "off":
        return {"map_error_learn": False}
    if mode in ("learn", *REPLAYED):
        return {}
    kw = FAMILIES[family]
    rms, corr = EXACT_STATEMENT if family == "exact" else (kw.get("world_error_rms_m", 3.0),
                                                           kw.get("world_error_corr_m", 300.0))
    f_rms, f_corr = MISSTATED.get(mode, (1.0, 1.0))
    return {"map_error_rms_m": rms * f_rms, "map_error_corr_m": corr * f_corr}


def fly(job: tuple) -> dict:
    """One seed of a row (a worker's task): its converged horizontal RMSE, errors and 3σ after convergence, learned
    RMS and white error, the map-minus-world RMS, its re-spreads and whether it declared itself unconverged."""
    sid, seed, world_seed, kw, device, mode = job
    logs = [] if mode in REPLAYED else None
    r = run_scenario(sid, seed, device=device, world_seed=world_seed, bound=False, export_logs=logs, **kw)
    if logs:
        r = replay(logs[0], device=device, map_error=EXACT_STATEMENT)
    conv = r.run.t_s >= r.config.filter.converged_after_s
    parts = getattr(r.truth_terrain, "parts", None) or {}
    return {"horiz": float(np.hypot(*r.rmse_converged[:2])), "err": r.run.error[conv], "sig3": r.run.sigma3_pos[conv],
            "learned": r.run.info.get("map_error_learned_m"), "white": r.run.info.get("map_white_learned_m"),
            "world_rms": float(parts.get("map_minus_world_rms_m", 0.0)), "respreads": int(r.run.respread.sum()),
            "flagged": declared_unconverged(r.run, r.config.filter.converged_after_s),
            "lin_err": r.run.lin_err[conv, :6], "lin_sig3": r.run.sigma3_lin[conv, :6]}


def honesty(runs: list[dict], err_key: str, sig3_key: str) -> tuple[list[float], list[float]]:
    """Per axis, pooled over the runs' epochs after convergence: the share of errors within the reported 3σ, and the
    mean reported σ over the RMSE."""
    err = np.concatenate([r[err_key] for r in runs])
    sig3 = np.concatenate([r[sig3_key] for r in runs])
    rmse = np.sqrt(np.mean(err**2, axis=0))
    return np.mean(np.abs(err) <= sig3, axis=0).tolist(), (np.mean(sig3, axis=0) / 3.0 / rmse).tolist()


def run_row(sid: str, family: str, mode: str, seeds: int, worlds: int, duration_s: float, device: str,
            pool=None) -> dict:
    kw = {**FAMILIES[family], **mode_keywords(mode, family), "duration_s": duration_s}
    jobs = [(sid, seed, 2000 + seed * worlds // seeds, kw, device, mode) for seed in range(seeds)]
    runs = list(pool.map(fly, jobs)) if pool is not None else [fly(j) for j in jobs]
    horiz = np.array([r["horiz"] for r in runs])
    coverage, sigma_over_rmse = honesty(runs, "err", "sig3")
    lin_coverage, lin_sigma_over_rmse = honesty(runs, "lin_err", "lin_sig3")
    mean, half = ci95(horiz)
    learned, white = [r["learned"] for r in runs], [r["white"] for r in runs]
    return {"scenario": sid, "family": family, "mode": mode, "seeds": seeds, "worlds": worlds,
            "duration_s": duration_s,
            "keywords": {k: v for k, v in kw.items() if k != "duration_s"},
            "horizontal_rmse_m": float(mean), "horizontal_rmse_ci95_m": float(half), "per_seed_m": horiz.tolist(),
            "coverage_3sigma": coverage, "sigma_over_rmse": sigma_over_rmse,
            "world_rms_m": float(np.mean([r["world_rms"] for r in runs])),
            "velocity_coverage_3sigma": lin_coverage[:3], "attitude_coverage_3sigma": lin_coverage[3:],
            "attitude_sigma_over_rmse": lin_sigma_over_rmse[3:],
            "learned_m": None if learned[0] is None else [float(v) for v in learned],
            "white_learned_m": None if white[0] is None else [float(v) for v in white],
            "respreads": int(sum(r["respreads"] for r in runs)),
            "declared_unconverged": int(sum(r["flagged"] for r in runs)),
            "lost_unflagged": int(sum(r["horiz"] > LOST_M and not r["flagged"] for r in runs)),
            "meta": run_meta((device,))}


def merged_meta(rows: list[dict]) -> dict:
    """The artifact's meta of rows run on several machines: the first row's, with every row's devices, the GPU's
    name and driver where one ran, every commit and this merge's command."""
    meta = dict(rows[0]["meta"])
    meta["devices"] = {k: v for r in rows for k, v in r["meta"]["devices"].items()}
    gpu = next((r["meta"]["gpu"] for r in rows if "gpu" in r["meta"]), None)
    if gpu is not None:
        meta["gpu"] = gpu
    meta["git_commits"] = sorted({str(r["meta"]["git_commit"]) for r in rows})
    meta["command"] = " ".join(sys.argv)
    return meta


def write_md(rows: list[dict], path: Path) -> None:
    lines = ["# Honest without being told: the map's error learned in flight", "",
             "Per row: 20 seeds over 4 world realisations of the family (5 seeds each), 120 s. Modes: `learn` nothing "
             "stated (the default: the learner starts from 5 m / 500 m), `off` nothing stated with the learner off "
             "(the filter as it was), `told` the world's own error stated (a prior; over `exact`, where the map is the "
             "world, 5 m / 1 km: a map better than stated), `rms-half` / `rms-double` / `corr-third` / `corr-triple` "
             "that statement with its RMS × 0.5 / × 2 or its correlation length × 1/3 / × 3, `replay-told` the "
             "flight's log replayed told 5 m / 1 km. Horizontal RMSE after "
             "convergence, mean ± 95 % interval over seeds; 3σ coverage pooled over seeds and epochs after "
             "convergence; σ/RMSE the mean reported σ over the RMSE per axis; learned: the learned RMS at the end of "
             "the flight, mean (min–max) over seeds; attitude and velocity: the roll / pitch / yaw and the north / "
             "east / down velocity errors' 3σ coverage likewise (rows run since they were recorded; — before). "
             "Commands and machines: `PROVENANCE.md`.", "",
             "| scenario | family | map − world RMS (m) | mode | horizontal RMSE (m) | 3σ coverage N / E / D | "
             "σ/RMSE N / E / D | attitude 3σ coverage r / p / y | velocity 3σ coverage N / E / D | learned RMS (m) | "
             "re-spreads | device |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["scenario"], r["family"], r["mode"])):
        cov = " / ".join(f"{100 * c:.0f}%" for c in r["coverage_3sigma"])
        sr = " / ".join(f"{v:.2f}" for v in r["sigma_over_rmse"])
        att, vel = (" / ".join(f"{100 * c:.0f}%" for c in r[key]) if key in r else "—"
                    for key in ("attitude_coverage_3sigma", "velocity_coverage_3sigma"))
        lm = "—" if not r["learned_m"] else (f"{np.mean(r['learned_m']):.2f} ({min(r['learned_m']):.2f}–"
                                            f"{max(r['learned_m']):.2f})")
        lines.append(f"| {r['scenario']} | {r['family']} | {r['world_rms_m']:.2f} | {r['mode']} | "
                     f"{r['horizontal_rmse_m']:.2f} ± {r['horizontal_rmse_ci95_m']:.2f} | {cov} | {sr} | {att} | "
                     f"{vel} | {lm} | "
                     f"{r['respreads']} | {', '.join(r['meta']['devices'].values())} |")
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", nargs="+", default=["S8"])
    p.add_argument("--families", nargs="+", default=list(FAMILIES), choices=list(FAMILIES))
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--worlds", type=int, default=4)
    p.add_argument("--duration-s", type=float, default=120.0)
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--resume", action="store_true")
    p.add_argument("--jobs", type=int, default=1, help="seeds flown side by side in this many worker processes")
    p.add_argument("--merge", nargs="+", type=Path, default=None,
                   help="write OUT from these study.json files instead of running (a later file's row replaces an "
                        "earlier one of the same scenario, family and mode)")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "study.json"
    if args.merge:
        merged = {}
        for source in args.merge:
            for r in json.loads(source.read_text())["rows"]:
                merged[(r["scenario"], r["family"], r["mode"])] = r
        rows = list(merged.values())
        path.write_text(json.dumps({"meta": merged_meta(rows), "rows": rows}, indent=1))
        write_md(rows, args.out / "study.md")
        return 0
    rows = json.loads(path.read_text())["rows"] if args.resume and path.exists() else []
    done = {(r["scenario"], r["family"], r["mode"], r["seeds"]) for r in rows}
    pool = None
    if args.jobs > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn"))
    for sid in args.scenarios:
        for family in args.families:
            for mode in args.modes:
                if (sid, family, mode, args.seeds) in done or (family == "exact" and mode == "off") or (
                        family != "exact" and mode in REPLAYED):
                    continue
                rows.append(run_row(sid, family, mode, args.seeds, args.worlds, args.duration_s, args.device, pool))
                path.write_text(json.dumps({"meta": run_meta((args.device,)), "rows": rows}, indent=1))
                write_md(rows, args.out / "study.md")
                print(f"{sid} {family} {mode}: {rows[-1]['horizontal_rmse_m']:.2f} m, "
                      f"coverage {rows[-1]['coverage_3sigma']}", flush=True)
    if pool is not None:
        pool.shutdown()  # (left to the interpreter's exit, the pool's wake-up wrote to a closed pipe)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
