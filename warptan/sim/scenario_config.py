"""A scenario, typed: :class:`Scenario` (parsed once from its TOML file by :func:`load_config`, every problem of the
file and its overrides listed at once; its tables are the dataclasses of the layers that use them:
:class:`~warptan.terrain.maps.MapSpec`, :class:`~warptan.nav.flightplan.FlightPlan`,
:class:`~warptan.terrain.world.WorldModel`, and the sensing / filter tables here), the seeds and the memory a run
needs. The schema and validation are :mod:`warptan.sim.scenario_schema`; :mod:`warptan.sim.scenarios` assembles
and runs what a scenario describes."""

from __future__ import annotations

import collections
import dataclasses
import difflib
import os
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from warptan.checks import check_seed, host_memory_available
from warptan.filter.config import FilterConfig
from warptan.filter.prior import InitialErrors
from warptan.nav.flightplan import FlightPlan
from warptan.sim.scenario_schema import (  # noqa: F401  (the scenario's public names, one import away)
    MAX_SEED,
    MAX_SPEED_MPS,
    MEMORY_FRACTION,
    OVERRIDES,
    RUN_KEYWORDS,
    SCENARIO_IDS,
    SCHEMA,
    SURFACES,
    TERRAIN_KINDS,
    ScenarioError,
    validate,
    with_optional_defaults,
)
from warptan.terrain.maps import MapSpec
from warptan.terrain.world import WorldModel

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib


@dataclass(frozen=True)
class ImuSpec:
    """A scenario's ``[imu]`` table."""

    grade: str
    """The IMU's grade (:data:`~warptan.nav.imu.IMU_GRADES`)."""
    rate_hz: float
    """IMU sample rate, Hz."""


@dataclass(frozen=True)
class SensorSpec:
    """A scenario's ``[sensor]`` table."""

    model: str
    """Measurement model: ``raycast``, ``sliding`` or ``altimeter``."""
    backend: str
    """Ray-cast backend of the ``raycast`` model (:data:`~warptan.terrain.raycast.BACKENDS`)."""
    surface: str
    """What the ``sliding`` and ``altimeter`` models read from the map: ``triangles`` or ``bilinear``."""
    rate_hz: float
    """Measurement rate, Hz (divides the IMU rate)."""
    scan_nx: int
    """Rays of the scan across the track."""
    scan_ny: int
    """Rays of the scan along the track."""
    scan_half_angle_deg: float
    """Half the scan's opening angle, degrees."""
    range_sigma_m: float
    """Range noise of the point cloud, m (σ)."""
    altimeter_sigma_m: float
    """Radar-altimeter noise, m (σ)."""
    baro_sigma_m: float
    """Barometer noise, m (σ)."""
    use_baro: bool
    """The altimeter model uses the barometer (its residual then does not depend on a particle's altitude)."""


@dataclass(frozen=True)
class LikelihoodSpec:
    """A scenario's ``[likelihood]`` table."""

    kind: str
    """The likelihood (:data:`~warptan.sensing.likelihood.LIKELIHOODS`)."""
    r_err_m2: float
    """The paper's error variance, m²."""
    sigma_m: float | str
    """Per-point σ, m, or ``"auto"`` (sensor ⊕ map, calibrated)."""
    nu: float
    """Student-t degrees of freedom."""
    map_aware: bool
    """σ counts the map's own interpolation error when its grid is not the world's."""
    map_error_rms_m: float
    """The DEM's stated correlated error, RMS, m (0: none)."""
    map_error_corr_m: float
    """Its correlation length, m."""
    map_error_learn: bool | str = "auto"
    """Learn the error's RMS in flight, the statement (or :data:`~warptan.sim.scenarios.DEFAULT_MAP_ERROR`) its prior:
    ``"auto"`` whenever the map is not known to be the world (a ``[world]``, another map, a replay), or true / false."""
    map_error_confidence: float = 2.0
    """The factor (1–10) the statement's RMS is right within, when it is a prior: the learner's ceiling and the
    reported altitude σ's share of the map's offset (:attr:`warptan.sensing.likelihood.Likelihood.
    map_error_confidence`)."""


@dataclass(frozen=True)
class FilterSpec:
    """A scenario's ``[filter]`` table: the filter's settings (:meth:`config`) and when the run counts as
    converged."""

    particles: int
    """Particles per filter."""
    resample_threshold: float
    """Resample when ESS < this · N."""
    resampler: str
    """Resampling scheme (:data:`~warptan.filter.config.RESAMPLERS`)."""
    pos_noise_m_rthz: float
    """Particle position noise, m/√s."""
    kalman_pos_noise_m_rthz: float
    """Position noise the Kalman part models, m/√s."""
    regularize: float
    """Regularisation bandwidth factor."""
    shrinkage: float
    """Kernel shrinkage in [0, 1]."""
    temper_ess: float
    """Tempering target ESS fraction (0: no tempering)."""
    max_stages: int
    """Most tempering stages an update."""
    integrity_window: int
    """Updates the integrity monitor averages."""
    integrity_threshold: float
    """Averaged NIS above which the cloud is re-spread."""
    measurement_update: bool
    """Weigh the particles by the measurements (False: INS only)."""
    closed_loop: bool
    """Feed the estimate back into the nominal INS."""
    converged_after_s: float
    """The run's converged statistics start here, s."""

    def config(self) -> FilterConfig:
        """The filter's settings (:class:`~warptan.filter.config.FilterConfig`)."""
        return FilterConfig(n_particles=self.particles, resample_threshold=self.resample_threshold,
                            resampler=self.resampler, pos_noise=self.pos_noise_m_rthz,
                            kalman_pos_noise=self.kalman_pos_noise_m_rthz, regularize=self.regularize,
                            shrinkage=self.shrinkage, temper_ess=self.temper_ess, max_stages=self.max_stages,
                            integrity_window=self.integrity_window, integrity_threshold=self.integrity_threshold,
                            measurement_update=self.measurement_update, closed_loop=self.closed_loop)


@dataclass(frozen=True)
class InitialErrorSpec:
    """A scenario's ``[initial_error]`` table (σ of the initial INS error)."""

    pos_m: tuple
    """Position σ north, east, down, m."""
    vel_mps: float
    """Velocity σ per axis, m/s."""
    att_deg: tuple
    """Attitude σ roll, pitch, yaw, degrees."""

    def errors(self) -> InitialErrors:
        return InitialErrors(tuple(self.pos_m), self.vel_mps, tuple(self.att_deg))


@dataclass(frozen=True)
class RunSpec:
    """A scenario's ``[run]`` table."""

    seed: int
    """Added to each run's seed (S4 differs from S1 by it)."""


SECTIONS = {"terrain": MapSpec, "flight": FlightPlan, "imu": ImuSpec, "sensor": SensorSpec,
            "likelihood": LikelihoodSpec, "filter": FilterSpec, "initial_error": InitialErrorSpec, "run": RunSpec,
            "world": WorldModel}
"""A scenario file's tables and the dataclass each becomes (their fields are the schema's keys:
``tests/test_scenarios.py`` checks)."""


@dataclass(frozen=True)
class Scenario:
    """A scenario parsed once: its tables as typed, frozen dataclasses (see :data:`SECTIONS`; a changed copy:
    :meth:`replace`)."""

    id: str
    description: str
    paper_rmse_m: tuple
    """The paper's RMSE north, east, down, m (NaN: none)."""
    terrain: MapSpec
    flight: FlightPlan
    imu: ImuSpec
    sensor: SensorSpec
    likelihood: LikelihoodSpec
    filter: FilterSpec
    initial_error: InitialErrorSpec
    run: RunSpec
    world: WorldModel

    @classmethod
    def from_dict(cls, config: dict, source: str = "scenario") -> Scenario:
        """From a scenario's tables (a file's, as :mod:`tomllib` reads it; optional tables filled in), validated:
        raises :class:`ScenarioError` listing every problem, naming ``source``."""
        config = with_optional_defaults(dict(config))  # (it replaces whole tables: the caller's stay as they were)
        problems = validate(config, source)
        if problems:
            raise ScenarioError(f"{len(problems)} problem(s) in {source}:\n  " + "\n  ".join(problems))
        return cls.from_tables(config)

    @classmethod
    def from_tables(cls, config: dict) -> Scenario:
        """From tables already validated, or made by the program (a replay's: a recorded flight has no altitude
        rule); optional tables are filled in, lists become tuples."""
        config = with_optional_defaults(dict(config))

        def value(v):
            return tuple(v) if isinstance(v, list) else v

        tables = {name: kind(**{f.name: value(config[name][f.name]) for f in dataclasses.fields(kind)})
                  for name, kind in SECTIONS.items()}
        return cls(id=config["id"], description=config["description"], paper_rmse_m=tuple(config["paper_rmse_m"]),
                   **tables)

    def to_dict(self) -> dict:
        """The scenario as its file's tables (JSON-ready; what flight logs store): ``from_tables(s.to_dict()) == s``."""
        def value(v):
            return list(v) if isinstance(v, tuple) else v

        out = {"id": self.id, "description": self.description, "paper_rmse_m": list(self.paper_rmse_m)}
        for name in SECTIONS:
            table = getattr(self, name)
            out[name] = {f.name: value(getattr(table, f.name)) for f in dataclasses.fields(table)}
        return out

    def replace(self, **tables) -> Scenario:
        """A copy with fields of its tables changed: ``s.replace(flight={"duration_s": 60.0})``."""
        return dataclasses.replace(self, **{name: dataclasses.replace(getattr(self, name), **changes)
                                            for name, changes in tables.items()})


def check_seeds(seeds, base: int = 0) -> list[int]:
    """The run seeds as Python ints: each a whole number ≥ 0 with ``base + seed ≤`` :data:`MAX_SEED`, no repeats.

    Raises:
        ScenarioError: naming the first bad seed.
    """
    if isinstance(seeds, range):  # arithmetic only: `--seeds 5000000000` is answered at once
        if len(seeds) == 0:
            raise ScenarioError("at least one seed is needed")
        low, high = min(seeds[0], seeds[-1]), max(seeds[0], seeds[-1])
        if low < 0 or high > MAX_SEED - base:
            raise ScenarioError(f"seeds {seeds[0]} … {seeds[-1]} ({len(seeds)} seeds) must lie in "
                                f"[0, {MAX_SEED - base}] (run.seed {base} + seed ≤ {MAX_SEED})")
        return seeds
    if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__iter__"):
        seeds = [seeds]
    out = []
    for seed in seeds:
        value = check_seed(seed, "seed", ScenarioError)
        if value > MAX_SEED - base:
            raise ScenarioError(f"seed {seed} must be in [0, {MAX_SEED - base}] (run.seed {base} + seed ≤ {MAX_SEED})")
        out.append(value)
    if not out:
        raise ScenarioError("at least one seed is needed")
    if len(set(out)) != len(out):
        repeated = sorted(x for x, n in collections.Counter(out).items() if n > 1)
        raise ScenarioError(f"seed(s) {repeated[:10]}{' …' if len(repeated) > 10 else ''} given more than once; "
                            "each seed is one run")
    return out


def scan_points(scenario: Scenario) -> int:
    """Points of one of the scenario's measurements (``scan_nx × scan_ny``; 1 for the altimeter)."""
    s = scenario.sensor
    return 1 if s.model == "altimeter" else int(s.scan_nx) * int(s.scan_ny)


def particle_bytes(particles: float, points: int, model: str) -> float:
    """Device bytes of ``particles`` particles evaluating ``points`` points each, about (the particles' state, the
    model's residuals and, for ray casts, hit normals)."""
    per_point = 4.0 + (12.0 if model == "raycast" else 0.0)
    return float(particles) * (1024.0 + per_point * points)


def memory_estimate(scenario: Scenario, n_seeds: int, kept: int = 0) -> dict[str, float]:
    """Bytes a run of ``n_seeds`` seeds at once needs, about: ``host`` (the flight, each seed's IMU samples and
    scans, the histories, and the results of ``kept`` more seeds run one by one before, held for the report) and
    ``device`` (:func:`particle_bytes`, and each seed's scan)."""
    s = scenario.sensor
    samples = scenario.flight.duration_s * scenario.imu.rate_hz
    epochs = scenario.flight.duration_s * s.rate_hz
    points = scan_points(scenario)
    host = samples * (400.0 + 64.0 * n_seeds) + epochs * n_seeds * 2048.0 + points * (200.0 + 64.0 * n_seeds)
    host += kept * (16_000.0 + 512.0 * epochs)  # (a result's histories, summary and info: an S8 10 s one held 44 kB)
    device = particle_bytes(float(scenario.filter.particles) * n_seeds, points, s.model) + points * n_seeds * 64.0
    return {"host": host, "device": device}


def available_memory(device) -> dict[str, float]:
    """Bytes available now on the host (MemAvailable) and on ``device`` (free memory; the host's for the CPU)."""
    from warptan.device import resolve_device

    host = host_memory_available()
    d = resolve_device(device)
    dev = host if d.is_cpu else float(getattr(d, "free_memory", 0) or d.total_memory)
    return {"host": host, "device": dev}


MAX_SCAN_POINTS = 65_536
"""Points of one scan (``scan_nx × scan_ny``) at most: a 256×256 lidar frame. A scan of 100 000 × 10 points passed
the memory check and a 0.3 s flight was not done after two minutes (every particle evaluates every point)."""


def check_memory(scenario: Scenario, n_seeds: int, device="cpu", kept: int = 0) -> None:
    """Refuse (ScenarioError) a scan of more than :data:`MAX_SCAN_POINTS` points and a run whose
    :func:`memory_estimate` exceeds :data:`MEMORY_FRACTION` of what is available, before anything is allocated
    (``kept``: seeds run one by one whose results are held; ``--seeds 100000000`` ran on for days)."""
    s = scenario.sensor
    if scan_points(scenario) > MAX_SCAN_POINTS:
        raise ScenarioError(f"scenario {scenario.id}: a scan of {s.scan_nx}×{s.scan_ny} = {scan_points(scenario)} "
                            f"points (sensor.scan_nx × scan_ny) is more than {MAX_SCAN_POINTS} per scan; every "
                            "particle evaluates every point: use fewer")
    need, have = memory_estimate(scenario, n_seeds, kept), available_memory(device)
    for where in ("host", "device"):
        if need[where] > MEMORY_FRACTION * have[where]:
            name = "host" if where == "host" else f"device {device}"
            raise ScenarioError(
                f"scenario {scenario.id}: needs about {format_bytes(need[where])} of {name} memory ({n_seeds} "
                f"seed(s) at once × {scenario.filter.particles} particles, scan {s.scan_nx}×{s.scan_ny}, "
                f"{scenario.flight.duration_s:g} s at {scenario.imu.rate_hz:g} Hz"
                f"{f'; the results of {kept} seeds run one by one held' if kept else ''}) but "
                f"{format_bytes(have[where])} is available; use fewer particles, scan points, seeds or a shorter "
                "flight")


def format_bytes(n: float) -> str:
    """``n`` bytes in words (kB, MB, GB: powers of 1000)."""
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if n < 1000.0 or unit == "PB":
            return f"{n:.3g} {unit}"
        n /= 1000.0
    return f"{n:.3g} PB"


def scenario_path(name_or_path: str | os.PathLike) -> Path:
    """The TOML file of a scenario id (S1…S12, shipped with the package) or an explicit path."""
    text = os.fspath(name_or_path)
    if text.upper() in SCENARIO_IDS:
        return Path(str(resources.files("warptan") / "scenario_files" / f"{text.upper()}.toml"))
    path = Path(text)
    if path.suffix == ".toml":
        if not path.exists():
            raise ScenarioError(f"scenario file not found: {path}")
        return path
    raise ScenarioError(f"unknown scenario {text!r}; use one of {', '.join(SCENARIO_IDS)}, 'all', or a .toml path")


def _relative_to_file(config: dict, path: Path) -> None:
    """A scenario file's relative DEM paths (``[terrain] path``, ``map_path``; a ``#band=N`` kept) made relative to
    the file's folder, in place: they resolved against the current folder, so a run started elsewhere read another
    file of that name, or none (an override's path stays relative to the current folder, as a command line's)."""
    table = config.get("terrain")
    if not isinstance(table, dict):
        return
    for key in ("path", "map_path"):
        value = table.get(key)
        if isinstance(value, str) and value.strip() and not os.path.isabs(value) and not value.startswith(
                "synthetic:"):
            table[key] = str(Path(path).resolve().parent / value)


def load_config(name_or_path, overrides_from: str = "override", **overrides) -> Scenario:
    """Read, override and validate a scenario, parsed once into a :class:`Scenario`; raises :class:`ScenarioError`
    listing every problem. A problem of an overridden value names ``overrides_from`` (e.g. the campaign file that
    set it), not the scenario file."""
    path = scenario_path(name_or_path)
    try:
        with open(path, "rb") as f:
            config = tomllib.load(f)
    except tomllib.TOMLDecodeError as err:
        raise ScenarioError(f"{path}: not valid TOML ({err})") from None
    _relative_to_file(config, path)
    config = with_optional_defaults(config)
    problems = []
    for key, value in overrides.items():
        if value is None or key in ("terrain", "paper_rates"):
            continue
        if key not in OVERRIDES:
            hint = difflib.get_close_matches(key, RUN_KEYWORDS, n=1)
            problems.append(f"unknown override {key!r}" + (f" (did you mean {hint[0]!r}?)" if hint else ""))
            continue
        section, k = OVERRIDES[key]
        config.setdefault(section, {})[k] = value
    if overrides.get("paper_rates"):
        config.setdefault("sensor", {})["rate_hz"] = config.get("imu", {}).get("rate_hz")
    overridden = {f"{OVERRIDES[k][0]}.{OVERRIDES[k][1]} ": k for k, v in overrides.items()
                  if v is not None and k in OVERRIDES}
    problems = [f"{path}: {p}" for p in problems]
    for problem in validate(config, ""):
        problem = problem[2:]  # validate's "{source}: " with an empty source
        key = next((k for prefix, k in overridden.items() if problem.startswith(prefix)), None)
        problems.append(f"{overrides_from} {key}: {problem}" if key else f"{path}: {problem}")
    if problems:
        raise ScenarioError(f"{len(problems)} problem(s) in scenario {path.stem}:\n  " + "\n  ".join(problems))
    return Scenario.from_tables(config)

