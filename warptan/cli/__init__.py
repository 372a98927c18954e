"""The ``warptan`` command line: ``warptan run`` (scenarios, reports, plots), ``warptan replay`` (recorded flights),
``warptan campaign`` (sweeps × seeds, local or on Ray) and ``warptan terrain``."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import warnings

from warptan.cli.args import (
    DEFAULT_TERRAIN,
    _finite,
    _relief_arg,
    count_arg,
    heading_arg,
    number_arg,
    script_inputs,
    seed_arg,
    text_arg,
)
from warptan.cli.commands import _campaign, _replay, _run, _stated_accuracy
from warptan.cli.logs import _log_export, _log_import
from warptan.cli.terrain import _terrain_export, _terrain_info

__all__ = ["DEFAULT_TERRAIN", "Terminated", "build_parser", "count_arg", "main", "number_arg", "script_inputs",
           "seed_arg"]


DEVICE_HELP = "Warp device: auto (the default: a CUDA GPU when Warp sees one, else cpu), cpu, cuda:0"


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
    info.add_argument("terrain", type=text_arg, nargs="?", default=DEFAULT_TERRAIN, help=spec_help)
    info.add_argument("--spacing", type=number_arg(0.0, True), default=None, help="resample to this post spacing in m")
    info.add_argument("--json", action="store_true", help="print JSON instead of a table")
    where = info.add_argument_group("information", "where terrain navigation works: the 1σ horizontal position "
                                    "bound of one scan and of a leg of scans at every post (--information)")
    where.add_argument("--information", action="store_true", help="compute the information map")
    where.add_argument("--sensor", type=text_arg, default="S8",
                       help="the sensor of this scenario (S1…S12 or a .toml): its scan or "
                       "altimeter, noise, surface, rate, speed and stated map error (default S8)")
    where.add_argument("--altitude-agl", type=number_arg(0.0, True), default=None, metavar="M",
                       help="height above the terrain in m (default: the scenario's altitude rule, 600 or 150 m)")
    where.add_argument("--heading-deg", type=heading_arg, default=0.0, help="flight heading, degrees from north")
    where.add_argument("--scans", type=count_arg, default=10, help="scans along the leg of the second bound "
                       "(default 10: one second at 10 Hz)")
    where.add_argument("--map-error-m", type=number_arg(0.0, False), default=None, metavar="RMS",
                       help="the DEM's stated correlated error, RMS in m (default: the scenario's)")
    where.add_argument("--map-error-corr-m", type=number_arg(0.0, False), default=None, metavar="L",
                       help="its correlation length in m (default: the scenario's)")
    where.add_argument("--stride", type=count_arg, default=1, help="every N-th post (default 1)")
    where.add_argument("--out", action="append", default=[], metavar="FILE",
                       help="write the map: .png (a picture with units) and/or .tif (GeoTIFF, 2 bands: one scan, "
                       "the leg; needs a DEM with a CRS); may be given twice")
    where.add_argument("--overwrite", action="store_true", help="replace output files that exist")
    info.set_defaults(func=_terrain_info)

    export = tsub.add_parser("export", help="write the triangulated DEM as PLY/GLB/OBJ/STL for viewing")
    export.add_argument("terrain", type=text_arg, help=spec_help)
    export.add_argument("out", type=text_arg, help="output file (.ply, .glb, .obj, .stl)")
    export.add_argument("--spacing", type=number_arg(0.0, True), default=None,
                        help="resample to this post spacing in m")
    export.add_argument("--frame", choices=("enu", "ned"), default="enu", help="vertex frame (default enu, z up)")
    export.add_argument("--overwrite", action="store_true", help="replace the output file if it exists")
    export.set_defaults(func=_terrain_export)

    run = sub.add_parser("run", help="run scenarios S1–S12 (no scenario: a short demonstration)",
                         description="Run paper scenarios with several seeds; write results.json, results.md "
                                     "and PNG plots. Without a scenario: a one-minute demonstration (S8, 60 s, "
                                     "generated rugged terrain).")
    run.add_argument("scenarios", type=text_arg, nargs="*", help="S1 … S12, 'all', or scenario .toml files")
    run.add_argument("--seeds", type=count_arg, default=None, help="seeds per scenario, ≥ 1 (default 1)")
    run.add_argument("--batch", action="store_true",
                     help="run the seeds of a scenario as one batched filter (one launch per kernel for all; "
                          "results as without it)")
    run.add_argument("--device", default="auto", help=DEVICE_HELP)
    run.add_argument("--out", default=None,
                     help="output folder (default warptan-results, demo: warptan-demo)")
    run.add_argument("--paper-rates", action="store_true", help="terrain measurements at the IMU rate, as the paper")
    run.add_argument("--particles", type=count_arg, default=None, help="override the particle count")
    run.add_argument("--backend", default=None, help="ray-cast backend: dda, mesh, bisection")
    run.add_argument("--likelihood", default=None, help="paper, gaussian or student_t")
    run.add_argument("--surface", default=None,
                     help="what the sliding and altimeter models read: triangles (the map's triangulated surface) or "
                          "bilinear")
    run.add_argument("--terrain", type=text_arg, default=None,
                     help="the world of every scenario: rugged, rugged30 (30 m San Gabriel tile), flat, a DEM path "
                          "or synthetic:KIND (default: the scenario's)")
    run.add_argument("--map", type=text_arg, default=None,
                     help="the filter's map from another DEM file of the same ground")
    _renamed(run, "--sim-map-spacing-m", "--map-spacing-m", dest="map_spacing_m", type=number_arg(0.0, True),
             help="SIMULATES a damaged map: coarser posts (block means); the filter is not told")
    _renamed(run, "--sim-map-noise-m", "--map-noise-m", dest="map_noise_m", type=number_arg(0.0, False),
             help="SIMULATES a damaged map: white noise σ per post, m; the filter is not told")
    _renamed(run, "--sim-map-bias-m", "--map-bias-m", dest="map_bias_m", type=_finite,
             help="SIMULATES a damaged map: vertical offset of the map, m; the filter is not told")
    _stated_accuracy(run, "what the filter is told of its map's correlated error (a published accuracy; not the "
                          "simulation's)")
    world = run.add_argument_group("world", "a world that is not the map: the DEM (or --terrain) becomes the filter's "
                                            "map and the flight sees a world made from it (scenario [world] table)")
    world.add_argument("--world-relief-m", default=None, type=_relief_arg,
                       help="sub-post relief RMS, m, or 'auto' (extrapolated from the DEM's spectrum)")
    world.add_argument("--world-relief-slope", default=None, type=_relief_arg,
                       help="spectral slope β of the relief (2-D PSD ∝ k^-β, 2…5), or 'auto'")
    world.add_argument("--world-error-m", type=number_arg(0.0, False), default=None,
                       help="SIMULATES a world that is not the map: RMS of the map's correlated vertical error "
                            "against it, m; the filter is not told")
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
    run.add_argument("--export-log", type=text_arg, default=None, metavar="DIR",
                     help="also write each simulated flight as a warptan flight log DIR/ID_seedN.h5 (warptan replay "
                          "reads it back)")
    run.add_argument("--export-bag", action="store_true",
                     help="with --export-log: also as a ROS 2 bag DIR/ID_seedN_bag (FLU/ENU topics; needs rosbags)")
    run.set_defaults(func=_run)

    rep = sub.add_parser("replay", help="filter a recorded flight (warptan flight log or ROS 2 bag)",
                         description="Run the filter on a recorded flight with its timestamps; write results.json, "
                                     "results.md, plots and the trajectory (CSV; GeoJSON when the DEM has a CRS).")
    rep.add_argument("log", type=text_arg, help="a warptan flight log (.h5) or a ROS 2 bag (folder, .db3 or .mcap)")
    rep.add_argument("--terrain", type=text_arg, default=None,
                     help="the DEM (name, path or spec; default: the log's dem.reference)")
    rep.add_argument("--model", choices=("sliding", "raycast", "altimeter"), default=None,
                     help="measurement model (default: the log's settings, else sliding with scans, altimeter without)")
    rep.add_argument("--backend", default=None, help="ray-cast backend: dda, mesh, bisection")
    rep.add_argument("--likelihood", default=None, help="paper, gaussian or student_t")
    rep.add_argument("--particles", type=count_arg, default=None, help="particle count")
    rep.add_argument("--seed", type=seed_arg, default=None, help="the filter's seed (default: the log's, else 0)")
    rep.add_argument("--device", default="auto", help=DEVICE_HELP)
    rep.add_argument("--out", default=None, help="output folder (default warptan-replay)")
    rep.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    rep.add_argument("--allow-gaps", action="store_true",
                     help="fly through nodata under the track (its updates skipped and counted) instead of refusing")
    rep.add_argument("--quiet", action="store_true", help="no progress bar")
    _stated_accuracy(rep, "its published correlated vertical error (SRTM, Copernicus, DTED): the filter's bounds "
                          "count it")
    bag = rep.add_argument_group("ROS 2 bags", "topics and mounting (a TOML file, or these flags)")
    bag.add_argument("--bag-config", type=text_arg, default=None,
                     help="TOML with topics, mounting, initial σ, IMU grade")
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
    imp.add_argument("layout", type=text_arg, help="the layout .toml (warptan log export writes an example)")
    imp.add_argument("--out", required=True, help="the flight log to write (.h5)")
    imp.set_defaults(func=_log_import)
    exp = lsub.add_parser("export", help="a flight log (with truth and a geodetic frame) → CSV tables and layout.toml")
    exp.add_argument("log", type=text_arg, help="a warptan flight log (.h5)")
    exp.add_argument("--out", required=True, help="a new folder for the tables")
    exp.set_defaults(func=_log_export)

    camp = sub.add_parser("campaign", help="parameter sweeps × seeds × scenarios, in-process or on a Ray cluster",
                          description="Run a campaign file (scenarios, seeds, [overrides], [sweep]): one batch per "
                                      "(scenario, combination), in this process or as Ray tasks; write campaign.json, "
                                      "campaign.md and one plot per swept parameter.")
    camp.add_argument("file", type=text_arg, help="campaign .toml file")
    camp.add_argument("--engine", choices=("local", "ray"), default="local",
                      help="local: in-process, one batch after another (default); ray: one Ray task per batch "
                           "(pip install 'warptan[cluster]')")
    camp.add_argument("--address", default=None,
                      help="Ray cluster address (default: start a local cluster for the campaign)")
    camp.add_argument("--device", default="auto",
                      help="auto (the default: a CUDA GPU when Warp sees one, else cpu), cpu or a CUDA device (local: "
                           "cuda:0; ray: cuda = one GPU per task)")
    camp.add_argument("--cpus-per-task", type=count_arg, default=1,
                      help="ray on the CPU: CPUs each task asks for (its launch threads; default 1)")
    camp.add_argument("--out", default="warptan-campaign",
                      help="output folder (default warptan-campaign)")
    camp.add_argument("--check", action="store_true",
                      help="validate the file and every batch (scenario, seeds, memory, terrain, flight) and stop")
    camp.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    camp.add_argument("--quiet", action="store_true", help="no progress bar")
    camp.set_defaults(func=_campaign)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``warptan`` command; returns the exit status."""
    args = build_parser().parse_args(argv)  # (before Warp is imported: --help and usage errors come at once)
    from warptan.device import quiet_warp
    from warptan.outputs import release_locks

    quiet_warp()
    warnings.formatwarning = _warning_line
    global _SIGTERM_SEEN
    _SIGTERM_SEEN = False
    previous = _terminate_as_interrupt()
    try:
        return args.func(args)
    except (ValueError, OSError) as err:  # every expected failure: one line, exit 2, no traceback
        print(f"warptan: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        if not (isinstance(err, Terminated) or _SIGTERM_SEEN):  # (Ray re-raises a plain KeyboardInterrupt)
            print("warptan: interrupted; the output folder is as it was before this run", file=sys.stderr)
            return 130
        print("warptan: terminated (SIGTERM); the output folder is as it was before this run", file=sys.stderr)
        return 128 + signal.SIGTERM
    finally:
        release_locks()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


_SIGTERM_SEEN = False
"""SIGTERM arrived (a library between the handler and :func:`main` may turn :class:`Terminated` into a plain
KeyboardInterrupt)."""


class _Deprecated(argparse.Action):
    """An option's old name: stores as the new one and says, once per use, that the name will go."""

    def __init__(self, option_strings, dest, new_name: str = "", **kwargs):
        self.new_name = new_name
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"warptan: warning: {option_string} is deprecated and will be removed in the next release: use "
              f"{self.new_name} (the same value: it SIMULATES a damaged map; --map-error-m TELLS the filter)",
              file=sys.stderr)
        setattr(namespace, self.dest, values)


def _renamed(parser, new: str, old: str, dest: str, **kwargs) -> None:
    """``new`` (shown in --help) and its deprecated alias ``old`` (hidden; a warning when used), one value."""
    parser.add_argument(new, dest=dest, default=None, metavar="M", **kwargs)
    parser.add_argument(old, dest=dest, default=None, action=_Deprecated, new_name=new, type=kwargs.get("type"),
                        help=argparse.SUPPRESS)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the command is (as Ctrl-C is) so that it cleans up the same way."""


def _terminate_as_interrupt():
    """Make SIGTERM raise :class:`Terminated` in the main thread; returns the previous handler (None elsewhere)."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum, frame):
        global _SIGTERM_SEEN
        _SIGTERM_SEEN = True
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

