"""Wall time of the information map (:func:`warptan.terrain.information.information_map`) of a DEM for a scenario's
sensor, median of ``--repeats`` after one run that compiles; with and without the scenario's stated map error.

    python scripts/bench_information_map.py --terrain rugged --sensor S8 --json info_cpu.json
    python scripts/bench_information_map.py --device cuda:0 --terrain rugged --sensor S8 --json info_h100.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

from warptan.cli import count_arg, script_inputs
from warptan.meta import run_meta


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--terrain", default="rugged")
    parser.add_argument("--sensor", default="S8")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--altitude-agl", type=float, default=600.0)
    parser.add_argument("--scans", type=count_arg, default=10)
    parser.add_argument("--repeats", type=count_arg, default=3)
    parser.add_argument("--json", dest="json_out")
    args = parser.parse_args(argv)
    terrain = script_inputs("bench_information_map", [args.device], args.terrain)
    import warp as wp

    from warptan.sensing.sensors import ScanPattern
    from warptan.sim.scenario_config import load_config

    s = load_config(args.sensor).sensor
    dirs = ScanPattern.grid(s.scan_nx, s.scan_ny, s.scan_half_angle_deg).dirs_s
    rows = []
    for label, error in (("no map error", {}), ("stated map error 5 m / 1 km",
                                                {"map_error_rms_m": 5.0, "map_error_corr_m": 1000.0})):
        def run(error=error):
            m = terrain.information_map(dirs, args.altitude_agl, s.range_sigma_m, n_scans=args.scans,
                                        device=args.device, **error)
            wp.synchronize_device(args.device)
            return m

        run()
        walls = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            m = run()
            walls.append(time.perf_counter() - t0)
        fixed = np.isfinite(m.bound_scan_m)
        rows.append({"case": label, "wall_s": statistics.median(walls), "walls_s": walls,
                     "posts": int(m.bound_scan_m.size), "rays": int(m.settings["rays"]), "scans": args.scans,
                     "error_modes": m.settings["error_modes"],
                     "bound_scan_median_m": float(np.median(m.bound_scan_m[fixed])) if fixed.any() else None,
                     "bound_leg_median_m": float(np.nanmedian(np.where(np.isinf(m.bound_leg_m), np.nan,
                                                                       m.bound_leg_m)))})
        print(f"{label}: {rows[-1]['wall_s']:.2f} s for {rows[-1]['posts']} posts ({terrain.name}, {args.sensor})")
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"meta": run_meta([args.device], terrain=terrain.name, sensor=args.sensor,
                                        spacing_m=[terrain.dn, terrain.de], shape=list(terrain.shape),
                                        what=__doc__.split("\n\n")[0]), "rows": rows}, fh, indent=1)
        print(f"wrote {args.json_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
