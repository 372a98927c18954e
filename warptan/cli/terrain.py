"""``warptan terrain``: a DEM's description, its information map and its export as a mesh; and the terrain specs
an output must not overwrite."""

from __future__ import annotations

import json
import os


def _terrain_info(args) -> int:
    from warptan.terrain.grid import Terrain

    if args.information:
        return _information(args)
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


def _information(args) -> int:
    """``warptan terrain info DEM --information``: the information map of the DEM for a scenario's sensor."""
    import math

    import numpy as np

    from warptan.nav.flightplan import ABOVE_TERRAIN_M
    from warptan.sim.scenario_config import load_config
    from warptan.sim.scenarios import scenario_scan
    from warptan.terrain.grid import Terrain
    from warptan.terrain.information import check_geotiff_target
    from warptan.terrain.meshfile import check_export_path
    from warptan.terrain.raster import TerrainError

    outs = [check_export_path(o, args.overwrite, (".png", ".tif", ".tiff"), "information map",
                              inputs=_input_files([args.terrain, args.sensor])) for o in args.out]
    if len({os.path.realpath(o) for o in outs}) < len(outs):
        raise TerrainError(f"--out names one file twice ({', '.join(outs)}); nothing was written")
    scenario = load_config(args.sensor)
    lk, scan = scenario.likelihood, scenario_scan(scenario)
    rms = lk.map_error_rms_m if args.map_error_m is None else args.map_error_m
    corr = lk.map_error_corr_m if args.map_error_corr_m is None else args.map_error_corr_m
    agl = ABOVE_TERRAIN_M.get(scenario.flight.altitude_rule, 600.0) if args.altitude_agl is None else args.altitude_agl
    terrain = Terrain.load(args.terrain, spacing=args.spacing)
    for out in outs:
        check_geotiff_target(out, terrain.crs_wkt)
    baro = scan["baro_sigma_m"]
    dirs = [[0.0, 0.0, 1.0]] if scan["dirs_body"] is None else scan["dirs_body"]
    sigma = math.hypot(scan["sigma_m"], baro or 0.0)  # an altimeter's residual carries the barometer's noise
    m = terrain.information_map(dirs, agl, sigma, heading_deg=args.heading_deg, n_scans=args.scans,
                                scan_step_m=scan["step_m"], map_noise_m=scenario.terrain.map_noise_m,
                                map_error_rms_m=rms, map_error_corr_m=corr, vertical_known=baro is not None,
                                surface="triangles" if scan["surface"] else "bilinear", stride=args.stride,
                                sensor=f"{scenario.id} ({scenario.sensor.model})")
    written = [m.save_geotiff(out) if out.lower().endswith((".tif", ".tiff")) else m.save_png(out) for out in outs]
    summary = {"terrain": terrain.name, **m.settings}
    for key, bound in (("one_scan", m.bound_scan_m), ("leg", m.bound_leg_m)):
        on_map = np.isfinite(bound) | np.isinf(bound)
        fixed = np.isfinite(bound)
        summary[f"{key}_bound_median_m"] = float(np.median(bound[fixed])) if fixed.any() else None  # no fix
        summary[f"{key}_fix_fraction"] = float(fixed.sum() / max(on_map.sum(), 1))
    if args.json:
        print(json.dumps({**summary, "files": written}, indent=2))
        return 0
    print(f"information map of {terrain.name} for {m.settings['sensor']} at {agl:g} m above the terrain, heading "
          f"{args.heading_deg:g}°, σ {sigma:g} m" + (f", map error {rms:g} m / {corr:g} m" if rms else ""))
    def median(key):
        value = summary[f"{key}_bound_median_m"]
        return "no fix" if value is None else f"{value:.3g} m"

    print(f"1σ horizontal bound (DRMS), median where the terrain fixes the position: one scan {median('one_scan')} "
          f"({100 * summary['one_scan_fix_fraction']:.0f} % of posts fix it), {args.scans} scans {median('leg')} "
          f"({100 * summary['leg_fix_fraction']:.0f} %)")
    for path in written:
        print(f"wrote {path}")
    return 0


def _terrain_export(args) -> int:
    from warptan.terrain.grid import Terrain
    from warptan.terrain.meshfile import check_export_path

    check_export_path(args.out, args.overwrite, inputs=_input_files([args.terrain]))  # before the DEM is loaded
    terrain = Terrain.load(args.terrain, spacing=args.spacing)
    terrain.export(args.out, frame=args.frame, overwrite=args.overwrite)
    print(f"wrote {args.out} ({terrain.shape[0]}×{terrain.shape[1]} posts, {args.frame.upper()} frame)")
    return 0


def _input_files(items) -> list:
    """``items`` (paths, terrain specs, None) with each terrain spec as the file it reads (a named terrain's file,
    ``WARPTAN_DEM_DIR``'s included; a DEM without its ``#band=N``): what an output folder must not be, hold or lie
    in."""
    from warptan.terrain.grid import terrain_source_file

    return [terrain_source_file(item) or item for item in items]
