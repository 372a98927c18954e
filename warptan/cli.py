"""The ``warptan`` command line: terrain inspection and export (scenario runs come with the runner)."""

from __future__ import annotations

import argparse
import json
import sys

DEFAULT_TERRAIN = "synthetic:rugged"


def _terrain_info(args) -> int:
    from warptan.terrain import Terrain

    terrain = Terrain.load(args.terrain, spacing=args.spacing)
    info = terrain.info()
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    n_min, n_max, e_min, e_max = info["bounds_ne_m"]
    lines = [
        f"terrain     {info['name']}",
        f"source      {info['description']}",
        f"CRS         {info['crs']}",
        f"shape       {info['shape'][0]} rows (north) × {info['shape'][1]} cols (east)",
        f"spacing     {info['spacing_m'][0]:.3f} m north, {info['spacing_m'][1]:.3f} m east",
        f"bounds      north {n_min:.1f} … {n_max:.1f} m, east {e_min:.1f} … {e_max:.1f} m",
    ]
    if "bounds_latlon_deg" in info:
        la0, la1, lo0, lo1 = info["bounds_latlon_deg"]
        lines.append(f"            lat {la0:.5f} … {la1:.5f}°, lon {lo0:.5f} … {lo1:.5f}° (SW and NE corners)")
    lines += [
        f"heights     {info['height_range_m'][0]:.1f} … {info['height_range_m'][1]:.1f} m above MSL",
        f"nodata      {100.0 * info['nodata_fraction']:.3f} % of posts",
    ]
    print("\n".join(lines))
    return 0


def _terrain_export(args) -> int:
    from warptan.terrain import Terrain

    terrain = Terrain.load(args.terrain, spacing=args.spacing)
    terrain.export(args.out, frame=args.frame)
    print(f"wrote {args.out} ({terrain.shape[0]}×{terrain.shape[1]} posts, {args.frame.upper()} frame)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="warptan", description="Terrain-aided navigation on NVIDIA Warp.")
    sub = parser.add_subparsers(dest="command", required=True)

    terrain = sub.add_parser("terrain", help="inspect or export a DEM")
    tsub = terrain.add_subparsers(dest="terrain_command", required=True)
    spec_help = "a DEM file (DTED, .hgt, GeoTIFF, .npz) or synthetic:rugged|flat[,size_m=..,spacing=..,seed=..]"

    info = tsub.add_parser("info", help="CRS, bounds, spacing, shape, height range, nodata fraction")
    info.add_argument("terrain", nargs="?", default=DEFAULT_TERRAIN, help=spec_help)
    info.add_argument("--spacing", type=float, default=None, help="resample to this post spacing in m")
    info.add_argument("--json", action="store_true", help="print JSON instead of a table")
    info.set_defaults(func=_terrain_info)

    export = tsub.add_parser("export", help="write the triangulated DEM as PLY/GLB/OBJ/STL for viewing")
    export.add_argument("terrain", help=spec_help)
    export.add_argument("out", help="output file (.ply, .glb, .obj, .stl)")
    export.add_argument("--spacing", type=float, default=None, help="resample to this post spacing in m")
    export.add_argument("--frame", choices=("enu", "ned"), default="enu", help="vertex frame (default enu, z up)")
    export.set_defaults(func=_terrain_export)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``warptan`` command; returns the exit status."""
    import warp as wp

    wp.config.quiet = True
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as err:
        print(f"warptan: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
