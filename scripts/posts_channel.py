#!/usr/bin/env python3
"""Where a smooth map error leaks into the filter over a world on the map's own posts (issue 65's ``posts`` family):
S8 (or another scenario) told the world's error, one world, seeds as a batch (the learner off), the Kalman part's
measurement update from the terrain on and off, the fix-wander noise (``Likelihood.fix_process``) scaled and the
attitude information's weight (``LikParams.att_scale``) scaled; per variant the converged
horizontal RMSE, the 3σ coverage of position (N, E) and attitude (roll, pitch, yaw), and the roll error's mean against
its mean 3σ (a world's field biases every seed alike).

    python scripts/posts_channel.py --scenarios S8 S2 --json results/learned/posts_channel.json
    python scripts/posts_channel.py --scenarios S2 --family long --json results/learned/posts_channel_long.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import math

import numpy as np

VARIANTS = ((True, 1.0, 1.0), (False, 1.0, 1.0), (True, 0.0, 1.0), (True, 10.0, 1.0), (True, 1.0, 0.1))
"""(the Kalman measurement update on, the fix-wander noise's factor, the attitude information's factor) per row."""


def variant_row(sid: str, seeds: int, world: dict, measurement_update: bool, fix_scale: float,
                att_scale: float) -> dict:
    from warptan.sensing.likelihood import Likelihood
    from warptan.sensing.measurement import MeasurementModel
    from warptan.sim.scenarios import run_scenario_batch

    base, params = Likelihood.fix_process, MeasurementModel.params

    def scaled(self):
        p = params(self)
        p.att_scale = p.att_scale * att_scale
        return p

    Likelihood.fix_process = lambda self, v: fix_scale * base(self, v)  # (this process only)
    MeasurementModel.params = scaled
    try:
        runs = run_scenario_batch(sid, list(range(seeds)), "cpu", duration_s=120.0, bound=False,
                                  measurement_update=measurement_update, **world)
    finally:
        Likelihood.fix_process, MeasurementModel.params = base, params
    sel = runs[0].run.t_s >= runs[0].config.filter.converged_after_s
    err = np.stack([r.run.error[sel, :2] for r in runs])
    sig3 = np.stack([r.run.sigma3_pos[sel, :2] for r in runs])
    att = np.stack([r.run.lin_err[sel, 3:6] for r in runs])
    att3 = np.stack([r.run.sigma3_lin[sel, 3:6] for r in runs])
    return {"scenario": sid, "seeds": seeds, "world": world, "measurement_update": measurement_update,
            "fix_scale": fix_scale, "att_scale": att_scale,
            "horizontal_rmse_m": math.sqrt(float(np.mean(np.sum(err**2, axis=-1)))),
            "coverage_3sigma_ne": np.mean(np.abs(err) <= sig3, axis=(0, 1)).tolist(),
            "attitude_coverage_3sigma": np.mean(np.abs(att) <= att3, axis=(0, 1)).tolist(),
            "roll_error_mean_mrad": 1e3 * float(att[..., 0].mean()),
            "roll_sigma3_mean_mrad": 1e3 * float(att3[..., 0].mean())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", nargs="+", default=["S8"])
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--world-seeds", type=int, nargs="+", default=[2000])
    p.add_argument("--family", choices=("posts", "long"), default="posts",
                   help="posts: the world on the map's own posts; long: the study's long family (sub-post relief)")
    p.add_argument("--json", required=True)
    args = p.parse_args(argv)
    from warptan.meta import run_meta

    rows = []
    for w in args.world_seeds:
        world = {"world_error_rms_m": 5.0, "world_error_corr_m": 1000.0, "world_seed": w,
                 "map_error_rms_m": 5.0, "map_error_corr_m": 1000.0,
                 **({"world_refine": 1} if args.family == "posts" else {"world_relief_rms_m": "auto"})}
        for sid, (update, scale, att) in itertools.product(args.scenarios, VARIANTS):
            row = variant_row(sid, args.seeds, world, update, scale, att)
            rows.append(row)
            print(f"{sid} world {w} update {update!s:5} fix x{scale:g} attitude x{att:g}: "
                  f"RMSE {row['horizontal_rmse_m']:.2f} m, coverage "
                  f"N/E {np.round(row['coverage_3sigma_ne'], 2)}, "
                  f"attitude {np.round(row['attitude_coverage_3sigma'], 2)}"
                  f", roll {row['roll_error_mean_mrad']:+.2f} mrad (3σ {row['roll_sigma3_mean_mrad']:.2f})", flush=True)
    with open(args.json, "w") as fh:
        json.dump({"meta": run_meta(["cpu"], what=__doc__.split("\n\n")[0]), "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
