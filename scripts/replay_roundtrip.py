"""Round trip of whole simulated flights through the flight log and a ROS 2 bag: ``warptan run`` in memory vs
``warptan replay`` of its exported ``.h5`` and bag (same device). Prints one line per scenario and writes JSON.

    python scripts/replay_roundtrip.py --scenarios S8 S7 S10 --json results/replay_roundtrip.json
"""

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from warptan.device import quiet_warp
from warptan.io.flightlog import read_log, write_log
from warptan.io.rosbag import read_bag, write_bag
from warptan.meta import run_meta
from warptan.sim.replay import replay
from warptan.sim.scenarios import run_scenario

FIELDS = ("est_pos", "sigma3_pos", "ess", "lin_err", "sigma3_lin")
ESTIMATE = ("est_pos", "sigma3_pos", "ess", "sigma3_lin")
"""What the filter gives (the bag's truth attitude passes a quaternion frame change, so ``lin_err`` may differ by
float rounding)."""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=["S8", "S7", "S10"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    quiet_warp()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for sid in args.scenarios:
            logs = []
            ref = run_scenario(sid, seed=args.seed, export_logs=logs)
            path = write_log(logs[0], Path(tmp) / f"{sid}.h5")
            t0 = time.perf_counter()
            h5 = replay(read_log(path))
            wall = time.perf_counter() - t0
            bag_dir = Path(tmp) / f"{sid}_bag"
            shutil.rmtree(bag_dir, ignore_errors=True)
            write_bag(logs[0], bag_dir)
            bag = replay(read_bag(bag_dir))
            row = {"scenario": sid, "model": ref.config.sensor.model, "epochs": len(ref.run.t_s),
                   "h5_identical": all(np.array_equal(getattr(ref.run, f), getattr(h5.run, f)) for f in FIELDS),
                   "bag_estimate_identical": all(np.array_equal(getattr(ref.run, f), getattr(bag.run, f))
                                                 for f in ESTIMATE),
                   "bag_max_abs_att_err_diff_deg": float(np.degrees(np.max(np.abs(bag.run.lin_err[:, 3:6]
                                                                                  - ref.run.lin_err[:, 3:6])))),
                   "bag_max_abs_est_diff_m": float(np.max(np.abs(bag.run.est_pos - ref.run.est_pos))),
                   "rmse_converged_m": ref.rmse_converged.tolist(), "replay_wall_s": wall,
                   "log_mb": path.stat().st_size / 1e6}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"meta": run_meta(["cpu"]), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
