"""What each ``warptan`` subcommand does (:func:`warptan.cli.main` parses the arguments and calls one)."""

from __future__ import annotations

import os
import sys

from warptan.cli.args import number_arg
from warptan.cli.terrain import _input_files
from warptan.progress import compile_notice, progress_bar


def _map_words(scenario) -> str:
    t = scenario.terrain  # (the world's name, the terrain, says how it differs)
    parts = [f"map {t.map_path}" if t.map_path else "",
             f"map posts {t.map_spacing_m:g} m" if t.map_spacing_m else "",
             f"map noise {t.map_noise_m:g} m" if t.map_noise_m else "",
             f"map bias {t.map_bias_m:+g} m" if t.map_bias_m else "",
             "the map is the DEM" if scenario.world.active else ""]
    return "".join(", " + p for p in parts if p)


def _scenario_key(name: str) -> str:
    """What makes two scenario arguments the same run: the id (S1…S12, any case) or the file's real path."""
    from warptan.sim.scenario_config import SCENARIO_IDS

    return name.upper() if name.upper() in SCENARIO_IDS else os.path.realpath(name)


def _pick_device(args, cluster: bool = False) -> str:
    """``args.device`` with ``auto`` decided (:func:`warptan.device.auto_device`), in place; returns how the run's
    first line names it (:func:`warptan.device.device_words`)."""
    from warptan.device import auto_device, device_words

    given, args.device = args.device, auto_device(args.device, cluster=cluster)
    return device_words(given, args.device)


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
    device_words = _pick_device(args)
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
                 "map_error_corr_m": args.map_error_corr_m, "map_error_learn": _learn_arg(args.map_error_learn),
                 "map_error_confidence": args.map_error_confidence}
    plans = {name: prepare(name, terrain=terrain, seeds=range(seeds), device=args.device, batched=args.batch,
                           **overrides) for name in names}
    ids = [scenario.id for scenario, _, _ in plans.values()]
    clash = sorted({i for i in ids if ids.count(i) > 1})
    if clash:
        raise ScenarioError(f"two scenarios have the id {', '.join(clash)} (results are kept by id); give one of "
                            "the files another id")
    for scenario, _, _ in plans.values():
        _check_effective(args, scenario)
    inputs = [path for name, (scenario, _, _) in plans.items() for path in _scenario_inputs(name, scenario, terrain)]
    for folder in (out, export):
        if folder is not None:
            folder.refuse_inputs(_input_files(inputs))
    if args.check:
        for scenario, truth, flight in plans.values():
            print(f"{scenario.id}: ok ({truth.name}{_map_words(scenario)}, altitude {-flight.pos_n[0, 2]:.0f} m, "
                  f"{flight.duration_s:.0f} s, {scenario.sensor.model}, {seeds} seed(s); "
                  f"{_size_words(scenario, seeds)})")
        print(f"output folder {out.path}: ok" + (f"; flight logs {export.path}: ok" if export else ""))
        return 0
    if demo:
        print(f"warptan run: no scenario given, running the demonstration: S8 (sliding, navigation IMU) for "
              f"{duration:.0f} s on {terrain}, {seeds} seed(s), device {device_words}")
    elif not args.quiet:
        print(f"warptan run: {', '.join(ids)}, {seeds} seed(s), device {device_words}",
              file=sys.stderr)
    total = 0
    for scenario, _, flight in plans.values():
        decim = 1 if args.paper_rates else round(scenario.imu.rate_hz / scenario.sensor.rate_hz)
        total += seeds * (len(flight.f_b) // decim)
    results, terrains, logs = [], {}, ([] if export is not None else None)
    with progress_bar(total, "update", disable=args.quiet) as bar, compile_notice(_say(args, bar)):
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
    _say(args)(f"writing results{'' if args.no_plots else ' and plots'} to {out.path} ...")
    written = write_outputs(results, out, terrains, plots=not args.no_plots)
    print(written["table"])
    if not written["plots"] and not args.no_plots:
        print("plots skipped: matplotlib is not installed (pip install 'warptan[plot]')")
    print("wrote " + ", ".join(written["files"]))
    _report_unconverged(results)
    return _report_skipped(results)


def _duration_words(seconds: float) -> str:
    """``42 s``, ``3.5 min``, ``2.1 h``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.1f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


def _say(args, bar=None):
    """A line on stderr for what the run is doing (through the progress bar's ``write`` while one is shown, so the
    bar is not torn); nothing with ``--quiet``."""
    if args.quiet:
        return lambda text: None
    if bar is not None and hasattr(bar, "write"):
        return bar.write
    return lambda text: print(text, file=sys.stderr)


def _report_unconverged(results) -> None:
    """A note for every run that declared itself unconverged (:func:`warptan.sim.report.declared_unconverged`)."""
    from warptan.sim.report import UNCONVERGED_3SIGMA_M, declared_unconverged

    for r in results:
        if declared_unconverged(r.run, r.config.filter.converged_after_s):
            print(f"warptan: note: {r.scenario} seed {r.seed}: unconverged: its horizontal 3σ after convergence "
                  f"exceeds {UNCONVERGED_3SIGMA_M:g} m (declared_unconverged in results.json)")


def _report_skipped(results, allow_gaps: bool = False) -> int:
    """A line for every run in which updates were skipped; 1 (after an error line) when a run used none of its
    updates (it navigated nothing: INS only), or (unless ``allow_gaps``) fewer than half of them (199 of 200 skipped
    over a DEM with data on a strip only had been exit 0 with a note), else 0."""
    from warptan.sim.report import update_counts

    blind, mostly = [], []
    for r in results:
        updates, skipped, used = update_counts(r.run)
        label = f"{r.scenario} seed {r.seed}"
        if used == 0 and updates > 0:
            blind.append(label)
        elif 2 * used < updates and not allow_gaps:
            mostly.append(f"{label} ({updates - used} of {updates})")
        elif used < updates:
            print(f"warptan: note: {label}: {updates - used} of {updates} updates were not used ({skipped} skipped: "
                  f"the map could not predict the scan; {updates - skipped - used} without a valid measurement)")
    if blind:
        print(f"warptan: error: {', '.join(blind)}: every update was skipped (no valid measurement, or the map does "
              "not cover the scans): the run navigated nothing (INS only); results were written, marked "
              "updates_used = 0 in results.json", file=sys.stderr)
        return 1
    if mostly:
        print(f"warptan: error: {', '.join(mostly)}: most updates were not used (no valid measurement, or the map "
              "does not cover the scans): the run navigated mostly on its INS; results were written, with their "
              "update counts in results.json (replay --allow-gaps accepts a flight over gaps)", file=sys.stderr)
        return 1
    return 0


def _refuse_nested(out, export) -> None:
    """--out and --export-log are two folders, neither inside the other."""
    from warptan.outputs import OutputError

    a, b = out.path, export.path
    if a == b or a in b.parents or b in a.parents:
        raise OutputError(f"--export-log {b} and --out {a} must be separate folders, neither inside the other")


def _check_effective(args, scenario) -> None:
    """Refuse (ScenarioError) an option that would change nothing in ``scenario`` (it was silently ignored): a
    correlation length without a stated RMS (or without the world's error RMS), clutter without a height or a
    fraction, a refined world that is the map."""
    from warptan.sim.scenario_config import ScenarioError

    w, where = scenario.world, f"scenario {scenario.id}"
    if args.map_error_corr_m is not None and not scenario.likelihood.map_error_rms_m:
        raise ScenarioError(f"{where}: --map-error-corr-m {args.map_error_corr_m:g} is the correlation length of a "
                            "stated map error, and none is stated: give --map-error-m too (they go together)")
    if args.world_error_corr_m is not None and not w.error_rms_m:
        raise ScenarioError(f"{where}: --world-error-corr-m {args.world_error_corr_m:g} is the correlation length of "
                            "the world's error, and it has none: give --world-error-m too (they go together)")
    if (args.world_clutter_m is not None or args.world_clutter_fraction is not None) and not (
            w.clutter_height_m and w.clutter_fraction):
        raise ScenarioError(f"{where}: clutter needs a height and a fraction of the ground (now "
                            f"--world-clutter-m {w.clutter_height_m:g}, --world-clutter-fraction "
                            f"{w.clutter_fraction:g}): with either 0 there is none; give both")
    if args.world_refine is not None and not w.active:
        raise ScenarioError(f"{where}: --world-refine {args.world_refine} refines a world that differs from the map, "
                            "and this one is the map: give the difference too (--world-relief-m, --world-error-m, "
                            "--world-bias-m or --world-clutter-m)")


def _size_words(scenario, seeds: int) -> str:
    """What a run of ``seeds`` seeds holds and evaluates (checked against memory before work)."""
    from warptan.sim.scenario_config import format_bytes, memory_estimate, scan_points

    updates = round(scenario.flight.duration_s * scenario.sensor.rate_hz) * seeds
    need = memory_estimate(scenario, seeds)
    return (f"{updates} updates × {scenario.filter.particles} particles × {scan_points(scenario)} point(s), about "
            f"{format_bytes(need['host'])} of host memory")


def _scenario_inputs(name: str, scenario, terrain) -> list:
    """The files a scenario run reads: its scenario file (not for S1…S12), the world's DEM and the map's DEM."""
    from warptan.sim.scenario_config import SCENARIO_IDS, scenario_path

    t = scenario.terrain
    world = terrain if isinstance(terrain, (str, os.PathLike)) else t.dem  # (a name: its file, WARPTAN_DEM_DIR's)
    return [None if name.upper() in SCENARIO_IDS else scenario_path(name), world, t.map_path or None]


def _campaign(args) -> int:
    from warptan.outputs import OutputFolder
    from warptan.sim.campaign import Campaign
    from warptan.sim.campaign_report import write_campaign
    from warptan.sim.campaign_run import check_options, run_campaign

    out = OutputFolder(args.out, kind="campaign")
    campaign = Campaign.load(args.file)
    device_words = _pick_device(args, cluster=args.engine == "ray")
    plans = campaign.check(check_options(args.engine, args.device, args.address, args.cpus_per_task))
    scenario_dems = [d for scenario, _, _ in plans for d in (scenario.terrain.dem, scenario.terrain.map_path or None)]
    out.refuse_inputs(_input_files([args.file, *campaign.inputs(), *scenario_dems]))
    if args.check:
        from warptan.sim.campaign_run import estimate_batch_s

        where, total = args.device, 0.0  # (auto decided by _pick_device)
        for b, (scenario, truth, flight) in zip(campaign.batches, plans, strict=True):
            eta = estimate_batch_s(b, flight.duration_s, where)
            total += eta
            print(f"{b.label}: ok ({truth.name}{_map_words(scenario)}, {flight.duration_s:.0f} s, "
                  f"{scenario.sensor.model}, {len(b.seeds)} seed(s){'' if b.batched else ', seed by seed'}; "
                  f"about {_duration_words(eta)} on {where})")
        print(f"{len(campaign.batches)} batch(es), about {_duration_words(total)} one after the other on {where} "
              f"(timed from a 1 s pilot of each batch); output folder {out.path}: ok")
        return 0
    if not args.quiet:
        print(f"warptan campaign {campaign.title}: {len(campaign.batches)} batch(es) × {len(campaign.seeds)} seed(s), "
              f"engine {args.engine}, device {device_words}", file=sys.stderr)
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
    out.refuse_inputs(_input_files([args.log, _bag_folder(args.log), args.terrain, args.bag_config]))
    device_words = _pick_device(args)
    resolve_device(args.device)
    log = _load_flight(args)
    out.refuse_inputs(_input_files([log.dem_reference or None, log.settings.get("terrain_spec")]))
    from warptan.sim.replay import check_replay_memory, replay_config, replay_terrain

    stated = None
    if args.map_error_m is not None or args.map_error_corr_m is not None:
        if args.map_error_m is None or (args.map_error_m > 0 and args.map_error_corr_m is None):
            raise ValueError("--map-error-m and --map-error-corr-m go together (the DEM's stated accuracy: RMS and "
                              "correlation length of its vertical error, m)")
        stated = (args.map_error_m, args.map_error_corr_m or 0.0)
    learn = _learn_arg(args.map_error_learn)
    scenario = replay_config(log, args.model, args.backend, args.particles, args.likelihood, stated,
                             map_error_learn=learn, map_error_confidence=args.map_error_confidence)  # checks them
    check_replay_memory(log, scenario, args.device)
    replay_terrain(log, scenario, args.terrain)  # loads (and caches) the DEM before the progress bar
    n_meas = len(log.alt_t if scenario.sensor.model == "altimeter" else log.scan_t)
    if not args.quiet:
        print(f"warptan replay: {log.name}, device {device_words}", file=sys.stderr)
    with progress_bar(n_meas, "update", disable=args.quiet) as bar, compile_notice(_say(args, bar)):
        bar.set_description(f"replay {log.name}")
        result = replay(log, args.terrain, model=args.model, backend=args.backend, particles=args.particles,
                        likelihood=args.likelihood, seed=args.seed, device=args.device,
                        progress=lambda k, n: bar.update(1), allow_gaps=args.allow_gaps, map_error=stated,
                        map_error_learn=learn, map_error_confidence=args.map_error_confidence)
    dropped = result.run.info.get("dropped_measurements", 0)
    if dropped:
        print(f"warptan: note: {dropped} measurement(s) outside the IMU's time span were not used")
    if result.run.info.get("gaps_allowed"):
        print(f"warptan: note: --allow-gaps: {result.run.info['track_points_over_nodata']} track point(s) over nodata; "
              "the updates there were skipped (skipped_updates in results.json)")
    _say(args)(f"writing results{'' if args.no_plots else ' and plots'} to {out.path} ...")
    written = write_outputs([result], out, {result.scenario: result.truth_terrain}, plots=not args.no_plots,
                            trajectories=True, title=f"warptan replay of {log.name}")
    print(written["table"])
    if not log.has_truth:
        print("(the log has no truth: errors are undefined; results.json holds the estimate and its 3σ)")
    print("wrote " + ", ".join(written["files"]))
    _report_unconverged([result])
    return _report_skipped([result], allow_gaps=args.allow_gaps)


def _learn_arg(value: str | None):
    """``--map-error-learn``'s value as ``likelihood.map_error_learn`` (None: the scenario's)."""
    return {"on": True, "off": False}.get(value, value)


def _stated_accuracy(parser, description: str) -> None:
    """``--map-error-m`` and ``--map-error-corr-m``: the DEM's stated accuracy (likelihood.map_error_rms_m and
    map_error_corr_m)."""
    group = parser.add_argument_group("the DEM's stated accuracy", description)
    group.add_argument("--map-error-m", type=number_arg(0.0, False), default=None,
                       help="TELLS the filter the RMS of its map's correlated vertical error (a published "
                            "accuracy), m; simulates nothing (likelihood.map_error_rms_m)")
    group.add_argument("--map-error-corr-m", type=number_arg(0.0, False), default=None,
                       help="its correlation length, m (likelihood.map_error_corr_m)")
    group.add_argument("--map-error-learn", choices=("auto", "on", "off"), default=None,
                       help="learn the error's RMS in flight, the statement (or 5 m / 500 m; an altimeter 5 m / 2 km) "
                            "its prior: auto (the default) whenever the map is not known to be the world or an error "
                            "is stated (likelihood.map_error_learn)")
    group.add_argument("--map-error-confidence", type=number_arg(1.0, False), default=None, metavar="F",
                       help="the factor (1-10) the stated (or default) RMS is right within, default 2: the learned "
                            "RMS stays under F times it and the altitude's σ counts F times it for the map's offset, "
                            "which no scan sees (likelihood.map_error_confidence)")


def _bag_folder(path: str) -> str | None:
    """The bag folder of a bag's .db3/.mcap file (the whole bag is the input), else None."""
    if path.endswith((".db3", ".mcap")) and os.path.isfile(os.path.join(os.path.dirname(path) or ".", "metadata.yaml")):
        return os.path.dirname(os.path.abspath(path))
    return None


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
