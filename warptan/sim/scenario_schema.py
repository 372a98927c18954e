"""A scenario file's schema: every table and key with its type and range, the overrides ``run_scenario`` takes,
and :func:`validate` (every problem of a scenario dict listed at once). :mod:`warptan.sim.scenario_config` reads
files into the typed :class:`~warptan.sim.scenario_config.Scenario`."""

from __future__ import annotations

import dataclasses
import difflib
import math

from warptan.filter.config import MIN_PARTICLES, RESAMPLERS
from warptan.nav.flightplan import ALTITUDE_RULES, PATTERNS, PLACEMENTS
from warptan.nav.imu import IMU_GRADES
from warptan.sensing.likelihood import LIKELIHOODS, MAX_CONFIDENCE
from warptan.sensing.measurement import MODELS
from warptan.terrain.grid import NAMED_TERRAINS
from warptan.terrain.raycast import BACKENDS
from warptan.terrain.world import WorldModel

SCENARIO_IDS = tuple(f"S{i}" for i in range(1, 13))
TERRAIN_KINDS = (*NAMED_TERRAINS, "path")
SURFACES = ("triangles", "bilinear")
"""What the sliding and altimeter models read from the map: its triangulated surface (the surface ray casts
see, and the simulated world when the map is the world) or the bilinear interpolant of its posts."""


class ScenarioError(ValueError):
    """A scenario that cannot run; the message lists every problem found."""


# (type, check(value) -> error text or None)
def _pos(v):
    return None if v > 0 else "must be > 0"


def _nonneg(v):
    return None if v >= 0 else "must be ≥ 0"


def _upto(high: float, unit: str):
    """A number in [0, high]: beyond it the value is a typo or a corrupt file, not a setting (and large enough to
    overflow the device's float32)."""
    def check(v):
        return None if 0 <= v <= high else f"must be in [0, {high:g}]{' ' + unit if unit else ''}"
    return check


def _one_of(options):
    def check(v):
        return None if v in options else f"must be one of {', '.join(map(str, options))}"
    return check


def _vec(n, check=None):
    def inner(v):
        if not (isinstance(v, list) and len(v) == n and all(isinstance(x, (int, float)) for x in v)):
            return f"must be a list of {n} numbers"
        if not all(math.isfinite(x) for x in v):
            return f"must be a list of {n} finite numbers"
        if check:
            bad = [check(x) for x in v if check(x)]
            return bad[0] if bad else None
        return None
    return inner


SCHEMA: dict[str, dict[str, tuple[type | tuple, object]]] = {
    "": {"id": (str, None), "description": (str, None), "paper_rmse_m": (list, _vec(3, _nonneg))},
    "terrain": {
        "kind": (str, _one_of(TERRAIN_KINDS)),
        "path": (str, None),
        "map_path": (str, None),
        "map_noise_m": (float, _upto(1e4, "m")),
        "map_spacing_m": (float, _upto(1e5, "m")),
        "map_bias_m": (float, lambda v: None if abs(v) <= 1e4 else "must be within ±10000 m"),
        "map_seed": (int, lambda v: None if v >= -1 else "must be ≥ 0, or -1 (each run's own seed)"),
    },
    "flight": {
        "speed_mps": (float, lambda v: None if 0 < v <= MAX_SPEED_MPS else
                      f"must be in (0, {MAX_SPEED_MPS:g}] m/s (an aircraft's speed over ground)"),
        "duration_s": (float, _pos),
        "heading_deg": (float, None),
        "pattern": (str, _one_of(PATTERNS)),
        "bank_deg": (float, lambda v: None if 0 <= v < 90 else "must be in [0, 90) degrees"),
        "altitude_rule": (str, _one_of(ALTITUDE_RULES)),
        "placement": (str, _one_of(PLACEMENTS)),
        "hill_offset_m": (float, _nonneg),
        "margin_m": (float, _nonneg),
    },
    "imu": {"grade": (str, _one_of(tuple(IMU_GRADES))), "rate_hz": (float, _pos)},
    "sensor": {
        "model": (str, _one_of(tuple(MODELS))),
        "backend": (str, _one_of(tuple(BACKENDS))),
        "surface": (str, _one_of(SURFACES)),
        "rate_hz": (float, _pos),
        "scan_nx": (int, _pos),
        "scan_ny": (int, _pos),
        "scan_half_angle_deg": (float, lambda v: None if 0 <= v < 90 else "must be in [0, 90) degrees"),
        "range_sigma_m": (float, _upto(1e4, "m")),
        "altimeter_sigma_m": (float, _upto(1e4, "m")),
        "baro_sigma_m": (float, _upto(1e4, "m")),
        "use_baro": (bool, None),
    },
    "likelihood": {
        "kind": (str, _one_of(tuple(LIKELIHOODS))),
        "r_err_m2": (float, _pos),
        "sigma_m": ((float, str), lambda v: None if v == "auto" or (not isinstance(v, str) and v > 0)
                    else "must be 'auto' (σ_sensor ⊕ σ_map) or a positive number of metres"),
        "nu": (float, _pos),
        "map_aware": (bool, None),
        "map_error_rms_m": (float, _upto(1e3, "m")),
        "map_error_corr_m": (float, _upto(1e6, "m")),
        "map_error_learn": ((bool, str), lambda v: None if v in (True, False, "auto") else
                            "must be 'auto' (learn the map's error unless the map is the world), true or false"),
        "map_error_confidence": (float, lambda v: None if 1.0 <= v <= MAX_CONFIDENCE else
                                 f"must be a factor in [1, {MAX_CONFIDENCE:g}]: the stated RMS is right within it"),
    },
    "filter": {
        "particles": (int, lambda v: None if v >= MIN_PARTICLES else f"must be ≥ {MIN_PARTICLES} (a particle filter "
                      "weighs particles against each other)"),
        "resample_threshold": (float, lambda v: None if 0 <= v <= 1 else "must be in [0, 1]"),
        "resampler": (str, _one_of(tuple(RESAMPLERS))),
        "pos_noise_m_rthz": (float, _upto(1e3, "m/√s")),
        "kalman_pos_noise_m_rthz": (float, _upto(1e3, "m/√s")),
        "regularize": (float, _upto(100.0, "")),
        "shrinkage": (float, lambda v: None if 0 <= v <= 1 else "must be in [0, 1]"),
        "temper_ess": (float, lambda v: None if 0 <= v <= 1 else "must be in [0, 1]"),
        "max_stages": (int, lambda v: None if 1 <= v <= 64 else "must be in [1, 64]"),
        "integrity_window": (int, lambda v: None if 1 <= v <= 64 else "must be in [1, 64]"),
        "integrity_threshold": (float, lambda v: None if 0 < v <= 1e6 else "must be in (0, 1e6]"),
        "measurement_update": (bool, None),
        "closed_loop": (bool, None),
        "converged_after_s": (float, _nonneg),
    },
    "initial_error": {
        "pos_m": (list, _vec(3, _upto(1e5, "m"))),
        "vel_mps": (float, _upto(1e3, "m/s")),
        "att_deg": (list, _vec(3, _upto(180.0, "°"))),
    },
    "run": {"seed": (int, lambda v: None if 0 <= v <= MAX_SEED else f"must be in [0, {MAX_SEED}]")},
    "world": {  # types here; the ranges are WorldModel.problems (one place for files and the API)
        "relief_rms_m": ((float, str), None),
        "relief_slope": ((float, str), None),
        "error_rms_m": (float, None),
        "error_corr_m": (float, None),
        "bias_m": (float, None),
        "clutter_height_m": (float, None),
        "clutter_fraction": (float, None),
        "clutter_patch_m": (float, None),
        "refine": (int, None),
        "seed": (int, None),
    },
}
STATED_ACCURACY_DEFAULTS = {"map_error_rms_m": 0.0, "map_error_corr_m": 0.0, "map_error_learn": "auto",
                            "map_error_confidence": 2.0}
"""``[likelihood]`` keys a file may leave out: the DEM's stated correlated error (none), whether the filter learns
it in flight (``"auto"``: whenever the map is not known to be the world) and the factor its RMS is right within."""
WORLD_DEFAULTS = {f.name: f.default for f in dataclasses.fields(WorldModel)}
"""A scenario without a ``[world]`` table (or without some of its keys) flies these: the world is the map."""

MAX_SPEED_MPS = 1000.0
"""Fastest flight a scenario may state (Mach 3); beyond it the flight is a typo, not an aircraft."""
MAX_SEED = 2**32 - 1
"""Largest seed (file ``run.seed`` + the run's seed): the IMU, sensor and filter streams are seeded from it."""
MEMORY_FRACTION = 0.9
"""A run whose estimated memory exceeds this fraction of the available host (or device) memory is refused."""

OVERRIDES = {
    "particles": ("filter", "particles"),
    "duration_s": ("flight", "duration_s"),
    "backend": ("sensor", "backend"),
    "surface": ("sensor", "surface"),
    "likelihood": ("likelihood", "kind"),
    "model": ("sensor", "model"),
    "meas_rate_hz": ("sensor", "rate_hz"),
    "scan_nx": ("sensor", "scan_nx"),
    "scan_ny": ("sensor", "scan_ny"),
    "use_baro": ("sensor", "use_baro"),
    "r_err_m2": ("likelihood", "r_err_m2"),
    "sigma_m": ("likelihood", "sigma_m"),
    "imu_grade": ("imu", "grade"),
    "pos_noise": ("filter", "pos_noise_m_rthz"),
    "kalman_pos_noise": ("filter", "kalman_pos_noise_m_rthz"),
    "regularize": ("filter", "regularize"),
    "shrinkage": ("filter", "shrinkage"),
    "temper_ess": ("filter", "temper_ess"),
    "max_stages": ("filter", "max_stages"),
    "integrity_threshold": ("filter", "integrity_threshold"),
    "integrity_window": ("filter", "integrity_window"),
    "measurement_update": ("filter", "measurement_update"),
    "closed_loop": ("filter", "closed_loop"),
    "map_path": ("terrain", "map_path"),
    "map_spacing_m": ("terrain", "map_spacing_m"),
    "map_noise_m": ("terrain", "map_noise_m"),
    "map_bias_m": ("terrain", "map_bias_m"),
    "map_seed": ("terrain", "map_seed"),
    "map_aware": ("likelihood", "map_aware"),
    "map_error_rms_m": ("likelihood", "map_error_rms_m"),
    "map_error_corr_m": ("likelihood", "map_error_corr_m"),
    "map_error_learn": ("likelihood", "map_error_learn"),
    "map_error_confidence": ("likelihood", "map_error_confidence"),
    "world_relief_rms_m": ("world", "relief_rms_m"),
    "world_relief_slope": ("world", "relief_slope"),
    "world_error_rms_m": ("world", "error_rms_m"),
    "world_error_corr_m": ("world", "error_corr_m"),
    "world_bias_m": ("world", "bias_m"),
    "world_clutter_height_m": ("world", "clutter_height_m"),
    "world_clutter_fraction": ("world", "clutter_fraction"),
    "world_clutter_patch_m": ("world", "clutter_patch_m"),
    "world_refine": ("world", "refine"),
    "world_seed": ("world", "seed"),
}
"""run_scenario keyword -> (section, key). Also: terrain= (path, spec or Terrain), paper_rates=True."""
RUN_KEYWORDS = (*OVERRIDES, "terrain", "paper_rates")
"""Every keyword run_scenario takes besides the seed, device and callbacks."""


def _type_ok(value, kind) -> bool | None:
    """True when ``value`` has the schema type ``kind``; None for a non-finite float (nan, inf: never a setting)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(kind, tuple):
        return any(_type_ok(value, k) for k in kind)
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, kind)


def validate(config: dict, source: str = "scenario") -> list[str]:
    """Every problem of a scenario dict (empty list: valid)."""
    problems = []
    known_sections = [s for s in SCHEMA if s]
    for key, value in config.items():
        if isinstance(value, dict) and key not in SCHEMA:
            hint = difflib.get_close_matches(key, known_sections, n=1)
            problems.append(f"unknown section [{key}]" + (f" (did you mean [{hint[0]}]?)" if hint else ""))
    for section, keys in SCHEMA.items():
        table = config if not section else config.get(section)
        where = section + "." if section else ""
        if table is None:
            problems.append(f"missing section [{section}]")
            continue
        if not isinstance(table, dict):
            problems.append(f"[{section}] must be a table")
            continue
        for key, value in table.items():
            if isinstance(value, dict) and not section:
                continue
            if key not in keys:
                hint = difflib.get_close_matches(key, list(keys), n=1)
                problems.append(f"unknown key {where}{key}" + (f" (did you mean {where}{hint[0]}?)" if hint else ""))
        for key, (kind, check) in keys.items():
            if key not in table:
                problems.append(f"missing key {where}{key}")
                continue
            value = table[key]
            if _type_ok(value, float) is None:
                problems.append(f"{where}{key} = {value!r} must be a finite number")
                continue
            if not _type_ok(value, kind):
                names = " or ".join(k.__name__ for k in kind) if isinstance(kind, tuple) else kind.__name__
                problems.append(f"{where}{key} = {value!r} must be of type {names}")
                continue
            msg = check(value) if check else None
            if msg:
                problems.append(f"{where}{key} = {value!r} {msg}")
    if isinstance(config.get("world"), dict) and not any(p.startswith("world.") for p in problems):
        problems += WorldModel.from_config(config["world"]).problems()
    if not problems:
        imu_rate, meas_rate = config["imu"]["rate_hz"], config["sensor"]["rate_hz"]
        ratio = imu_rate / meas_rate
        if abs(ratio - round(ratio)) > 1e-9 or ratio < 1:
            problems.append(f"sensor.rate_hz = {meas_rate} must divide imu.rate_hz = {imu_rate}")
        lk = config["likelihood"]
        if lk["map_error_rms_m"] > 0 and lk["map_error_corr_m"] <= 0:
            problems.append(f"likelihood.map_error_rms_m = {lk['map_error_rms_m']:g} needs likelihood.map_error_corr_m "
                            "> 0 (the stated error's correlation length, m)")
        if config["terrain"]["kind"] == "path" and not config["terrain"]["path"]:
            problems.append("terrain.path must be set when terrain.kind = 'path'")
        if config["flight"]["pattern"] != "straight" and config["flight"]["bank_deg"] <= 0:
            problems.append(f"flight.pattern = {config['flight']['pattern']!r} needs flight.bank_deg > 0")
        if config["flight"]["duration_s"] * meas_rate < 1.0 - 1e-9:
            problems.append(f"flight.duration_s = {config['flight']['duration_s']:g} is shorter than one measurement "
                            f"interval (1 / sensor.rate_hz = {1.0 / meas_rate:g} s)")
        if config["filter"]["kalman_pos_noise_m_rthz"] == 0 and config["initial_error"]["vel_mps"] == 0:
            problems.append("filter.kalman_pos_noise_m_rthz = 0 with initial_error.vel_mps = 0 makes the filter's N_k "
                            "singular (no position uncertainty enters the Kalman part); make one of them > 0")
    return [f"{source}: {p}" for p in problems]


def with_optional_defaults(config: dict) -> dict:
    """``config`` with the keys a scenario may leave out filled in: the ``[world]`` table (the world is the map)
    and the DEM's stated accuracy in ``[likelihood]`` (none). Configs stored before these existed (flight logs)
    read the same way."""
    if isinstance(config.get("world", {}), dict):
        config["world"] = {**WORLD_DEFAULTS, **config.get("world", {})}
    if isinstance(config.get("likelihood"), dict):
        config["likelihood"] = {**STATED_ACCURACY_DEFAULTS, **config["likelihood"]}
    return config
