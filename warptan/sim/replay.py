"""Filtering a recorded flight (``warptan replay``): a :class:`~warptan.io.flightlog.FlightLog` through the same filter
as ``warptan run``, and simulated runs written as flight logs (``warptan run --export-log``).

Timing: IMU sample k is held over its step ``[t_k, t_k+1)``; each step is integrated with its own length (the
filter's ``predict_many(..., dt=)``). A step within 1 ppm of the nominal period (1 / ``imu.rate_hz``) is taken as the
nominal period (float rounding of timestamps, not jitter), so an evenly sampled log runs exactly as the simulator.
A measurement between two IMU samples **splits** that sample's step: the filter integrates the sample up to the
measurement time, updates, and integrates the rest of the step after it (no interpolation of IMU data). A
measurement within 1 ppm of a period of a sample boundary is taken at the boundary. Measurements before the first
IMU sample or after the end of the last step are not used (counted in ``info["dropped_measurements"]``). The
altimeter's barometric altitude is the barometer stream interpolated linearly at the altimeter's time (NaN = none
when the barometer has no reading within 1 s).

Truth, when the log has it, is interpolated to the update times (linear; quaternions normalised; exact at a
recorded time), for the errors; without truth the errors are NaN and the report shows the estimate and its 3σ.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import time

import numpy as np

from warptan.checks import FilterError, check_seed
from warptan.device import auto_device
from warptan.filter.config import MIN_PARTICLES
from warptan.filter.mpf import MarginalizedParticleFilter
from warptan.io.export import convert_log
from warptan.io.flightlog import MAX_GAP_S, FlightLog, LogError, sample_at
from warptan.nav.frames import quat_to_mat
from warptan.nav.geoframe import corners, frame_change
from warptan.nav.imu import imu_grade
from warptan.nav.ins import Ins, NavState
from warptan.sensing.likelihood import Likelihood, check_confidence
from warptan.sensing.sensors import AltimeterReading, PointCloud
from warptan.sim.runner import collect_runs
from warptan.sim.scenario_config import Scenario

SNAP = 1e-6
"""Relative tolerance (of the nominal period) within which a step is the nominal period and a time a boundary."""


# ---------------------------------------------------------------------- simulation -> log
def timeline(log: FlightLog, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The filter's steps for measurements at ``times``: ``(sample, dt, ends, used)`` — the IMU sample index and
    length of each step, the number of steps before each used measurement, and which measurements are used (inside
    the IMU span)."""
    nominal = 1.0 / log.imu_rate_hz
    tol = SNAP * nominal
    edges = np.r_[log.imu_t, log.t_end]
    full = np.diff(edges)
    full = np.where(np.abs(full - nominal) <= tol, nominal, full)
    used = (times >= edges[0] - tol) & (times <= edges[-1] + tol)
    sample, dts, ends = [], [], []
    t_cur, k = edges[0], 0
    for tm in times[used]:
        near = int(np.clip(np.searchsorted(edges, tm), 1, len(edges) - 1))
        for j in (near - 1, near):
            if abs(edges[j] - tm) <= tol:
                tm = edges[j]
        tm = max(tm, t_cur)
        while k < len(full) and edges[k + 1] <= tm:
            sample.append(k)
            dts.append(full[k] if t_cur == edges[k] else edges[k + 1] - t_cur)
            t_cur = edges[k + 1]
            k += 1
        if t_cur < tm:
            sample.append(k)
            dts.append(tm - t_cur)
            t_cur = tm
        ends.append(len(sample))
    return np.array(sample, dtype=np.int64), np.array(dts, dtype=np.float64), np.array(ends, dtype=np.int64), used


def _measurements(log: FlightLog, model_name: str, idx: np.ndarray) -> list:
    """The filter's measurement objects of the log's measurements ``idx`` (altimeter readings or point clouds)."""
    if model_name == "altimeter":
        t = log.alt_t[idx]
        baro = np.full(len(idx), np.nan)
        if log.baro_t is not None:
            baro = np.interp(t, log.baro_t, log.baro_alt, left=np.nan, right=np.nan)
            after = np.clip(np.searchsorted(log.baro_t, t), 0, len(log.baro_t) - 1)
            before = np.maximum(after - 1, 0)
            gap = np.minimum(np.abs(log.baro_t[after] - t), np.abs(log.baro_t[before] - t))
            baro[gap > MAX_GAP_S] = np.nan
        return [AltimeterReading(float(log.alt_range[j]), float(h)) for j, h in zip(idx, baro, strict=True)]
    rot = quat_to_mat(log.mount_quat)
    mounted = not (np.array_equal(log.mount_quat, [1.0, 0.0, 0.0, 0.0]) and not log.mount_lever.any())
    clouds = []
    for j in idx:
        ranges = np.where(log.scan_valid[j], log.scan_ranges[j], np.nan)
        dirs = np.where(log.scan_valid[j][:, None], log.scan_dirs[j], [0.0, 0.0, 1.0])
        if mounted:  # body-frame points, as range and direction from the body origin
            clouds.append(PointCloud.from_points((ranges[:, None] * dirs) @ rot.T + log.mount_lever))
        else:
            clouds.append(PointCloud(dirs, ranges))
    return clouds


# ---------------------------------------------------------------------- replay
SETTINGS = {"config": dict, "likelihood": dict, "seed": int, "scenario_seed": int, "terrain_spec": str,
            "dem_sha256": str}
"""A flight log's ``settings`` keys (what ``run --export-log`` writes) and their JSON types."""


def check_settings(log: FlightLog) -> None:
    """Refuse (:class:`LogError`, every problem named ``settings.KEY``) a log whose settings a replay would read
    wrong: an unknown key, a value of the wrong type, a ``config`` the scenario schema refuses, a ``likelihood``
    with keys the :class:`~warptan.sensing.likelihood.Likelihood` lacks or values it refuses (hand-edited
    ``settings_json`` was a raw TypeError or KeyError on replay, or silently ignored)."""
    from warptan.sim.scenario_schema import validate, with_optional_defaults

    problems = []
    for key, value in log.settings.items():
        kind = SETTINGS.get(key)
        if kind is None:
            hint = difflib.get_close_matches(str(key), list(SETTINGS), n=1)
            problems.append(f"settings: unknown key {key!r}" + (f" (did you mean {hint[0]!r}?)" if hint else ""))
        elif kind is int and (isinstance(value, bool) or not isinstance(value, int) or value < 0):
            problems.append(f"settings.{key} must be a whole number ≥ 0, got {value!r}")
        elif not isinstance(value, kind):
            problems.append(f"settings.{key} must be a JSON {'object' if kind is dict else 'string'}, got "
                            f"{value!r:.60}")
    config, stored = log.settings.get("config"), log.settings.get("likelihood")
    if isinstance(config, dict):
        problems += [f"settings.config: {p[2:]}" for p in validate(with_optional_defaults(dict(config)), "")]
    if isinstance(stored, dict):
        names = {f.name for f in dataclasses.fields(Likelihood)}
        unknown = sorted(set(stored) - names, key=str)
        problems += [f"settings.likelihood: unknown key {k!r}" for k in unknown]
        if not unknown:
            try:
                Likelihood(**stored)
            except (TypeError, ValueError, FilterError) as err:
                problems.append(f"settings.likelihood: {err}")
    if problems:
        raise LogError(f"flight log {log.name}", problems)


def replay_config(log: FlightLog, model: str | None = None, backend: str | None = None,
                  particles: int | None = None, likelihood: str | None = None,
                  map_error: tuple[float, float] | None = None, map_error_learn: bool | str | None = None,
                  map_error_confidence: float | None = None) -> Scenario:
    """The scenario of a replay: the one the log was simulated with (settings), else S8's filter and likelihood
    settings with the log's IMU grade, sensor and rates; the keywords override (``map_error``: the DEM's stated
    accuracy, ``(RMS, correlation length)`` in m: ``likelihood.map_error_rms_m`` and ``map_error_corr_m``;
    ``map_error_confidence``: the factor its RMS is right within)."""
    from warptan.sim.scenario_config import load_config

    check_settings(log)
    stored = log.settings.get("config")
    scenario = load_config("S8") if stored is None else Scenario.from_tables(stored)
    if stored is None:
        times = log.scan_t if log.has_scans else log.alt_t
        sensor = {"model": "sliding" if log.has_scans else "altimeter", "range_sigma_m": log.range_sigma_m,
                  "altimeter_sigma_m": log.altimeter_sigma_m, "baro_sigma_m": log.baro_sigma_m,
                  "use_baro": log.baro_t is not None}
        if len(times) > 1:
            sensor["rate_hz"] = float(1.0 / np.median(np.diff(times)))
        duration = float(log.t_end - log.imu_t[0])
        scenario = dataclasses.replace(scenario.replace(
            imu={"grade": log.imu_grade, "rate_hz": log.imu_rate_hz}, sensor=sensor,
            flight={"speed_mps": float(max(np.linalg.norm(log.init_vel), 1.0)), "duration_s": duration,
                    "bank_deg": math.nan, "altitude_rule": "recorded"},
            filter={"converged_after_s": min(scenario.filter.converged_after_s, 0.5 * duration)}),
            id="replay", description=f"replay of {log.name}", paper_rmse_m=(math.nan,) * 3)
    if map_error is not None:
        rms, corr = (float(v) for v in map_error)
        if not (math.isfinite(rms) and rms >= 0.0 and math.isfinite(corr) and corr >= 0.0) or (rms > 0 and corr <= 0):
            raise FilterError(f"the DEM's stated accuracy must be an RMS ≥ 0 m and, with an RMS, a correlation length "
                              f"> 0 m; got RMS {rms!r} m, correlation length {corr!r} m")
        scenario = scenario.replace(likelihood={"map_error_rms_m": rms, "map_error_corr_m": corr})
    if map_error_learn is not None:
        if map_error_learn not in (True, False, "auto"):
            raise FilterError(f"map_error_learn must be 'auto', True or False, got {map_error_learn!r}")
        scenario = scenario.replace(likelihood={"map_error_learn": map_error_learn})
    if map_error_confidence is not None:
        scenario = scenario.replace(likelihood={"map_error_confidence": check_confidence(map_error_confidence)})
    if model is not None:
        if model not in ("sliding", "raycast", "altimeter"):
            raise FilterError(f"unknown model {model!r}; choose sliding, raycast or altimeter")
        scenario = scenario.replace(sensor={"model": model})
    if backend is not None:
        from warptan.terrain.raycast import BACKENDS

        if backend not in BACKENDS:  # (warp9 was accepted: the sliding model never reads it)
            raise FilterError(f"unknown backend {backend!r}; choose {', '.join(BACKENDS)}")
        scenario = scenario.replace(sensor={"backend": backend})
    if particles is not None:
        if isinstance(particles, bool) or not isinstance(particles, (int, np.integer)) or particles < MIN_PARTICLES:
            raise FilterError(f"particles must be a whole number ≥ {MIN_PARTICLES}, got {particles!r}")
        scenario = scenario.replace(filter={"particles": int(particles)})
    if likelihood is not None:
        from warptan.sensing.likelihood import LIKELIHOODS

        if likelihood not in LIKELIHOODS:
            raise FilterError(f"unknown likelihood {likelihood!r}; choose {', '.join(LIKELIHOODS)}")
        scenario = scenario.replace(likelihood={"kind": likelihood})
    kind = scenario.sensor.model
    if kind == "altimeter" and not log.has_altimeter:
        raise LogError(f"flight log {log.name}", ["the altimeter model needs altimeter readings (group /altimeter)"])
    if kind != "altimeter" and not log.has_scans:
        raise LogError(f"flight log {log.name}", [f"the {kind} model needs point-cloud scans (group /scans)"])
    return scenario


def check_replay_memory(log: FlightLog, scenario: Scenario, device) -> None:
    """Refuse (FilterError) a replay whose particles' arrays exceed what ``device`` has (as a run is checked before
    work; 10⁹ particles were a raw allocation error)."""
    from warptan.sim.scenario_config import MEMORY_FRACTION, available_memory, format_bytes, particle_bytes

    s = scenario.sensor
    points = 1 if s.model == "altimeter" or not log.has_scans else int(np.shape(log.scan_ranges)[-1])
    need = particle_bytes(scenario.filter.particles, points, s.model)
    have = available_memory(device if device is not None else "cpu")["device"]
    if need > MEMORY_FRACTION * have:
        raise FilterError(f"{scenario.filter.particles} particles × {points} point(s) need about {format_bytes(need)} "
                          f"of device memory but {format_bytes(have)} is available; use fewer particles")


def _simulated_on_its_map(ran: Scenario) -> bool:
    """The log was simulated over its own DEM as the world (no ``[world]``, no other map, noise, bias or coarsening):
    replayed over that DEM, its map is known to be the world."""
    from warptan.terrain.world import WorldModel

    t = ran.terrain
    world = WorldModel.from_config(dataclasses.asdict(ran.world))
    return not (world.active or t.map_path or t.map_noise_m or t.map_bias_m or t.map_spacing_m)


def _likelihood(log: FlightLog, scenario: Scenario, the_map, own: bool = True) -> Likelihood:
    """The log's stored likelihood when the model and likelihood are the ones it was simulated with, else the
    scenarios' calibration (:func:`~warptan.sim.scenarios.scenario_likelihood`) with the scan footprint measured from
    the log: the along-track extent of its directions at their median range. Over a DEM other than the log's own
    (``own`` False; another crop or projection is another grid of posts) the stored map σ also counts the map's
    interpolation error at its posts, as ``likelihood.map_aware`` does for a map whose grid is not the world's
    (:meth:`~warptan.terrain.grid.Terrain.interpolation_sigma_m`). The map error is learned in flight
    (:func:`~warptan.sim.scenarios.learned_statement`) unless the log was simulated over this DEM as its world
    (:func:`_simulated_on_its_map`): a recorded flight's map is never known to be its world."""
    from warptan.sim.scenarios import fix_geometry, learned_statement, scenario_likelihood

    stored, stored_config = log.settings.get("likelihood"), log.settings.get("config")
    lk = scenario.likelihood
    ran = Scenario.from_tables(stored_config) if stored_config is not None else None
    if stored is not None and ran is not None and (ran.sensor.model, ran.likelihood.kind) == (scenario.sensor.model,
                                                                                           lk.kind):
        lik = Likelihood(**stored)
        rms, corr, learn = learned_statement(lk, own and _simulated_on_its_map(ran), max(the_map.dn, the_map.de),
                                             scenario.sensor.model == "altimeter")
        if (rms, corr, learn, lk.map_error_confidence) != (lik.map_error_sigma_m, lik.map_error_corr_m,
                                                           lik.map_error_learn, lik.map_error_confidence):
            lik = dataclasses.replace(lik, map_error_sigma_m=rms, map_error_corr_m=corr, map_error_learn=learn,
                                      map_error_confidence=lk.map_error_confidence,
                                      **fix_geometry(the_map, rms, _footprint(lik, ran)))
        if not own and lk.map_aware:
            lik = dataclasses.replace(lik, map_sigma_m=math.hypot(lik.map_sigma_m,
                                                                  the_map.interpolation_sigma_m(lik.map_sigma_m)))
        return lik
    footprint = None
    if scenario.sensor.model != "altimeter":
        valid = log.scan_valid
        median_range = float(np.nanmedian(np.where(valid, log.scan_ranges, np.nan)))
        along = np.where(valid, log.scan_dirs[..., 0] / np.maximum(log.scan_dirs[..., 2], 1e-3), np.nan)
        footprint = median_range * float(np.nanmax(along) - np.nanmin(along)) if np.isfinite(along).any() else 0.0
    return scenario_likelihood(scenario, the_map, None, footprint_m=footprint)


def _footprint(lik: Likelihood, ran: Scenario) -> float:
    """The scan footprint of the run a log was simulated with: its stored likelihood's, else its flight's at the
    altitude rule's clearance (0 for the altimeter)."""
    if lik.fix_footprint_m or ran.sensor.model == "altimeter":
        return lik.fix_footprint_m
    return ran.flight.footprint_m(ran.sensor.scan_half_angle_deg)


def check_coverage(log: FlightLog, terrain, ins_pos: np.ndarray, allow_gaps: bool = False) -> int:
    """A :class:`LogError` when the DEM does not cover the flight — the initial position and the truth (without
    truth: the INS-only track at the updates) leave it (both extents named, in latitude/longitude when the DEM has a
    CRS), or pass over nodata (unless ``allow_gaps``: then the updates over gaps are skipped and counted). Returns
    the number of track points over nodata."""
    from warptan.nav.flightplan import track_problem
    from warptan.nav.geoframe import latlon_extent

    tracks = [("initial.pos_n", np.array([log.imu_t[0]]), log.init_pos[None]),
              ("truth.pos_n", log.truth_t, log.truth_pos) if log.has_truth else ("INS-only track", None, ins_pos)]
    source = f"flight log {log.name}"
    geo = bool(getattr(terrain, "crs_wkt", None))
    for name, t, pos in tracks:
        inside = terrain.contains(pos[:, 0], pos[:, 1])
        if not inside.all():
            i = int(np.argmax(~inside))
            when = f" at t = {t[i]:.2f} s" if t is not None else f" (epoch {i})"
            n0, n1, e0, e1 = terrain.bounds_ne
            if geo:
                box = np.array([[n0, e0], [n0, e1], [n1, e0], [n1, e1]])
                flight = np.vstack([p[:, :2] for _, _, p in tracks])
                raise LogError(source, [f"the DEM {terrain.name} does not contain the flight: the flight ("
                                        f"{latlon_extent(terrain, flight)}) against the DEM ("
                                        f"{latlon_extent(terrain, box)}); {name} leaves it first{when}"])
            raise LogError(source, [f"{name} leaves the DEM {terrain.name}{when}: north {pos[i, 0]:.1f} m, east "
                                    f"{pos[i, 1]:.1f} m (DEM north {n0:.0f} … {n1:.0f}, east {e0:.0f} … {e1:.0f} m)"])
    pos = tracks[1][2]
    over = int(np.isnan(terrain.height_at(pos[:, 0], pos[:, 1])).sum())
    if over and not allow_gaps:
        raise LogError(source, [f"{track_problem(terrain, pos[:, :2], 0.0, f'DEM {terrain.name}')}; --allow-gaps "
                                "(replay(..., allow_gaps=True)) flies through them: the updates over gaps are skipped "
                                "and counted"])
    return over


def own_terrain(log: FlightLog, terrain) -> bool:
    """``terrain`` (None, a name, path, spec or Terrain) is the DEM the log names."""
    if terrain is None:
        return True
    name = getattr(terrain, "name", None) or str(terrain)
    return name in {log.settings.get("terrain_spec"), log.dem_reference} - {None, ""}


def place_log(log: FlightLog, terrain, own: bool) -> tuple[FlightLog, dict]:
    """``log`` in the frame of ``terrain`` (its own DEM when ``own``): a geodetic frame is converted into the DEM's
    (:func:`convert_log`); a DEM-grid frame (version 1, or kind dem-grid) is the DEM's own grid. Returns the placed
    log and what was done (for ``run.info``). A :class:`LogError` when the two cannot be related: a DEM without a
    CRS under a geodetic frame (unless it is the log's own), another DEM under a dem-grid frame of version 2."""
    import warnings

    source = f"flight log {log.name}"
    if log.frame is None:
        if own:
            return log, {"frame": "dem-grid"}
        if log.version >= 2:
            raise LogError(source, [f"its frame is the grid of the DEM {log.dem_reference!r} (frame kind dem-grid, "
                                    f"no position on the Earth): it cannot be placed on {terrain.name}; replay it over "
                                    f"its own DEM {log.dem_reference!r} (leave out --terrain)"])
        warnings.warn(f"{source}: a version 1 log's frame is the grid of its DEM {log.dem_reference!r}; replayed over "
                      f"{terrain.name} as if that grid were this DEM's (write the log again as version 2 to tie it to "
                      "the Earth)", UserWarning, stacklevel=3)
        return log, {"frame": "dem-grid (version 1, over another DEM)"}
    if not getattr(terrain, "crs_wkt", None):
        if own:
            return log, {"frame": "geodetic, own DEM without CRS"}
        raise LogError(source, [f"the DEM {terrain.name} has no CRS: it cannot be related to the log's frame (origin "
                                f"lat {log.frame.origin_lat_deg:.6f}°, lon {log.frame.origin_lon_deg:.6f}°); give a "
                                "georeferenced DEM"])
    box = corners(log.truth_pos if log.has_truth else log.init_pos[None])
    change = frame_change(log.frame, terrain, box, dz=log.frame.origin_height_m)
    info = {"frame": "geodetic", "frame_identity": change.identity,
            "frame_turn_deg": float(np.degrees(change.angles(box)[0][-1])),  # at the box's centre
            "frame_scale_ppm": change.scale_ppm(box)}
    return convert_log(log, change, frame=log.frame), info


def replay_terrain(log: FlightLog, scenario: Scenario, terrain=None):
    """The DEM of a replay: ``terrain`` (Terrain, name, path or spec), else the one the log names. Another DEM file
    that must be resampled anyway (geographic, say) is resampled onto the log's DEM posts when the log records them
    and the file's own spacing is theirs (:attr:`~warptan.io.flightlog.FlightLog.dem_posts`,
    :func:`warptan.terrain.raster.read_raster`): another cut of the log's DEM is then the same map
    (:func:`same_posts`)."""
    from warptan.sim.scenarios import resolve_terrain

    spec = terrain if terrain is not None else (log.settings.get("terrain_spec") or log.dem_reference or None)
    if spec is None:
        raise LogError(f"flight log {log.name}", ["no DEM: the log names none (dem.reference); give --terrain"])
    recorded = log.settings.get("dem_sha256")
    if terrain is None and recorded:  # the file the log names must be the one it was recorded over
        from warptan.io.export import file_sha256
        from warptan.terrain.grid import terrain_source_file

        file = terrain_source_file(spec)
        if file is None:
            raise LogError(f"flight log {log.name}", [f"its DEM {spec} is not there; give --terrain"])
        if file_sha256(file) != recorded:
            raise LogError(f"flight log {log.name}", [f"the DEM file {file} it names is not the one it was recorded "
                                                      "over (its SHA-256 differs); give the right one with --terrain"])
    posts = None
    if log.dem_posts is not None and log.frame is not None and not own_terrain(log, terrain):
        posts = (log.frame.crs_wkt, (0.0, 0.0), tuple(float(v) for v in log.dem_posts))
    return resolve_terrain(scenario, spec, posts=posts)


def same_posts(log: FlightLog, terrain) -> bool:
    """``terrain``'s posts are among the log's DEM posts (:attr:`~warptan.io.flightlog.FlightLog.dem_posts`), in the
    log's frame: another cut of the same grid, whose heights are the log's DEM's (the map it was flown over)."""
    if log.dem_posts is None or log.frame is None or not getattr(terrain, "crs_wkt", None):
        return False
    n0, e0, dn, de = (float(v) for v in log.dem_posts[:4])
    if not (math.isclose(terrain.dn, dn, rel_tol=1e-12) and math.isclose(terrain.de, de, rel_tol=1e-12)):
        return False
    k = np.array([(terrain.n0 - n0) / dn, (terrain.e0 - e0) / de])
    if np.abs(k - np.round(k)).max() > 1e-6:
        return False
    probe = np.array([[terrain.n0, terrain.e0, 0.0], [terrain.n0 + 1e4, terrain.e0 + 1e4, 0.0]])
    return frame_change(log.frame, terrain, probe).identity


def replay(log: FlightLog, terrain=None, *, model: str | None = None, backend: str | None = None,
           particles: int | None = None, likelihood: str | None = None, seed: int | None = None, device="auto",
           progress=None, allow_gaps: bool = False, map_error: tuple[float, float] | None = None,
           map_error_learn: bool | str | None = None, map_error_confidence: float | None = None):
    """Filter a recorded flight; returns a :class:`~warptan.sim.scenarios.ScenarioResult` (errors NaN without truth).

    Args:
        log: The flight (validated).
        terrain: The DEM (Terrain, name, path or spec); default the log's ``dem.reference``.
        model, backend, particles, likelihood: Override the log's settings (default: the settings of the run that
            wrote the log, else S8's with the log's sensors).
        seed: The filter's seed (default the log's, else 0).
        device: Warp device (default ``"auto"``: a CUDA GPU when Warp sees one, else the CPU).
        progress: Optional callable(k, n) per update.
        allow_gaps: Fly through nodata under the track (its updates are skipped and counted) instead of refusing.
        map_error: The DEM's stated accuracy, ``(RMS, correlation length)`` of its correlated vertical error in m (a
            published figure: SRTM, Copernicus, DTED; :meth:`~warptan.sensing.likelihood.Likelihood.error_modes`);
            default the log's settings, else none.
        map_error_learn: Learn the error's RMS in flight, the statement (or the default) its prior: ``"auto"`` (the
            default) unless the log was simulated over this DEM as its world, True or False.
        map_error_confidence: The factor (1–10) the stated (or default) RMS is right within (default the log's,
            else 2; :attr:`~warptan.sensing.likelihood.Likelihood.map_error_confidence`).

    The log is placed in the DEM's frame first (:func:`place_log`: a geodetic frame converted, any DEM that covers
    the flight); a DEM that does not contain the flight, nodata under the track, or a frame the DEM cannot be
    related to is a :class:`~warptan.io.flightlog.LogError` before any filtering.
    """
    from warptan.sim.scenarios import ScenarioResult, map_terrain, scenario_model

    log.validate(f"flight log {log.name}")
    device = auto_device(device)
    scenario = replay_config(log, model, backend, particles, likelihood, map_error, map_error_learn,
                             map_error_confidence)
    check_replay_memory(log, scenario, device)
    truth_terrain = replay_terrain(log, scenario, terrain)
    own = own_terrain(log, terrain)
    log, placed = place_log(log, truth_terrain, own)
    if not own:
        placed["same_posts"] = same_posts(log, truth_terrain)
    filter_seed = check_seed(log.settings.get("seed", 0) if seed is None else seed)
    the_map = map_terrain(truth_terrain, scenario, filter_seed) if "config" in log.settings else truth_terrain
    s = scenario.sensor
    altimeter = s.model == "altimeter"
    times = log.alt_t if altimeter else log.scan_t
    sample, dts, ends, used = timeline(log, times)
    if not used.any():
        stream = "altimeter reading" if altimeter else "scan"
        raise LogError(f"flight log {log.name}", [
            f"none of its {len(times)} {stream}(s) (t = {times[0]:.3f} … {times[-1]:.3f} s) lies within the IMU's "
            f"time span (t = {log.imu_t[0]:.3f} … {log.t_end:.3f} s): nothing to navigate with"])
    nominal0 = NavState(log.init_pos, log.init_vel, log.init_quat, log.init_accel_bias, log.init_gyro_bias)
    ins = Ins(nominal0, log.imu_rate_hz).run(log.imu_f[sample], log.imu_w[sample], dt=dts)["pos_n"]
    ins_at = ins[np.r_[0, ends]]
    over_gaps = check_coverage(log, truth_terrain, ins_at, allow_gaps)
    lik = _likelihood(log, scenario, the_map, own or placed.get("same_posts", False))
    mpf_model = scenario_model(scenario, the_map, lik)
    sig = log.init_sigma
    mpf = MarginalizedParticleFilter(mpf_model, nominal0, imu_grade(log.imu_grade), log.imu_rate_hz, sig[0:3],
                                     np.diag(sig[3:15] ** 2), scenario.filter.config(), device=device, seed=filter_seed)
    idx = np.flatnonzero(used)
    t_used = times[used]
    measurements = _measurements(log, s.model, idx)
    prior = mpf.estimate()
    received, update_time, predict_time = [], [], 0.0
    t_start = time.perf_counter()
    start = 0
    for n, (meas, end) in enumerate(zip(measurements, ends, strict=True)):
        t0 = time.perf_counter()
        if end > start:
            mpf.predict_many(log.imu_f[sample[start:end]], log.imu_w[sample[start:end]], dt=dts[start:end])
        start = end
        predict_time += time.perf_counter() - t0
        t0 = time.perf_counter()
        mpf.update(meas, sync=False)
        update_time.append(time.perf_counter() - t0)
        received.append(mpf.last_n_received)
        if progress is not None:
            progress(n + 1, len(idx))
    edges = np.r_[log.imu_t, log.t_end]
    epoch_t = np.r_[edges[0], np.minimum(np.maximum(t_used, edges[0]), edges[-1])]
    truth = bias = None
    if log.has_truth:
        truth = {"pos": sample_at(log.truth_t, log.truth_pos, epoch_t),
                 "vel": sample_at(log.truth_t, log.truth_vel, epoch_t),
                 "quat": sample_at(log.truth_t, log.truth_quat, epoch_t, unit=True)}
        if log.truth_accel_bias is not None and log.truth_gyro_bias is not None:
            bias = [sample_at(log.truth_t, np.hstack([log.truth_accel_bias, log.truth_gyro_bias]), epoch_t)]
    run = collect_runs(mpf, epoch_t, truth, bias, [ins_at], prior, received, update_time, predict_time, False,
                       {"imu_steps": len(sample), "meas_rate_hz": s.rate_hz,
                        "dropped_measurements": int((~used).sum()), "log": log.name, **placed,
                        **({"gaps_allowed": True, "track_points_over_nodata": over_gaps} if allow_gaps else {})})
    wall = time.perf_counter() - t_start
    return ScenarioResult(scenario=scenario.id, seed=int(log.settings.get("scenario_seed", filter_seed)),
                          device=run.device, terrain=truth_terrain.name, config=scenario, run=run, wall_s=wall,
                          truth_terrain=truth_terrain, map=the_map.name, map_sigma_m=lik.map_sigma_m)


# ---------------------------------------------------------------------- trajectory file
