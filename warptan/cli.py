"""The ``warptan`` command line: ``warptan run`` (scenarios, reports, plots), ``warptan replay`` (recorded flights),
``warptan campaign`` (sweeps × seeds, local or on Ray) and ``warptan terrain``."""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading
import warnings
from pathlib import Path

from warptan.progress import progress_bar

DEFAULT_TERRAIN = "synthetic:rugged"


def count_arg(text: str) -> int:
    """argparse type: a whole number ≥ 1 (the command line's and the scripts' counts)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number ≥ 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be ≥ 1, got {value}")
    return value


def seed_arg(text: str) -> int:
    """argparse type: a seed, a whole number in [0, 2**63)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number ≥ 0, got {text!r}") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**63), got {value}")
    return value


def number_arg(minimum: float, strict: bool):
    """argparse type: a finite number > minimum (strict) or ≥ minimum."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
        if not math.isfinite(value) or value < minimum or (strict and value == minimum):
            raise argparse.ArgumentTypeError(f"must be a finite number {'>' if strict else '≥'} {minimum:g}, "
                                             f"got {text!r}")
        return value
    return parse


def _relief_arg(text: str):
    """argparse type: 'auto' or a finite number (checked with the scenario)."""
    return "auto" if text.strip().lower() == "auto" else _finite(text)


def _finite(text: str) -> float:
    """argparse type: any finite number."""
    return number_arg(-math.inf, False)(text)


def _terrain_info(args) -> int:
    from warptan.terrain.grid import Terrain

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
    from warptan.terrain.grid import Terrain, check_export_path

    check_export_path(args.out, args.overwrite)  # before the DEM is loaded
    terrain = Terrain.load(args.terrain, spacing=args.spacing)
    terrain.export(args.out, frame=args.frame, overwrite=args.overwrite)
    print(f"wrote {args.out} ({terrain.shape[0]}×{terrain.shape[1]} posts, {args.frame.upper()} frame)")
    return 0


def _map_words(config: dict) -> str:
    from warptan.terrain.world import WorldModel

    model = WorldModel.from_config(config["world"])  # the world's name (the terrain) says how it differs
    t = config["terrain"]
    parts = [f"map {t['map_path']}" if t["map_path"] else "",
             f"map posts {t['map_spacing_m']:g} m" if t["map_spacing_m"] else "",
             f"map noise {t['map_noise_m']:g} m" if t["map_noise_m"] else "",
             f"map bias {t['map_bias_m']:+g} m" if t["map_bias_m"] else "",
             "the map is the DEM" if model.active else ""]
    return "".join(", " + p for p in parts if p)


def _scenario_key(name: str) -> str:
    """What makes two scenario arguments the same run: the id (S1…S12, any case) or the file's real path."""
    from warptan.sim.scenario_config import SCENARIO_IDS

    return name.upper() if name.upper() in SCENARIO_IDS else os.path.realpath(name)


def _run(args) -> int:
    from warptan.device import resolve_device
    from warptan.outputs import OutputFolder
    from warptan.sim.report import write_outputs
    from warptan.sim.scenario_config import SCENARIO_IDS, ScenarioError
    from warptan.sim.scenarios import prepare, run_scenario, run_scenario_batch

    demo = not args.scenarios
    names = ["S8"] if demo else list(args.scenarios)
    if [n.lower() for n in names] == ["all"]:
        names = list(SCENARIO_IDS)
    elif any(n.lower() == "all" for n in names):
        raise ScenarioError("'all' runs every scenario; give it alone, not with other scenarios")
    keys = [_scenario_key(n) for n in names]
    repeated = sorted({n for n, k in zip(names, keys, strict=True) if keys.count(k) > 1})
    if repeated:
        raise ScenarioError(f"scenario(s) {', '.join(repeated)} given more than once; use --seeds for more runs")
    terrain = args.terrain or ("synthetic:rugged" if demo else None)
    duration = args.duration_s if args.duration_s is not None else (60.0 if demo else None)
    seeds = args.seeds if args.seeds is not None else 1
    # Validate everything before any computation: the output folder, the device, every scenario (file,
    # overrides, seeds, memory, terrain, flight, map). --check stops here.
    out = OutputFolder(args.out if args.out is not None else ("warptan-demo" if demo else "warptan-results"),
                       kind="run")
    export = None
    if args.export_log is not None:
        export = OutputFolder(args.export_log, kind="flight-logs", option="--export-log")
        _refuse_nested(out, export)
        if args.export_bag:
            _require_rosbags()
    elif args.export_bag:
        raise ScenarioError("--export-bag writes beside --export-log; give --export-log DIR")
    resolve_device(args.device)
    overrides = {"particles": args.particles, "backend": args.backend, "surface": args.surface,
                 "likelihood": args.likelihood,
                 "duration_s": duration, "paper_rates": args.paper_rates,
                 "use_baro": False if args.no_baro else None, "map_path": args.map,
                 "map_spacing_m": args.map_spacing_m, "map_noise_m": args.map_noise_m, "map_bias_m": args.map_bias_m,
                 "world_relief_rms_m": args.world_relief_m, "world_relief_slope": args.world_relief_slope,
                 "world_error_rms_m": args.world_error_m, "world_error_corr_m": args.world_error_corr_m,
                 "world_bias_m": args.world_bias_m, "world_clutter_height_m": args.world_clutter_m,
                 "world_clutter_fraction": args.world_clutter_fraction, "world_refine": args.world_refine,
                 "world_seed": args.world_seed, "map_error_rms_m": args.map_error_m,
                 "map_error_corr_m": args.map_error_corr_m}
    plans = {name: prepare(name, terrain=terrain, seeds=range(seeds), device=args.device, batched=args.batch,
                           **overrides) for name in names}
    ids = [config["id"] for config, _, _ in plans.values()]
    clash = sorted({i for i in ids if ids.count(i) > 1})
    if clash:
        raise ScenarioError(f"two scenarios have the id {', '.join(clash)} (results are kept by id); give one of "
                            "the files another id")
    inputs = [path for name, (config, _, _) in plans.items() for path in _scenario_inputs(name, config, terrain)]
    for folder in (out, export):
        if folder is not None:
            folder.refuse_inputs(inputs)
    if args.check:
        for config, truth, flight in plans.values():
            print(f"{config['id']}: ok ({truth.name}{_map_words(config)}, altitude {-flight.pos_n[0, 2]:.0f} m, "
                  f"{flight.duration_s:.0f} s, {config['sensor']['model']}, {seeds} seed(s))")
        print(f"output folder {out.path}: ok" + (f"; flight logs {export.path}: ok" if export else ""))
        return 0
    if demo:
        print(f"warptan run: no scenario given, running the demonstration: S8 (sliding, navigation IMU) for "
              f"{duration:.0f} s on {terrain}, {seeds} seed(s), device {args.device}")
    total = 0
    for config, _, flight in plans.values():
        decim = 1 if args.paper_rates else round(config["imu"]["rate_hz"] / config["sensor"]["rate_hz"])
        total += seeds * (len(flight.f_b) // decim)
    results, terrains, logs = [], {}, ([] if export is not None else None)
    with progress_bar(total, "update", disable=args.quiet) as bar:
        for name in names:
            if args.batch:
                bar.set_description(f"{name} seeds 0-{seeds - 1} (batch)")
                batch = run_scenario_batch(name, list(range(seeds)), device=args.device,
                                           progress=lambda k, n: bar.update(seeds), export_logs=logs,
                                           terrain=terrain, **overrides)
            else:
                batch = []
                for seed in range(seeds):
                    bar.set_description(f"{name} seed {seed}")
                    batch.append(run_scenario(name, seed=seed, device=args.device,
                                              progress=lambda k, n: bar.update(1), export_logs=logs, terrain=terrain,
                                              **overrides))
            results.extend(batch)
            terrains[batch[0].scenario] = batch[0].truth_terrain
    if export is not None:
        _write_logs(logs, export, args.export_bag)
    written = write_outputs(results, out, terrains, plots=not args.no_plots)
    print(written["table"])
    if not written["plots"] and not args.no_plots:
        print("plots skipped: matplotlib is not installed (pip install 'warptan[plot]')")
    print("wrote " + ", ".join(written["files"]))
    _report_unconverged(results)
    return _report_skipped(results)


def _report_unconverged(results) -> None:
    """A note for every run that declared itself unconverged (:func:`warptan.sim.report.declared_unconverged`)."""
    from warptan.sim.report import UNCONVERGED_3SIGMA_M, declared_unconverged

    for r in results:
        if declared_unconverged(r.run, r.config["filter"]["converged_after_s"]):
            print(f"warptan: note: {r.scenario} seed {r.seed}: unconverged: its horizontal 3σ after convergence "
                  f"exceeds {UNCONVERGED_3SIGMA_M:g} m (declared_unconverged in results.json)")


def _report_skipped(results) -> int:
    """A line for every run in which updates were skipped; 1 (after an error line) when a run used none of its
    updates (it navigated nothing: INS only), else 0."""
    from warptan.sim.report import update_counts

    blind = []
    for r in results:
        updates, skipped, used = update_counts(r.run)
        label = f"{r.scenario} seed {r.seed}"
        if used == 0 and updates > 0:
            blind.append(label)
        elif used < updates:
            print(f"warptan: note: {label}: {updates - used} of {updates} updates were not used ({skipped} skipped: "
                  f"the map could not predict the scan; {updates - skipped - used} without a valid measurement)")
    if blind:
        print(f"warptan: error: {', '.join(blind)}: every update was skipped (no valid measurement, or the map does "
              "not cover the scans): the run navigated nothing (INS only); results were written, marked "
              "updates_used = 0 in results.json", file=sys.stderr)
        return 1
    return 0


def _refuse_nested(out, export) -> None:
    """--out and --export-log are two folders, neither inside the other."""
    from warptan.outputs import OutputError

    a, b = out.path, export.path
    if a == b or a in b.parents or b in a.parents:
        raise OutputError(f"--export-log {b} and --out {a} must be separate folders, neither inside the other")


def _scenario_inputs(name: str, config: dict, terrain) -> list:
    """The files a scenario run reads: its scenario file (not for S1…S12), the world's DEM and the map's DEM."""
    from warptan.sim.scenario_config import SCENARIO_IDS, scenario_path

    t = config["terrain"]
    world = terrain if isinstance(terrain, (str, os.PathLike)) else (t["path"] if t["kind"] == "path" else None)
    return [None if name.upper() in SCENARIO_IDS else scenario_path(name), world, t["map_path"] or None]


def _campaign(args) -> int:
    from warptan.outputs import OutputFolder
    from warptan.sim.campaign import Campaign, check_options, run_campaign, write_campaign

    out = OutputFolder(args.out, kind="campaign")
    campaign = Campaign.load(args.file)
    plans = campaign.check(check_options(args.engine, args.device, args.address, args.cpus_per_task))
    out.refuse_inputs([args.file, *campaign.inputs()])
    if args.check:
        for b, (config, truth, flight) in zip(campaign.batches, plans, strict=True):
            print(f"{b.label}: ok ({truth.name}{_map_words(config)}, {flight.duration_s:.0f} s, "
                  f"{config['sensor']['model']}, {len(b.seeds)} seed(s){'' if b.batched else ', seed by seed'})")
        print(f"{len(campaign.batches)} batch(es); output folder {out.path}: ok")
        return 0
    if not args.quiet:
        print(f"warptan campaign {campaign.title}: {len(campaign.batches)} batch(es) × {len(campaign.seeds)} seed(s), "
              f"engine {args.engine}, device {args.device}", file=sys.stderr)
    result = run_campaign(campaign, engine=args.engine, device=args.device, address=args.address,
                          cpus_per_task=args.cpus_per_task, progress=not args.quiet, checked=True)
    written = write_campaign(result, out, plots=not args.no_plots)
    print(written["table"])
    if not written["plots"] and not args.no_plots and campaign.sweep:
        print("plots skipped: matplotlib is not installed (pip install 'warptan[plot]')")
    print("wrote " + ", ".join(written["files"]))
    blind = [f"{row['scenario']}{''.join(f' {k}={v}' for k, v in row['params'].items())} seed(s) "
             f"{row['seeds_without_any_update']}" for row in result.rows if row["seeds_without_any_update"]]
    if blind:
        print(f"warptan: error: {len(blind)} batch(es) have runs whose every update was skipped (they navigated "
              f"nothing; seeds_without_any_update in campaign.json): {'; '.join(blind[:5])}", file=sys.stderr)
    if result.failures:
        kept = f"the other {len(result.rows)} row(s) were written" if result.rows else "no row was written"
        print(f"warptan: error: {len(result.failures)} of {len(campaign.batches)} batch(es) failed after "
              f"{result.failures[0]['attempts']} attempts (listed in campaign.json and campaign.md); {kept}",
              file=sys.stderr)
    return 1 if result.failures or blind else 0


def _require_rosbags() -> None:
    try:
        import rosbags  # noqa: F401
    except ModuleNotFoundError:
        raise OSError("ROS 2 bags need the rosbags package: pip install 'warptan[ros]'") from None


def _write_logs(logs, folder, bags: bool) -> None:
    """Each flight as ``NAME.h5`` (and ``NAME_bag/`` with ``--export-bag``) in ``folder``, as one whole."""
    from warptan.io.flightlog import write_log

    names = []
    with folder as out:
        for log in logs:
            write_log(log, out / f"{log.name}.h5")
            names.append(f"{log.name}.h5")
            if bags:
                from warptan.io.rosbag import write_bag

                write_bag(log, out / f"{log.name}_bag")
                names.append(f"{log.name}_bag")
    print(f"wrote flight logs in {folder.path}: " + ", ".join(names))


def _replay(args) -> int:
    from warptan.device import resolve_device
    from warptan.outputs import OutputFolder
    from warptan.sim.replay import replay
    from warptan.sim.report import write_outputs

    out = OutputFolder(args.out if args.out is not None else "warptan-replay", kind="replay")
    out.refuse_inputs([args.log, _bag_folder(args.log), args.terrain, args.bag_config])
    resolve_device(args.device)
    log = _load_flight(args)
    out.refuse_inputs([log.dem_reference or None, log.settings.get("terrain_spec")])
    from warptan.sim.replay import replay_config, replay_terrain

    stated = None
    if args.map_error_m is not None or args.map_error_corr_m is not None:
        if args.map_error_m is None or (args.map_error_m > 0 and args.map_error_corr_m is None):
            raise ValueError("--map-error-m and --map-error-corr-m go together (the DEM's stated accuracy: RMS and "
                              "correlation length of its vertical error, m)")
        stated = (args.map_error_m, args.map_error_corr_m or 0.0)
    config = replay_config(log, args.model, args.backend, args.particles, args.likelihood, stated)  # checks them
    replay_terrain(log, config, args.terrain)  # loads (and caches) the DEM before the progress bar
    n_meas = len(log.alt_t if config["sensor"]["model"] == "altimeter" else log.scan_t)
    with progress_bar(n_meas, "update", disable=args.quiet) as bar:
        bar.set_description(f"replay {log.name}")
        result = replay(log, args.terrain, model=args.model, backend=args.backend, particles=args.particles,
                        likelihood=args.likelihood, seed=args.seed, device=args.device,
                        progress=lambda k, n: bar.update(1), allow_gaps=args.allow_gaps, map_error=stated)
    dropped = result.run.info.get("dropped_measurements", 0)
    if dropped:
        print(f"warptan: note: {dropped} measurement(s) outside the IMU's time span were not used")
    if result.run.info.get("gaps_allowed"):
        print(f"warptan: note: --allow-gaps: {result.run.info['track_points_over_nodata']} track point(s) over nodata; "
              "the updates there were skipped (skipped_updates in results.json)")
    written = write_outputs([result], out, {result.scenario: result.truth_terrain}, plots=not args.no_plots,
                            trajectories=True, title=f"warptan replay of {log.name}")
    print(written["table"])
    if not log.has_truth:
        print("(the log has no truth: errors are undefined; results.json holds the estimate and its 3σ)")
    print("wrote " + ", ".join(written["files"]))
    _report_unconverged([result])
    return _report_skipped([result])


def _stated_accuracy(parser, description: str) -> None:
    """``--map-error-m`` and ``--map-error-corr-m``: the DEM's stated accuracy (likelihood.map_error_rms_m and
    map_error_corr_m)."""
    group = parser.add_argument_group("the DEM's stated accuracy", description)
    group.add_argument("--map-error-m", type=number_arg(0.0, False), default=None,
                       help="RMS of the map's correlated vertical error, m (likelihood.map_error_rms_m)")
    group.add_argument("--map-error-corr-m", type=number_arg(0.0, False), default=None,
                       help="its correlation length, m (likelihood.map_error_corr_m)")


def _bag_folder(path: str) -> str | None:
    """The bag folder of a bag's .db3/.mcap file (the whole bag is the input), else None."""
    if path.endswith((".db3", ".mcap")) and os.path.isfile(os.path.join(os.path.dirname(path) or ".", "metadata.yaml")):
        return os.path.dirname(os.path.abspath(path))
    return None


def _log_import(args) -> int:
    from warptan.io.flightlog import LogError, write_log
    from warptan.io.logcsv import read_tables

    out = Path(args.out)
    if out.exists():
        raise LogError(f"--out {out}", ["exists; remove it or choose another name"])
    log = read_tables(args.layout)
    write_log(log, out)
    f = log.frame
    print(f"wrote {out}: {len(log.imu_t)} IMU samples, {len(log.scan_t) if log.has_scans else 0} scans, "
          f"{len(log.alt_t) if log.has_altimeter else 0} altimeter readings; frame origin lat {f.origin_lat_deg:.6f}°, "
          f"lon {f.origin_lon_deg:.6f}° (datum {f.vertical_datum or 'not stated'})")
    return 0


def _log_export(args) -> int:
    from warptan.io.flightlog import LogError, read_log
    from warptan.io.logcsv import write_tables

    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise LogError(f"--out {out}", ["is not empty; choose a new folder"])
    layout = write_tables(read_log(args.log), out)
    print(f"wrote {layout} and its tables in {out}")
    return 0


def _load_flight(args):
    """The LOG argument: a warptan flight log (.h5) or a ROS 2 bag (folder, .db3 or .mcap)."""
    from warptan.io.flightlog import read_log

    path = args.log
    bag_options = [f"--{name.replace('_', '-')}" for name in ("bag_config", "imu_topic", "cloud_topic", "range_topic",
                                                              "baro_topic", "odom_topic", "imu_grade")
                   if getattr(args, name) is not None]
    if os.path.isdir(path) or path.endswith((".db3", ".mcap")):
        _require_rosbags()
        from warptan.io.rosbag import BagConfig, read_bag

        config = BagConfig.load(args.bag_config) if args.bag_config else BagConfig.for_bag(path)
        config = config.with_overrides(imu=args.imu_topic, cloud=args.cloud_topic, range=args.range_topic,
                                       baro=args.baro_topic, odom=args.odom_topic, grade=args.imu_grade)
        return read_bag(path, config)
    if bag_options:
        raise ValueError(f"{', '.join(bag_options)}: for ROS 2 bags; {path} is a warptan flight log, which carries "
                         "its own settings")
    return read_log(path)


def script_inputs(prog: str, devices: list[str], terrain_spec: str):
    """For the benchmark scripts: silence Warp, check the device names and load the terrain; a bad name or
    terrain prints one line and exits with status 2 (no traceback)."""
    from warptan.device import quiet_warp, resolve_device
    from warptan.terrain.grid import Terrain

    quiet_warp()
    try:
        for d in devices:
            resolve_device(d)
        return Terrain.load(terrain_spec)
    except (ValueError, FileNotFoundError) as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None


def build_parser() -> argparse.ArgumentParser:
    from warptan import __version__

    parser = argparse.ArgumentParser(prog="warptan", description="Terrain-aided navigation on NVIDIA Warp.")
    parser.add_argument("--version", action="version", version=f"warptan {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    terrain = sub.add_parser("terrain", help="inspect or export a DEM")
    tsub = terrain.add_subparsers(dest="terrain_command", required=True)
    spec_help = ("rugged, rugged30, flat (real DEMs shipped with warptan), a DEM file (DTED, .hgt, GeoTIFF, .npz) "
                 "or synthetic:rugged|flat[,size_m=..,spacing=..,seed=..]")

    info = tsub.add_parser("info", help="CRS, bounds, spacing, shape, height range, nodata fraction")
    info.add_argument("terrain", nargs="?", default=DEFAULT_TERRAIN, help=spec_help)
    info.add_argument("--spacing", type=number_arg(0.0, True), default=None, help="resample to this post spacing in m")
    info.add_argument("--json", action="store_true", help="print JSON instead of a table")
    info.set_defaults(func=_terrain_info)

    export = tsub.add_parser("export", help="write the triangulated DEM as PLY/GLB/OBJ/STL for viewing")
    export.add_argument("terrain", help=spec_help)
    export.add_argument("out", help="output file (.ply, .glb, .obj, .stl)")
    export.add_argument("--spacing", type=number_arg(0.0, True), default=None,
                        help="resample to this post spacing in m")
    export.add_argument("--frame", choices=("enu", "ned"), default="enu", help="vertex frame (default enu, z up)")
    export.add_argument("--overwrite", action="store_true", help="replace the output file if it exists")
    export.set_defaults(func=_terrain_export)

    run = sub.add_parser("run", help="run scenarios S1–S12 (no scenario: a short demonstration)",
                         description="Run paper scenarios with several seeds; write results.json, results.md "
                                     "and PNG plots. Without a scenario: a one-minute demonstration (S8, 60 s, "
                                     "generated rugged terrain).")
    run.add_argument("scenarios", nargs="*", help="S1 … S12, 'all', or scenario .toml files")
    run.add_argument("--seeds", type=count_arg, default=None, help="seeds per scenario, ≥ 1 (default 1)")
    run.add_argument("--batch", action="store_true",
                     help="run the seeds of a scenario as one batched filter (one launch per kernel for all; "
                          "results as without it)")
    run.add_argument("--device", default="cpu", help="Warp device (cpu, cuda:0)")
    run.add_argument("--out", default=None, help="output folder (default warptan-results, demo: warptan-demo)")
    run.add_argument("--paper-rates", action="store_true", help="terrain measurements at the IMU rate, as the paper")
    run.add_argument("--particles", type=count_arg, default=None, help="override the particle count")
    run.add_argument("--backend", default=None, help="ray-cast backend: dda, mesh, bisection")
    run.add_argument("--likelihood", default=None, help="paper, gaussian or student_t")
    run.add_argument("--surface", default=None,
                     help="what the sliding and altimeter models read: triangles (the map's triangulated surface) or "
                          "bilinear")
    run.add_argument("--terrain", default=None,
                     help="the world of every scenario: rugged, rugged30 (30 m San Gabriel tile), flat, a DEM path "
                          "or synthetic:KIND (default: the scenario's)")
    run.add_argument("--map", default=None, help="the filter's map from another DEM file of the same ground")
    run.add_argument("--map-spacing-m", type=number_arg(0.0, True), default=None,
                     help="map error: coarser posts (block means)")
    run.add_argument("--map-noise-m", type=number_arg(0.0, False), default=None,
                     help="map error: white noise σ per post, m")
    run.add_argument("--map-bias-m", type=_finite, default=None,
                     help="map error: vertical offset of the map, m")
    _stated_accuracy(run, "what the filter is told of its map's correlated error (a published accuracy; not the "
                          "simulation's)")
    world = run.add_argument_group("world", "a world that is not the map: the DEM (or --terrain) becomes the filter's "
                                            "map and the flight sees a world made from it (scenario [world] table)")
    world.add_argument("--world-relief-m", default=None, type=_relief_arg,
                       help="sub-post relief RMS, m, or 'auto' (extrapolated from the DEM's spectrum)")
    world.add_argument("--world-relief-slope", default=None, type=_relief_arg,
                       help="spectral slope β of the relief (2-D PSD ∝ k^-β, 2…5), or 'auto'")
    world.add_argument("--world-error-m", type=number_arg(0.0, False), default=None,
                       help="RMS of the map's correlated vertical error, m")
    world.add_argument("--world-error-corr-m", type=number_arg(0.0, False), default=None,
                       help="correlation length of that error, m (≥ one map post)")
    world.add_argument("--world-bias-m", type=_finite, default=None, help="the map reads this much higher, m")
    world.add_argument("--world-clutter-m", type=number_arg(0.0, False), default=None,
                       help="height of canopy / buildings, m")
    world.add_argument("--world-clutter-fraction", type=number_arg(0.0, False), default=None,
                       help="fraction of the ground under clutter, [0, 1]")
    world.add_argument("--world-refine", type=count_arg, default=None, help="world posts per map post (default 3)")
    world.add_argument("--world-seed", type=int, default=None,
                       help="realisation of the world's random fields (-1: each run's own)")
    run.add_argument("--duration-s", type=number_arg(0.0, True), default=None,
                     help="override the flight duration, s (at least one measurement interval)")
    run.add_argument("--no-baro", action="store_true", help="altimeter scenarios without a barometer")
    run.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    run.add_argument("--check", action="store_true",
                     help="validate everything a run would (scenarios, seeds, memory, terrain, flight, map, --out) "
                          "and stop")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.add_argument("--export-log", default=None, metavar="DIR",
                     help="also write each simulated flight as a warptan flight log DIR/ID_seedN.h5 (warptan replay "
                          "reads it back)")
    run.add_argument("--export-bag", action="store_true",
                     help="with --export-log: also as a ROS 2 bag DIR/ID_seedN_bag (FLU/ENU topics; needs rosbags)")
    run.set_defaults(func=_run)

    rep = sub.add_parser("replay", help="filter a recorded flight (warptan flight log or ROS 2 bag)",
                         description="Run the filter on a recorded flight with its timestamps; write results.json, "
                                     "results.md, plots and the trajectory (CSV; GeoJSON when the DEM has a CRS).")
    rep.add_argument("log", help="a warptan flight log (.h5) or a ROS 2 bag (folder, .db3 or .mcap)")
    rep.add_argument("--terrain", default=None, help="the DEM (name, path or spec; default: the log's dem.reference)")
    rep.add_argument("--model", choices=("sliding", "raycast", "altimeter"), default=None,
                     help="measurement model (default: the log's settings, else sliding with scans, altimeter without)")
    rep.add_argument("--backend", default=None, help="ray-cast backend: dda, mesh, bisection")
    rep.add_argument("--likelihood", default=None, help="paper, gaussian or student_t")
    rep.add_argument("--particles", type=count_arg, default=None, help="particle count")
    rep.add_argument("--seed", type=seed_arg, default=None, help="the filter's seed (default: the log's, else 0)")
    rep.add_argument("--device", default="cpu", help="Warp device (cpu, cuda:0)")
    rep.add_argument("--out", default=None, help="output folder (default warptan-replay)")
    rep.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    rep.add_argument("--allow-gaps", action="store_true",
                     help="fly through nodata under the track (its updates skipped and counted) instead of refusing")
    rep.add_argument("--quiet", action="store_true", help="no progress bar")
    _stated_accuracy(rep, "its published correlated vertical error (SRTM, Copernicus, DTED): the filter's bounds "
                          "count it")
    bag = rep.add_argument_group("ROS 2 bags", "topics and mounting (a TOML file, or these flags)")
    bag.add_argument("--bag-config", default=None, help="TOML with topics, mounting, initial σ, IMU grade")
    bag.add_argument("--imu-topic", default=None, help="sensor_msgs/Imu topic (default /imu)")
    bag.add_argument("--cloud-topic", default=None, help="sensor_msgs/PointCloud2 topic (default /points)")
    bag.add_argument("--range-topic", default=None, help="sensor_msgs/Range altimeter topic (default /altimeter)")
    bag.add_argument("--baro-topic", default=None, help="sensor_msgs/FluidPressure topic (default /baro)")
    bag.add_argument("--odom-topic", default=None, help="nav_msgs/Odometry truth topic (default /truth)")
    bag.add_argument("--imu-grade", default=None, help="IMU grade (default navigation)")
    rep.set_defaults(func=_replay)

    logp = sub.add_parser("log", help="flight logs from tables of what a vehicle records, and back")
    lsub = logp.add_subparsers(dest="log_command", required=True)
    imp = lsub.add_parser("import", help="CSV tables described by a layout TOML (GPS lat/lon/height, IMU, scans or "
                                         "altimeter, baro) → a flight log (see warptan.io.logcsv)")
    imp.add_argument("layout", help="the layout .toml (warptan log export writes an example)")
    imp.add_argument("--out", required=True, help="the flight log to write (.h5)")
    imp.set_defaults(func=_log_import)
    exp = lsub.add_parser("export", help="a flight log (with truth and a geodetic frame) → CSV tables and layout.toml")
    exp.add_argument("log", help="a warptan flight log (.h5)")
    exp.add_argument("--out", required=True, help="a new folder for the tables")
    exp.set_defaults(func=_log_export)

    camp = sub.add_parser("campaign", help="parameter sweeps × seeds × scenarios, in-process or on a Ray cluster",
                          description="Run a campaign file (scenarios, seeds, [overrides], [sweep]): one batch per "
                                      "(scenario, combination), in this process or as Ray tasks; write campaign.json, "
                                      "campaign.md and one plot per swept parameter.")
    camp.add_argument("file", help="campaign .toml file")
    camp.add_argument("--engine", choices=("local", "ray"), default="local",
                      help="local: in-process, one batch after another (default); ray: one Ray task per batch "
                           "(pip install 'warptan[cluster]')")
    camp.add_argument("--address", default=None,
                      help="Ray cluster address (default: start a local cluster for the campaign)")
    camp.add_argument("--device", default="cpu",
                      help="cpu or a CUDA device (local: cuda:0; ray: cuda = one GPU per task)")
    camp.add_argument("--cpus-per-task", type=count_arg, default=1,
                      help="ray on the CPU: CPUs each task asks for (its launch threads; default 1)")
    camp.add_argument("--out", default="warptan-campaign", help="output folder (default warptan-campaign)")
    camp.add_argument("--check", action="store_true",
                      help="validate the file and every batch (scenario, seeds, memory, terrain, flight) and stop")
    camp.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    camp.add_argument("--quiet", action="store_true", help="no progress bar")
    camp.set_defaults(func=_campaign)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``warptan`` command; returns the exit status."""
    from warptan.device import quiet_warp
    from warptan.outputs import release_locks

    quiet_warp()
    args = build_parser().parse_args(argv)
    warnings.formatwarning = _warning_line
    previous = _terminate_as_interrupt()
    try:
        return args.func(args)
    except (ValueError, OSError) as err:  # every expected failure: one line, exit 2, no traceback
        print(f"warptan: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except Terminated:
        print("warptan: terminated (SIGTERM); the output folder is as it was before this run", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("warptan: interrupted; the output folder is as it was before this run", file=sys.stderr)
        return 130
    finally:
        release_locks()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the command is (as Ctrl-C is) so that it cleans up the same way."""


def _terminate_as_interrupt():
    """Make SIGTERM raise :class:`Terminated` in the main thread; returns the previous handler (None elsewhere)."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum, frame):
        raise Terminated()

    return signal.signal(signal.SIGTERM, handler)


def _warning_line(message, category, *_, **__) -> str:
    """A Python warning as the command line shows it: one line."""
    return f"warptan: warning: {message}\n"


def _one_line(err: BaseException) -> str:
    """An error as one line (a multi-problem scenario error keeps its list, joined by '; ')."""
    if isinstance(err, OSError) and err.filename and str(err.filename) not in str(err):
        return f"{err.strerror or err}: {err.filename}"
    parts = [part.strip() for part in str(err).splitlines() if part.strip()] or [type(err).__name__]
    line = parts[0]
    for part in parts[1:]:
        line += (" " if line.endswith(":") else "; ") + part
    return line


if __name__ == "__main__":
    sys.exit(main())
