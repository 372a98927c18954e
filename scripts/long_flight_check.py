#!/usr/bin/env python3
"""Long-flight integrity check: S8 (Thuringia SRTM3), 600 s, 100 particles, seeds 0…N-1 (default 4), with the
per-point and the paper likelihood. Does each run stay inside its 3σ, or does its record flag the loss (integrity
re-spread)?

    python scripts/long_flight_check.py results/long_flight_check.json --seeds 20
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from warptan.cli import count_arg
from warptan.meta import run_meta
from warptan.outputs import write_json
from warptan.sim.scenarios import run_scenario_batch

WHAT = ("S8, 600 s, 100 particles, seeds 0-3, CPU. Per run: converged RMSE (m), 3σ coverage, fraction of epochs after "
        "30 s with the horizontal error outside the 3σ box, times of the integrity re-spreads, largest horizontal "
        "error after 30 s, final horizontal error, largest window mean of the integrity statistic.")


def summarise(result) -> dict:
    run = result.run
    late = run.t_s >= 30.0
    outside = ~(np.abs(run.error[:, :2]) <= run.sigma3_pos[:, :2]).all(axis=1)
    horiz = np.linalg.norm(run.error[:, :2], axis=1)
    return {"rmse_converged_m": result.rmse_converged.round(3).tolist(),
            "coverage_3sigma": run.coverage(30.0).round(3).tolist(),
            "frac_outside_3sigma_after_30s": round(float(outside[late].mean()), 4),
            "respreads_at_s": run.t_s[np.flatnonzero(run.respread)].round(1).tolist(),
            "max_horizontal_error_after_30s_m": round(float(horiz[late].max()), 2),
            "final_horizontal_error_m": round(float(horiz[-1]), 2),
            "integrity_max": round(float(np.nanmax(run.nis_avg)), 2)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", nargs="?", default="long_flight_check.json")
    parser.add_argument("--seeds", type=count_arg, default=4, help="seeds 0 … N-1 (one batched run per likelihood)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--terrain", default=None,
                        help="truth = map DEM (a path or name); 600 s at 100 m/s needs more than the package's ±22 km "
                             "crop, e.g. tests/data/dem/thuringia_hilly_srtm3_n50e010.tif")
    args = parser.parse_args(argv)
    out_path = Path(args.out)
    command = f"python scripts/long_flight_check.py {out_path} --seeds {args.seeds} --device {args.device}"
    if args.terrain:
        command += f" --terrain {args.terrain}"
    out = {"meta": run_meta(args.device, command=command),
           "what": WHAT.replace("seeds 0-3, CPU", f"seeds 0-{args.seeds - 1}, {args.device}"), "runs": {}}
    for kind in ("gaussian", "paper"):
        for r in run_scenario_batch("S8", list(range(args.seeds)), args.device, duration_s=600.0, particles=100,
                                    likelihood=kind, terrain=args.terrain):
            out["terrain"] = r.terrain
            out["runs"][f"{kind}/seed{r.seed}"] = row = summarise(r)
            print(kind, r.seed, row, flush=True)
    write_json(out_path, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
