"""The filter against the best possible on the same flights: each scenario's seeds as one batch, the horizontal mean
squared error after convergence against the flight's posterior Cramér–Rao bound (:mod:`warptan.filter.bound`), and
whether the filter is ever better than the bound by more than twice its Monte-Carlo standard error (it must not be).

With ``--world-error-m`` (and ``--world-corr-m``, ``--world-bias-m``) the world carries a correlated error the map
lacks (world seed 2000), the filter told it (``--told``) or learning it; each row then has the exact floor too
(:func:`warptan.filter.floor.exact_pcrb`, the error field in the state) beside the fast per-scan bound, and the
check is against the floor. ``--world-refine 1`` builds that world on the map's own posts: its only difference from
the map is then the error field, which the floor holds exactly; at the scenarios' default (3) the world's finer
triangles also differ from the map's by 0.1–0.8 m over the rugged tile's scans (correlated over a post), which the
floor leaves out and the filter's white map error counts, so the floor is optimistic there.

    python scripts/bound_study.py --scenarios all --seeds 20 --device cuda:0 --json results/bound/bound_study.json
    python scripts/bound_study.py --scenarios S8 S1 --world-error-m 5 --world-corr-m 1000 --told --json out.json
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
    parser.add_argument("--told", action="store_true",
                        help="state the world's error to the filter (its RMS, or the bias where larger, over its "
                             "correlation length: the statement has no separate bias)")
    parser.add_argument("--json", dest="json_out")
    args = parser.parse_args(argv)
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
    for sid in ids:
        t0 = time.perf_counter()
        runs = run_scenario_batch(sid, list(range(args.seeds)), args.device, duration_s=args.duration_s,
                                  particles=args.particles, bound="exact" if world else True, **world)
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
        rows.append(row)
        print(f"{sid}: horizontal RMSE {row['rmse_horizontal_converged_m']:.3g} m, bound "
              f"{row['bound_converged_m']:.3g} m, ratio {row['rmse_over_bound']:.2f}"
              + ("  BELOW THE BOUND" if row["below_bound_beyond_mc_error"] else ""), flush=True)
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"meta": run_meta([args.device], what=__doc__.split("\n\n")[0]), "rows": rows}, fh, indent=1)
        print(f"wrote {args.json_out}")
    return 1 if any(r["below_bound_beyond_mc_error"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
