"""The documentation's picture of where terrain navigation works: the information map of the shipped rugged tile for
S8 (a 10 × 10 point cloud: one scan, and ten along a leg) and S9 (the radar altimeter with a barometer: one reading
fixes nothing, 100 readings along a north leg do), at the scenarios' 600 m above the terrain.

    python scripts/information_figure.py --out results/information/rugged_S8_S9.png \
        --json results/information/rugged_S8_S9.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from warptan.cli import script_inputs
from warptan.meta import run_meta


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--terrain", default="rugged")
    parser.add_argument("--out", required=True)
    parser.add_argument("--json", dest="json_out")
    parser.add_argument("--stride", type=int, default=1)
    args = parser.parse_args(argv)
    terrain = script_inputs("information_figure", ["cpu"], args.terrain)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    from warptan.sim.scenario_config import load_config
    from warptan.sim.scenarios import scenario_scan

    s8, s9 = scenario_scan(load_config("S8")), scenario_scan(load_config("S9"))
    cloud = terrain.information_map(s8["dirs_body"], 600.0, s8["sigma_m"], n_scans=10, scan_step_m=s8["step_m"],
                                    stride=args.stride, sensor="S8")
    alt = terrain.information_map([[0.0, 0.0, 1.0]], 600.0, math.hypot(s9["sigma_m"], s9["baro_sigma_m"]),
                                  n_scans=100, scan_step_m=s9["step_m"], vertical_known=True, stride=args.stride,
                                  sensor="S9")
    panels = [(cloud.bound_scan_m, "S8 point cloud, one scan"), (cloud.bound_leg_m, "S8, 10 scans (1 s)"),
              (alt.bound_leg_m, "S9 altimeter, 100 readings (10 s, north)")]
    extent = [cloud.east_m[0] / 1e3, cloud.east_m[-1] / 1e3, cloud.north_m[0] / 1e3, cloud.north_m[-1] / 1e3]
    norm = LogNorm(vmin=0.1, vmax=300.0)
    cmap = plt.get_cmap("viridis").copy()
    cmap.set_over("0.6")
    cmap.set_bad("white")
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8), constrained_layout=True)
    stats = {}
    for ax, (bound, title) in zip(axes, panels, strict=True):
        shown = np.where(np.isinf(bound), np.inf, np.minimum(bound, norm.vmax))
        im = ax.imshow(shown, origin="lower", extent=extent, cmap=cmap, norm=norm, interpolation="nearest")
        ax.set_title(title)
        ax.set_xlabel("east (km)")
        fixed = np.isfinite(bound)
        stats[title] = {"median_m": float(np.median(bound[fixed])) if fixed.any() else None,
                        "fix_fraction": float(fixed.sum() / max((~np.isnan(bound)).sum(), 1))}
    axes[0].set_ylabel("north (km)")
    fig.colorbar(im, ax=axes, extend="max", label="1σ horizontal position bound (m), grey: no fix")
    fig.suptitle(f"Where terrain navigation works: {terrain.name}, 600 m above the terrain, heading north")
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"meta": run_meta(["cpu"], terrain=terrain.name, what=__doc__.split("\n\n")[0]),
                       "panels": stats, "settings": {"S8": cloud.settings, "S9": alt.settings}}, fh, indent=1)
        print(f"wrote {args.json_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
