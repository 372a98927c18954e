"""Scenarios S1–S12 (paper §V, design notes §7): the world, the map and the flight a configuration describes, and
``run_scenario`` (the files, their schema and validation: :mod:`warptan.sim.scenario_config`).

A scenario file states every parameter (see ``warptan/scenario_files/S1.toml``); a file is validated as a
whole before anything runs, and every problem is listed at once (missing or misspelt keys, wrong types,
values out of range, a terrain that does not load, a flight that leaves the DEM). This module assembles: the map
and the world are built by the terrain layer (:mod:`warptan.terrain.maps`), the flight by the navigation layer
(:mod:`warptan.nav.flightplan`), each from its own table of the typed
:class:`~warptan.sim.scenario_config.Scenario`.

Choices the paper leaves open (design notes §7 fixes the rest):

* ``rugged`` / ``flat`` / ``rugged30`` terrains are the real DEMs shipped with the package
  (:data:`~warptan.terrain.grid.NAMED_TERRAINS`, ``warptan/data/dem``; ``$WARPTAN_DEM_DIR`` may replace them); any
  scenario flies another terrain with ``terrain=`` (a name, a DEM file, ``synthetic:rugged``): S1–S9 on the 30 m
  tile are ``terrain="rugged30"``. The result names the terrain it flew (``ScenarioResult.terrain``) and the
  map the filter read (``map``).
* The world is the truth terrain; the filter's map is the world unless ``[terrain]`` says otherwise
  (:func:`map_terrain`): another DEM file of the same ground (``map_path``, resampled into the world's frame), a
  coarser grid (``map_spacing_m``, block means), white post noise (``map_noise_m``, realisation ``map_seed``) and a
  vertical bias (``map_bias_m``), in that order. With ``likelihood.map_aware`` the per-point σ counts the map's
  own interpolation error (:meth:`~warptan.terrain.grid.Terrain.interpolation_sigma_m`) whenever the map's grid is not
  the world's.
* Flight patterns: ``straight`` (bank 0); ``s_turns`` (banked scenarios S1–S4: 10 s straight, then turns of
  ±150° alternating at the bank angle until the end); ``orbit`` (S5/S6: 5 s straight, then circling at
  the bank angle, placed so that the circle passes ``hill_offset_m`` beside the highest hill with the
  hill outside the circle, so the banked sensor looks away from it, into open ground).
* Altitude: ``high`` = 600 m above the highest terrain within 2 km of the track; ``low`` = 150 m within
  1 km (design notes §7); constant along the track.
* The track must stay ``margin_m`` inside the DEM (the footprint of the scan and the initial error).
* S4 has S1's parameters (the paper lists them identically); it differs only by its seed base.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field

import numpy as np

from warptan.device import auto_device
from warptan.nav.flightplan import FlightPlanError, track_problem
from warptan.nav.imu import ImuModel
from warptan.nav.trajectory import Trajectory
from warptan.sensing.likelihood import Likelihood
from warptan.sensing.measurement import make_model
from warptan.sensing.sensors import Barometer, PointCloudSensor, RadarAltimeter, ScanPattern
from warptan.sim.runner import FilterRun, run_filter
from warptan.sim.scenario_config import Scenario, ScenarioError, check_memory, check_seeds, load_config
from warptan.terrain.grid import NAMED_TERRAINS, Terrain, TerrainError
from warptan.terrain.maps import build_world, load_terrain
from warptan.terrain.world import World


# ---------------------------------------------------------------------- world, map, flight
def resolve_terrain(scenario: Scenario, terrain=None, posts=None) -> Terrain:
    """The DEM of the world: an override (Terrain, name, path or spec), else the scenario's (``terrain.kind``, a
    named real DEM, or ``terrain.path``); ``posts`` go to a raster's load
    (:meth:`~warptan.terrain.grid.Terrain.from_raster`)."""
    if isinstance(terrain, Terrain):
        return terrain
    if terrain is not None and not isinstance(terrain, (str, os.PathLike)):
        raise ScenarioError(f"terrain={terrain!r} ({type(terrain).__name__}) must be a Terrain, a name "
                            f"({', '.join(NAMED_TERRAINS)}), a DEM path or a 'synthetic:KIND' spec")
    try:
        return load_terrain(scenario.terrain.dem if terrain is None else terrain, posts=posts)
    except TerrainError as err:
        raise ScenarioError(str(err)) from None


def world_terrain(dem: Terrain, scenario: Scenario, seed: int) -> Terrain:
    """The world a scenario flies: ``dem`` itself, or with an active ``[world]`` table the
    :class:`~warptan.terrain.world.World` made from it (:func:`~warptan.terrain.maps.build_world`; ``seed``: the
    run's, used when ``world.seed`` is -1)."""
    try:
        return build_world(dem, scenario.world, seed)
    except TerrainError as err:
        raise ScenarioError(f"scenario {scenario.id}: {err}") from None


def map_terrain(truth: Terrain, scenario: Scenario, seed: int) -> Terrain:
    """The filter's map of the world ``truth`` (:meth:`~warptan.terrain.maps.MapSpec.build`)."""
    try:
        return scenario.terrain.build(truth, seed)
    except TerrainError as err:
        raise ScenarioError(str(err)) from None


def build_flight(scenario: Scenario, terrain: Terrain) -> Trajectory:
    """The truth trajectory of a scenario over ``terrain`` (:meth:`~warptan.nav.flightplan.FlightPlan.fly`).

    Raises:
        ScenarioError: the track does not fit ``margin_m`` inside the DEM or passes over nodata.
    """
    try:
        return scenario.flight.fly(terrain, scenario.imu.rate_hz)
    except FlightPlanError as err:
        raise ScenarioError(f"scenario {scenario.id}: {err}") from None


# ---------------------------------------------------------------------- running
@dataclass
class ScenarioResult:
    """One run of one scenario with one seed."""

    scenario: str
    seed: int
    device: str
    terrain: str
    config: Scenario
    """The scenario as it ran (overrides applied)."""
    run: FilterRun
    wall_s: float
    truth_terrain: Terrain = field(repr=False)
    map: str = ""
    """The terrain the filter read (its name; equal to ``terrain`` when the map is the world)."""
    map_sigma_m: float = 0.0
    """The map σ of the likelihood, m (stated noise, with the map's interpolation error when map-aware)."""
    pcrb_sigma_m: np.ndarray | None = field(default=None, repr=False)
    """(T, 3) σ north, east, down of the posterior Cramér–Rao bound at the epochs (:mod:`warptan.filter.bound`; a
    simulated flight's, None for a recorded one), m."""
    floor_sigma_m: np.ndarray | None = field(default=None, repr=False)
    """(T, 3) σ north, east, down of the exact floor (:func:`warptan.filter.floor.exact_pcrb`: the map's error field
    in the state) at the epochs, m; None unless asked for (``bound="exact"``)."""
    rmse: np.ndarray = field(init=False)
    """(3,) RMSE north, east, down over the whole run, m."""
    rmse_converged: np.ndarray = field(init=False)
    """(3,) RMSE after ``filter.converged_after_s``, m."""

    def __post_init__(self):
        self.rmse = self.run.rmse(0.0)
        self.rmse_converged = self.run.rmse(self.config.filter.converged_after_s)

    @property
    def pcrb_m(self) -> np.ndarray | None:
        """(T,) the bound's horizontal DRMS ``sqrt(σ_n² + σ_e²)`` at the epochs, m (None without a bound)."""
        return None if self.pcrb_sigma_m is None else np.hypot(self.pcrb_sigma_m[:, 0], self.pcrb_sigma_m[:, 1])

    def _converged_drms(self, sigmas: np.ndarray | None) -> float:
        """The horizontal DRMS of a bound's (T, 3) σ, RMS over the epochs after ``filter.converged_after_s`` (as the
        RMSE is taken), m; NaN without the bound or such epochs."""
        sel = self.run.t_s >= self.config.filter.converged_after_s
        if sigmas is None or not sel.any():
            return math.nan
        return float(np.sqrt(np.mean(np.sum(sigmas[sel, :2] ** 2, axis=1))))

    @property
    def pcrb_converged_m(self) -> float:
        """The fast bound's (:attr:`pcrb_sigma_m`) horizontal DRMS after convergence (:meth:`_converged_drms`), m."""
        return self._converged_drms(self.pcrb_sigma_m)

    @property
    def floor_converged_m(self) -> float:
        """The exact floor's (:attr:`floor_sigma_m`) horizontal DRMS after convergence (:meth:`_converged_drms`), m."""
        return self._converged_drms(self.floor_sigma_m)

    def summary(self) -> dict:
        """JSON-ready numbers of this run."""
        from warptan.sim.report import declared_unconverged, update_counts

        r = self.run
        updates, skipped, used = update_counts(r)
        bound = self.pcrb_m
        return {
            "pcrb_m": None if bound is None else bound.tolist(), "pcrb_converged_m": self.pcrb_converged_m,
            "rmse_horizontal_converged_m": float(np.hypot(*self.rmse_converged[:2])),
            "scenario": self.scenario, "seed": self.seed, "device": self.device, "terrain": self.terrain,
            "map": self.map or self.terrain, "map_sigma_m": self.map_sigma_m,
            "world": ({"model": dataclasses.asdict(self.truth_terrain.model), **self.truth_terrain.parts}
                      if isinstance(self.truth_terrain, World) else None),
            "rmse_m": self.rmse.tolist(), "rmse_converged_m": self.rmse_converged.tolist(),
            "ins_only_final_error_m": (r.ins_pos[-1] - r.truth_pos[-1]).tolist(),
            "coverage_3sigma": r.coverage(self.config.filter.converged_after_s).tolist(),
            "min_ess": float(r.ess[1:].min()) if len(r.ess) > 1 else float(r.ess[0]),
            "resamplings": int(r.resampled.sum()), "respreads": int(r.respread.sum()),
            "declared_unconverged": declared_unconverged(r, self.config.filter.converged_after_s),
            "updates": updates, "skipped_updates": skipped, "updates_used": used,
            "updates_without_points": updates - skipped - used,
            "max_tempering_stages": int(r.stages.max()),
            "integrity_max": float(np.nanmax(r.nis_avg)) if len(r.nis_avg) > 1 else 0.0,
            "unpredictable_particle_updates": int(r.n_unpredictable.sum()),
            "update_ms_median": 1e3 * float(np.median(r.update_time_s[1:])) if len(r.update_time_s) > 1 else 0.0,
            "predict_s_total": r.predict_time_s, "wall_s": self.wall_s,
            **self.linear_summary(),
        }

    def linear_summary(self) -> dict:
        """Attitude and bias numbers of the run: converged RMSE and 3σ coverage of the attitude error (body
        axes, deg), gyro-bias RMSE after 60 s (deg/h), and the mean reported σ over the RMSE per axis for position
        and attitude (honest bounds: about 1)."""
        r, conv = self.run, self.config.filter.converged_after_s
        sel = r.t_s >= conv
        att_rmse = r.lin_rmse(conv)[3:6]
        pos_sigma = np.mean(r.sigma3_pos[sel], axis=0) / 3.0 if sel.any() else np.full(3, np.nan)
        att_sigma = np.mean(r.sigma3_lin[sel, 3:6], axis=0) / 3.0 if sel.any() else np.full(3, np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            return {
                "attitude_rmse_converged_deg": np.degrees(att_rmse).tolist(),
                "coverage_3sigma_attitude": r.lin_coverage(conv)[3:6].tolist(),
                "gyro_bias_rmse_after_60s_dph": (np.degrees(r.lin_rmse(60.0)[9:12]) * 3600.0).tolist(),
                "sigma_over_rmse_pos": (pos_sigma / self.rmse_converged).tolist(),
                "sigma_over_rmse_attitude": (att_sigma / att_rmse).tolist(),
                "injections": int(r.info.get("injections", 0)),
                "map_error_learned_m": r.info.get("map_error_learned_m"),
                "map_error_learned_corr_m": r.info.get("map_error_learned_corr_m"),
                "map_white_learned_m": r.info.get("map_white_learned_m"),
            }


DEFAULT_MAP_ERROR = (5.0, 500.0)
"""The prior of a map error learned in flight when nothing is stated: RMS and correlation length, m. The RMS is
about SRTM's measured absolute error (5.6–9.0 m LE90 by continent, :mod:`warptan.terrain.world`) and Copernicus
GLO-30's < 4 m specification; the learner may take it to twice that (:class:`~warptan.sensing.learner.
MapErrorLearner`) or down to centimetres, and the length from a quarter to four times it. The length is on the short
side of the hundreds of metres to kilometres reported for these products: for a point cloud, stated or learned, a
longer correlation than the map's makes the filter overconfident (the scan's offset and tilt look shared, the rest
independent), a shorter one only costs accuracy. An altimeter has its own (:data:`DEFAULT_ALTIMETER_CORR_M`)."""
DEFAULT_ALTIMETER_CORR_M = 2000.0
"""The prior correlation length of a single range's map error when nothing is stated, m: the long side. One range
has no scan to structure the error over; what its one mode carries is the error's persistence along the track, and
a length shorter than the map's takes an error that persists for a position that moves (the reverse of a point
cloud). Measured before it was the default (S9, 20 seeds over 4 worlds, CPU, 5 m RMS stated at either length):
a 10 m / 3 km world with a 5 m bias 303 m mean horizontal RMSE with 3σ coverage 88/88 % at 500 m, 44 m at 99/93 %
at 2 km; a 5 m / 1 km world with relief 23.1 → 21.2 m (σ/RMSE 1.6/1.5 → 1.4/1.2); over a map that is the world,
learning, 252 → 9.6 m. ``results/learned`` has the rows with it as the default. The altimeter's learner rarely
reads (it seldom converges within its guard), so the prior is mostly what it flies with."""


def learned_statement(lk, map_is_world: bool, post_m: float, altimeter: bool = False) -> tuple[float, float, bool]:
    """``(RMS, correlation length, learn)`` of the map error the likelihood states, from a ``[likelihood]`` table
    ``lk``: learning on (``map_error_learn``: true, or ``"auto"`` unless the map is known to be the world and nothing
    is stated: a statement is always a prior, never a fixed truth), the statement, or without one
    :data:`DEFAULT_MAP_ERROR` (for an ``altimeter`` its length :data:`DEFAULT_ALTIMETER_CORR_M`; at least two posts,
    ``post_m``), is the prior; off, the statement as given (none: 0, 0)."""
    rms, corr, learn = float(lk.map_error_rms_m), float(lk.map_error_corr_m), lk.map_error_learn
    if rms > 0 and corr < post_m:
        raise ScenarioError(f"likelihood.map_error_corr_m = {corr:g} m is shorter than one post of the map "
                            f"({post_m:.4g} m): an error correlated over less than a post is noise per post (state the "
                            "map's σ with terrain.map_noise_m), or give a correlation length ≥ the post spacing")
    on = learn is True or (learn == "auto" and (not map_is_world or rms > 0))
    if on and lk.kind != "paper" and rms <= 0:
        rms = DEFAULT_MAP_ERROR[0]
        corr = max(DEFAULT_ALTIMETER_CORR_M if altimeter else DEFAULT_MAP_ERROR[1], 2.0 * post_m)
    return rms, corr, bool(on and rms > 0 and lk.kind != "paper")


def scenario_likelihood(scenario: Scenario, the_map: Terrain, truth: Terrain | None = None,
                        footprint_m: float | None = None) -> Likelihood:
    """The scenario's likelihood; ``sigma_m = "auto"`` calibrates σ from the sensor noise (range; altimeter ⊕
    barometer for the altimeter with a barometer), the map noise and the
    model's surface mismatch, with the map part inflated by the updates over which the scan reads the same DEM
    cells: ``n_corr = max(1, sqrt(dn de) / (speed / measurement rate))`` (7.4 on the 90 m tile at 100 m/s, 10 Hz);
    the attitude information's footprint correlation is the scan's along-track footprint at the flight's clearance
    over the same step (``2 · 600 m · tan 30° / 10 m`` = 69 for the high flights), the slant range of a banked
    orbit's scan lengthening it by ``1 / cos(bank)`` (S5/S6, 60° bank, world 1003 seeds 15–16 told 5 m / 1 km,
    CPU: attitude 3σ coverage about north 72 → 99 % and 22 → 32 %, the position unchanged).

    The map σ is the stated post noise ``map_noise_m``; with ``likelihood.map_aware`` and a map whose grid is not
    the world's (``truth`` given; another file or coarser posts) it is ``hypot(map_noise_m,
    the_map.interpolation_sigma_m(map_noise_m))``: the map's own bilinear error at its post spacing, estimated
    from its roughness (:meth:`~warptan.terrain.grid.Terrain.interpolation_sigma_m`; 30 m tile at 60/90/180 m posts:
    2.8/5.1/12.1 m estimated, 2.3/4.8/12.9 m measured against the 30 m triangles). A map on the world's own
    posts has no interpolation error beyond the bilinear-vs-triangles mismatch every sliding model counts.
    ``footprint_m`` replaces the scenario's footprint (a recorded flight's, measured from its scans).

    The map error is learned in flight (:func:`learned_statement`) unless the map is known to be the world (``truth``
    given and the map the world itself; a recorded flight, ``truth`` None, never knows) and no error is stated."""
    lk, s = scenario.likelihood, scenario.sensor
    noise_m = s.range_sigma_m
    if s.model == "altimeter":  # the residual a - (h_baro - h(p)) carries both sensors' noise
        noise_m = math.hypot(s.altimeter_sigma_m, s.baro_sigma_m if s.use_baro else 0.0)
    step_m = scenario.flight.speed_mps / s.rate_hz
    n_corr = max(1.0, math.sqrt(the_map.dn * the_map.de) / step_m)
    n_fp = n_corr
    if s.model != "altimeter":  # the scan's along-track footprint (default: at the flight's clearance)
        if footprint_m is None:
            footprint_m = scenario.flight.footprint_m(s.scan_half_angle_deg)
        n_fp = max(n_corr, footprint_m / step_m)
    map_sigma = scenario.terrain.map_noise_m
    if lk.map_aware and truth is not None and scenario.terrain.grid_differs(truth):
        map_sigma = math.hypot(map_sigma, the_map.interpolation_sigma_m(map_sigma))
    rms, corr, learn = learned_statement(lk, truth is the_map, max(the_map.dn, the_map.de), s.model == "altimeter")
    return Likelihood(lk.kind, r_err=lk.r_err_m2, sigma_m=None if lk.sigma_m == "auto" else lk.sigma_m,
                      nu=lk.nu, sensor_sigma_m=noise_m, map_sigma_m=map_sigma,
                      map_correlation=n_corr, footprint_correlation=n_fp,
                      map_error_sigma_m=rms, map_error_corr_m=corr, map_error_learn=learn,
                      map_error_confidence=lk.map_error_confidence, track_step_m=step_m,
                      **fix_geometry(the_map, rms, footprint_m if s.model != "altimeter" else None))


def fix_geometry(the_map: Terrain, rms: float, footprint_m: float | None) -> dict:
    """The likelihood's terms of the fix wander under a map error of RMS ``rms`` (none without one:
    :meth:`~warptan.sensing.likelihood.Likelihood.fix_process`): ``fix_corr_m``, the map's slope correlation length,
    and for a scan of ``footprint_m``, ``fix_slope`` (the map's RMS slope, at least
    :data:`~warptan.sensing.likelihood.MIN_FIX_SLOPE`) and ``fix_footprint_m``."""
    from warptan.sensing.likelihood import MIN_FIX_SLOPE

    if not rms > 0:
        return {"fix_corr_m": 0.0}
    terms = {"fix_corr_m": the_map.slope_correlation_m}
    if footprint_m:
        terms.update(fix_slope=max(the_map.slope_rms, MIN_FIX_SLOPE), fix_footprint_m=float(footprint_m))
    return terms


def prepare(name_or_path, seed: int = 0, terrain=None, *, seeds=None, device=None, batched: bool = False,
            **overrides):
    """Validate and build everything a run needs (the :class:`Scenario`, the world, the flight) without running
    it: the file and overrides, the seeds (``seeds``, default ``[seed]``; ``batched``: run as one batch, which a map
    with per-seed noise cannot be), the memory the run needs on ``device`` (when given), the terrain, the flight
    inside the DEM, and the filter's map. ``warptan run --check`` is this."""
    scenario = load_config(name_or_path, **overrides)
    base = scenario.run.seed
    seeds = check_seeds([seed] if seeds is None else seeds, base)
    if batched and len(seeds) > 1 and per_seed_maps(scenario):
        raise ScenarioError(f"{scenario.id}: map_noise_m with map_seed = -1, or a [world] with seed = -1, gives "
                            "every seed its own map or world; run the seeds one by one (without --batch), or fix "
                            "terrain.map_seed / world.seed")
    if device is not None:  # seeds one by one hold one seed's filter at a time, and every seed's result
        check_memory(scenario, len(seeds) if batched else 1, device, kept=0 if batched else len(seeds))
    truth_terrain = world_terrain(resolve_terrain(scenario, terrain), scenario, base + seeds[0])
    flight = build_flight(scenario, truth_terrain)
    the_map = map_terrain(truth_terrain, scenario, base + seeds[0])
    learned_statement(scenario.likelihood, the_map is truth_terrain, max(the_map.dn, the_map.de))  # checks it
    if the_map is not truth_terrain:  # the map must cover the flight as the world must
        problem = track_problem(the_map, flight.pos_n[:, :2], scenario.flight.margin_m, f"map {the_map.name}")
        if problem:
            raise ScenarioError(f"scenario {scenario.id}: the filter's map does not cover the flight: {problem}; "
                                "give a map of the same ground (terrain.map_path / --map)")
    return scenario, truth_terrain, flight


def per_seed_maps(scenario: Scenario) -> bool:
    """The filter's map has noise drawn per seed (``map_noise_m`` with ``map_seed = -1``): every seed reads its own
    map, so the seeds cannot share one batched filter."""
    return scenario.terrain.per_seed or scenario.world.per_seed


def run_scenario(name_or_path, seed: int = 0, device="auto", progress=None, export_logs=None, bound: bool | str = True,
                 **overrides) -> ScenarioResult:
    """Run one scenario with one seed.

    Args:
        name_or_path: "S1"…"S12" or a TOML path.
        seed: Seed (added to the file's ``run.seed``): initial error, IMU errors, sensor noise, filter.
        device: Warp device of the filter.
        progress: Optional callable(k, n) per measurement epoch.
        **overrides: ``terrain=`` (path, spec or Terrain), ``particles=``, ``duration_s=``, ``backend=``,
            ``likelihood=``, ``model=``, ``meas_rate_hz=``, ``paper_rates=True``, ``use_baro=``, ``r_err_m2=``,
            ``sigma_m=``, ``imu_grade=``.
        export_logs: A list to append the run's :class:`~warptan.io.flightlog.FlightLog` to (see
            :func:`run_scenario_batch`).
        bound: Compute the flight's posterior Cramér–Rao bound (``pcrb_sigma_m``; False: None, which saves its
            host work, about a third of a CPU run of S8 over a world; ``"exact"``: also the exact floor with the
            map's error field in the state, ``floor_sigma_m``, :func:`warptan.filter.floor.exact_pcrb`, seconds to
            minutes more).
    """
    return run_scenario_batch(name_or_path, [seed], device, progress, export_logs, bound=bound, **overrides)[0]


def scenario_model(scenario: Scenario, the_map: Terrain, likelihood: Likelihood):
    """The scenario's measurement model on ``the_map``."""
    s = scenario.sensor
    model_kwargs = {"use_baro": s.use_baro, "baro_sigma_m": max(s.baro_sigma_m, 0.1)} if s.model == "altimeter" \
        else {}
    if s.model != "raycast":
        model_kwargs["surface"] = s.surface == "triangles"
    return make_model(s.model, the_map, likelihood, backend=s.backend, **model_kwargs)


def terrain_spec(scenario: Scenario, terrain=None) -> str:
    """The spec :func:`resolve_terrain` loads the world from (a name, path or ``synthetic:`` spec; a Terrain object
    given directly: its name)."""
    if isinstance(terrain, Terrain):
        return terrain.name
    if terrain is not None:
        return os.fspath(terrain)
    return scenario.terrain.dem


def run_scenario_batch(name_or_path, seeds, device="auto", progress=None, export_logs=None, bound: bool | str = True,
                       **overrides) -> list[ScenarioResult]:
    """Run one scenario with several seeds as one batched filter (every run's particles in one array, one
    launch per kernel for all of them); each result is the same as :func:`run_scenario` with that seed on the
    same device, except under a stated map error (``likelihood.map_error_rms_m``), whose map-error mode table is the
    batch's, built from its first filter's scan geometry: there a batched seed differs from the seed alone by the
    filter's noise (S8, world 1003, seeds 15–16, 15 s: up to 1.1 m). A scenario whose map has per-seed error cannot
    be batched (its runs use different maps).
    ``export_logs``: a list to which each seed's flight is appended as a :class:`~warptan.io.flightlog.FlightLog`
    (what the filter received, truth, prior and settings: ``warptan replay`` of it gives the same run).
    ``bound``: as :func:`run_scenario`'s."""
    import time

    terrain = overrides.pop("terrain", None)
    seeds = list(seeds)
    device = auto_device(device)
    scenario, truth_terrain, flight = prepare(name_or_path, terrain=terrain, seeds=seeds, device=device, batched=True,
                                            **overrides)
    seeds = [int(seed) for seed in seeds]  # checked by prepare
    s = scenario.sensor
    total_seeds = [int(scenario.run.seed) + seed for seed in seeds]
    the_map = map_terrain(truth_terrain, scenario, total_seeds[0])  # a World's map: the DEM it was made from
    likelihood = scenario_likelihood(scenario, the_map, truth_terrain)
    model = scenario_model(scenario, the_map, likelihood)
    if s.model == "altimeter":
        sensor = RadarAltimeter(s.altimeter_sigma_m)
    else:
        sensor = PointCloudSensor(ScanPattern.grid(s.scan_nx, s.scan_ny, s.scan_half_angle_deg),
                                  range_sigma_m=s.range_sigma_m)
    imus = [ImuModel(scenario.imu.grade, scenario.imu.rate_hz, seed=ts) for ts in total_seeds]
    record = {} if export_logs is not None else None
    t0 = time.perf_counter()
    runs = run_filter(
        flight, the_map, model, imus, sensor, terrain_truth=truth_terrain, baro=Barometer(s.baro_sigma_m),
        config=scenario.filter.config(), device=device, seed=total_seeds, meas_rate_hz=s.rate_hz,
        initial=scenario.initial_error.errors(), progress=progress,
        record=record)
    wall = time.perf_counter() - t0
    if export_logs is not None:
        from warptan.io.export import logs_from_record

        export_logs.extend(logs_from_record(record, flight, scenario.to_dict(), likelihood, total_seeds, seeds,
                                            terrain_spec(scenario, terrain), truth_terrain))
    floor = scenario_bound(scenario, flight, the_map, runs[0].t_s, exact=True) if bound == "exact" else None
    bound = scenario_bound(scenario, flight, the_map, runs[0].t_s) if bound else None
    return [ScenarioResult(scenario=scenario.id, seed=seed, device=run.device, terrain=truth_terrain.name,
                           config=scenario, run=run, wall_s=wall, truth_terrain=truth_terrain, map=the_map.name,
                           map_sigma_m=likelihood.map_sigma_m, pcrb_sigma_m=bound, floor_sigma_m=floor)
            for seed, run in zip(seeds, runs, strict=True)]


def scenario_scan(scenario: Scenario) -> dict:
    """The scenario's sensor as the information map and the bound read it: ``dirs_body`` (the scan's ray directions;
    None: the altimeter), ``sigma_m`` (its noise), ``baro_sigma_m`` (the barometer's; None without one or for a
    point cloud), ``surface`` (the map's triangulated surface) and ``step_m`` (the scans' spacing along the track)."""
    s = scenario.sensor
    altimeter = s.model == "altimeter"
    return {"dirs_body": None if altimeter else ScanPattern.grid(s.scan_nx, s.scan_ny, s.scan_half_angle_deg).dirs_s,
            "sigma_m": s.altimeter_sigma_m if altimeter else s.range_sigma_m,
            "baro_sigma_m": s.baro_sigma_m if altimeter and s.use_baro else None,
            "surface": s.model == "raycast" or s.surface == "triangles",
            "step_m": scenario.flight.speed_mps / s.rate_hz}


def scenario_bound(scenario: Scenario, flight: Trajectory, the_map: Terrain, t_s: np.ndarray,
                   exact: bool = False) -> np.ndarray | None:
    """(T, 3) σ north, east, down of the flight's posterior Cramér–Rao bound at the epochs ``t_s`` (:func:`warptan.
    filter.bound.pcrb`): the scenario's sensor (its noise alone: the bound's truth), the filter's map, the map's error
    as it is (a simulated world's correlated error when it has one; else the stated one), the IMU grade and the
    filter's prior; None for a world the bound cannot hold (relief the map lacks, clutter: the bound models a
    correlated Gaussian error and noise only; a table showed such a run's 3.3 m RMSE beside a 0.34 m "bound" of a
    map taken for exact). ``exact``: the exact floor instead (:func:`warptan.filter.floor.exact_pcrb`: the world's
    error field and bias in the state; the fast bound's per-scan κ rule is an approximation of it)."""
    from warptan.filter.bound import pcrb
    from warptan.filter.floor import exact_pcrb
    from warptan.filter.prior import prior_sigma
    from warptan.nav.imu import imu_grade

    lk, scan, w = scenario.likelihood, scenario_scan(scenario), scenario.world
    error_rms, error_corr = lk.map_error_rms_m, lk.map_error_corr_m
    if w.active:
        if w.relief_rms_m != 0.0 or (w.clutter_height_m > 0 and w.clutter_fraction > 0):
            return None
        error_rms, error_corr = (w.error_rms_m, w.error_corr_m) if w.error_rms_m > 0 else (0.0, 0.0)
    grade = imu_grade(scenario.imu.grade)
    epochs = np.rint(np.asarray(t_s[1:]) * flight.rate_hz).astype(np.int64)
    p0 = np.diag(prior_sigma(scenario.initial_error.errors(), grade) ** 2)
    kw = {"dirs_body": scan["dirs_body"], "sigma_m": scan["sigma_m"], "baro_sigma_m": scan["baro_sigma_m"],
          "map_error_rms_m": error_rms, "map_error_corr_m": error_corr, "surface": scan["surface"]}
    if exact:
        sigmas = exact_pcrb(flight, the_map, epochs, grade, p0, map_bias_m=abs(w.bias_m) if w.active else 0.0, **kw)
    else:
        sigmas = pcrb(flight, the_map, epochs, grade, p0, **kw)
    return sigmas[:, :3]
