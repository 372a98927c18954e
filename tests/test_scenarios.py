"""Scenarios S1–S12: every file validates, a short version of each runs, bad files list every problem."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import warptan as wt
from warptan.sim.scenario_config import SCENARIO_IDS, ScenarioError, load_config, scenario_path
from warptan.sim.scenarios import prepare, run_scenario

SMALL = "synthetic:rugged,size_m=12000,spacing=40,seed=2"


@pytest.mark.parametrize("sid", SCENARIO_IDS)
def test_short_scenario_runs(sid):
    """A short version (8 s, 64 particles, generated terrain) of each scenario runs on the CPU and returns
    finite RMSEs and the time series."""
    flat = "synthetic:flat,size_m=12000,spacing=40,seed=2"
    terrain = flat if load_config(sid).terrain.kind == "flat" else SMALL
    r = run_scenario(sid, seed=1, device="cpu", terrain=terrain, particles=64, duration_s=8.0)
    assert r.scenario == sid and r.rmse.shape == (3,) and np.isfinite(r.rmse).all()
    # converged RMSE: defined only for epochs after `converged_after_s` (30 s in every file: none in 8 s)
    assert r.config.filter.converged_after_s == 30.0 and np.isnan(r.rmse_converged).all()
    assert len(r.run.t_s) == 81 and np.isfinite(r.run.est_pos).all() and (r.run.ess > 0).all()
    assert r.terrain.startswith("synthetic")


# design notes §7's table, typed from the specification (id: terrain, IMU, bank, altitude, model, paper RMSE x / y / z).
DESIGN_TABLE = {
    "S1": ("rugged", "navigation", 30, "high", "sliding", (4.85, 2.80, 0.24)),
    "S2": ("rugged", "tactical_low", 30, "high", "sliding", (5.12, 3.39, 0.25)),
    "S3": ("rugged", "navigation", 30, "high", "raycast", (2.45, 1.91, 0.15)),
    "S4": ("rugged", "navigation", 30, "high", "sliding", (2.44, 2.73, 0.21)),
    "S5": ("rugged", "navigation", 60, "low", "raycast", (8.96, 11.44, 4.47)),
    "S6": ("rugged", "navigation", 60, "low", "sliding", (25.12, 17.77, 5.99)),
    "S7": ("rugged", "navigation", 0, "high", "raycast", (1.60, 1.54, 0.17)),
    "S8": ("rugged", "navigation", 0, "high", "sliding", (2.15, 1.62, 0.17)),
    "S9": ("rugged", "navigation", 0, "high", "altimeter", (13.22, 5.92, 1.17)),
    "S10": ("flat", "navigation", 0, "high", "raycast", (7.23, 9.91, 0.17)),
    "S11": ("flat", "navigation", 0, "high", "sliding", (9.29, 10.94, 0.14)),
    "S12": ("flat", "navigation", 0, "high", "altimeter", (30.87, 42.73, 0.99)),
}


def test_files_state_every_parameter():
    """Each shipped file validates on its own (no defaults are filled in) and matches design notes §7's table in every
    column for all twelve scenarios, with design notes §7's common parameters (speed, scan, initial σ)."""
    assert set(DESIGN_TABLE) == set(SCENARIO_IDS)
    for sid in SCENARIO_IDS:
        c = load_config(sid)
        assert c.id == sid and c.filter.particles == 500 and c.imu.rate_hz == 100.0
        assert c.sensor.rate_hz == 10.0 and c.flight.duration_s == 120.0
        assert c.flight.speed_mps == 100.0
        terrain, grade, bank, rule, model, paper = DESIGN_TABLE[sid]
        assert (c.terrain.kind, c.imu.grade, c.flight.bank_deg, c.flight.altitude_rule,
                c.sensor.model) == (terrain, grade, bank, rule, model), sid
        assert c.paper_rmse_m == pytest.approx(paper), sid
        e = c.initial_error  # every scenario of the paper starts with the high initial error
        assert (e.pos_m, e.vel_mps, e.att_deg) == ((100.0, 100.0, 20.0), 0.5, (0.1, 0.1, 0.5)), sid
        if model != "altimeter":
            assert (c.sensor.scan_nx, c.sensor.scan_ny, c.sensor.scan_half_angle_deg) == (10, 10, 30)


def test_paper_rates_and_overrides():
    """--paper-rates makes the measurement rate the IMU rate; overrides land in the config."""
    c = load_config("S8", paper_rates=True, particles=77, backend="mesh", likelihood="student_t")
    assert c.sensor.rate_hz == 100.0 and c.filter.particles == 77
    assert c.sensor.backend == "mesh" and c.likelihood.kind == "student_t"


def test_bad_file_lists_every_problem(tmp_path):
    """A file with a misspelt key, a missing key, a wrong type and a bad value reports all four at once."""
    text = scenario_path("S8").read_text()
    text = text.replace("bank_deg = 0.0", "bank_degs = 0.0")          # misspelt (and so missing)
    text = text.replace('grade = "navigation"', 'grade = "navigaton"')  # unknown grade
    text = text.replace("particles = 500", 'particles = "many"')        # wrong type
    text = text.replace("rate_hz = 10.0", "rate_hz = -10.0")            # bad value
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ScenarioError) as info:
        load_config(path)
    msg = str(info.value)
    for part in ("unknown key flight.bank_degs (did you mean flight.bank_deg?)", "missing key flight.bank_deg",
                 "imu.grade = 'navigaton' must be one of", "filter.particles = 'many' must be of type int",
                 "sensor.rate_hz = -10.0 must be > 0"):
        assert part in msg, (part, msg)


def test_scenario_is_typed_and_its_tables_are_the_schema():
    """A scenario is parsed once into frozen dataclasses whose fields are exactly the schema's keys (one table per
    layer's dataclass); its tables round-trip (``from_tables(to_dict())``); ``from_dict`` validates like a file,
    listing every problem; ``replace`` changes fields and refuses unknown ones."""
    import dataclasses

    from warptan.sim.scenario_config import SCHEMA, SECTIONS, Scenario

    for name, kind in SECTIONS.items():
        assert {f.name for f in dataclasses.fields(kind)} == set(SCHEMA[name]), name
    top = {f.name for f in dataclasses.fields(Scenario)} - set(SECTIONS)
    assert top == set(SCHEMA[""])
    for sid in SCENARIO_IDS:
        c = load_config(sid)
        assert Scenario.from_tables(c.to_dict()) == c == Scenario.from_dict(c.to_dict())
        with pytest.raises(dataclasses.FrozenInstanceError):
            c.filter.particles = 3
    tables = load_config("S8").to_dict()
    tables["sensor"]["rate_hz"], tables["filter"]["particles"] = -1.0, "many"
    with pytest.raises(ScenarioError) as info:
        Scenario.from_dict(tables, "my tables")
    assert "2 problem(s) in my tables" in str(info.value) and "sensor.rate_hz = -1.0 must be > 0" in str(info.value)
    c = load_config("S8").replace(flight={"duration_s": 60.0}, filter={"particles": 64})
    assert (c.flight.duration_s, c.filter.particles, c.filter.config().n_particles) == (60.0, 64, 64)
    with pytest.raises(TypeError):
        c.replace(flight={"duration": 60.0})


@pytest.mark.parametrize(("call", "message"), [
    (lambda: load_config("S13"), "unknown scenario 'S13'"),
    (lambda: load_config("S8", particle=5), "unknown override 'particle' (did you mean 'particles'?)"),
    (lambda: prepare("S8", terrain="/no/such/dem.tif"), "does not load"),
    (lambda: prepare("S8", terrain=SMALL, duration_s=1000.0), "leaves the DEM"),
    (lambda: load_config("S8", backend="optix"), "sensor.backend = 'optix' must be one of"),
])
def test_bad_runs_fail_before_computing(call, message):
    """Unknown scenario or override, a terrain that does not load, a flight leaving the DEM: clear errors."""
    with pytest.raises(ScenarioError, match=re.escape(message)):
        call()


def _highest_post_within(terrain, track, radius):
    """Brute force: the highest post whose horizontal distance to some track point is ≤ radius."""
    nn, ee = np.meshgrid(terrain.n0 + np.arange(terrain.shape[0]) * terrain.dn,
                         terrain.e0 + np.arange(terrain.shape[1]) * terrain.de, indexing="ij")
    near = np.zeros(terrain.shape, dtype=bool)
    for n, e in track[:, :2]:
        near |= (nn - n) ** 2 + (ee - e) ** 2 <= radius**2
    return float(np.nanmax(terrain.heights_m[near]))


@pytest.mark.parametrize(("sid", "radius", "above", "discriminates"),
                         [("S8", 2000.0, 600.0, True), ("S6", 1000.0, 150.0, False)])
def test_altitude_rule_is_exact(sid, radius, above, discriminates):
    """design notes §7: high = 600 m above the highest terrain within 2 km (horizontal distance) of the track, low =
    150 m within 1 km; the track is sampled once per second (100 m apart). A brute-force search over every post is the
    oracle; the rule's disc matters (the highest post within 1.5× the radius is higher on this terrain)."""
    terrain = wt.Terrain.load(SMALL)
    _, _, flight = prepare(sid, terrain=terrain, duration_s=60.0)
    assert np.ptp(flight.pos_n[:, 2]) < 1e-6
    inside = _highest_post_within(terrain, flight.pos_n[::100], radius)
    assert -flight.pos_n[0, 2] == pytest.approx(inside + above, abs=1e-6)
    if discriminates:  # the test can tell a disc of `radius` from a larger window (S6 orbits the highest hill)
        assert _highest_post_within(terrain, flight.pos_n[::100], 1.5 * radius) > inside


def test_orbit_passes_beside_the_hill():
    """S5's orbit passes 100–700 m beside the highest hill, at 150 m above it (the low rule)."""
    terrain = wt.Terrain.load(SMALL)
    _, _, orbit = prepare("S5", terrain=terrain)
    i, j = np.unravel_index(np.nanargmax(terrain.heights_m), terrain.shape)
    hill = np.array([terrain.n0 + i * terrain.dn, terrain.e0 + j * terrain.de])
    closest = np.min(np.linalg.norm(orbit.pos_n[:, :2] - hill, axis=1))
    assert 100.0 < closest < 700.0
    assert -orbit.pos_n[0, 2] == pytest.approx(terrain.h_max + 150.0, abs=1.0)


@pytest.mark.slow
def test_warptan_run_demo(tmp_path):
    """`warptan run` with no arguments finishes and writes results.json, results.md and the plots."""
    proc = subprocess.run([sys.executable, "-m", "warptan.cli", "run", "--quiet"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "warptan-demo"
    names = {p.name for p in out.iterdir()}
    assert {"results.json", "results.md", "S8_seed0_track.png", "S8_seed0_errors.png"} <= names
    data = json.loads((out / "results.json").read_text())
    assert data["scenarios"]["S8"]["terrain"] == "synthetic:rugged"
    assert "| S8 |" in (out / "results.md").read_text()


def test_warptan_run_check_and_errors(tmp_path):
    """--check validates without running; an unknown scenario exits 2 with one clear line."""
    ok = subprocess.run([sys.executable, "-m", "warptan.cli", "run", "S1", "S9", "--check", "--terrain", SMALL,
                         "--duration-s", "60"],
                        capture_output=True, text=True, cwd=tmp_path)
    assert ok.returncode == 0 and "S1: ok" in ok.stdout and "S9: ok" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "warptan.cli", "run", "S42"], capture_output=True, text=True,
                         cwd=tmp_path)
    assert bad.returncode == 2 and "unknown scenario 'S42'" in bad.stderr and "Traceback" not in bad.stderr
    assert not Path(tmp_path / "warptan-results").exists()


def test_warptan_run_batch_equals_one_by_one(tmp_path):
    """`warptan run S7 --seeds 3 --batch` (one batched filter) reports the same numbers as without --batch."""
    rmse = {}
    for flag in ([], ["--batch"]):
        out = tmp_path / ("batch" if flag else "single")
        proc = subprocess.run([sys.executable, "-m", "warptan.cli", "run", "S7", "--seeds", "3", *flag, "--terrain",
                               SMALL, "--duration-s", "4", "--particles", "200", "--no-plots", "--quiet", "--out",
                               str(out)], capture_output=True, text=True, timeout=600, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr
        runs = json.loads((out / "results.json").read_text())["runs"]
        rmse[bool(flag)] = [r["rmse_m"] for r in runs]
    assert len(rmse[True]) == 3 and rmse[True] == rmse[False]


def test_likelihood_sigma_auto_or_number():
    """likelihood.sigma_m is "auto" or a positive number; anything else is named in the scenario error, and the
    calibrated σ of S8 includes the map-error correlation over the updates a scan reads the same cells."""
    with pytest.raises(ScenarioError, match=re.escape("likelihood.sigma_m = 'automatic' must be 'auto'")):
        load_config("S8", sigma_m="automatic")
    with pytest.raises(ScenarioError, match=re.escape("filter.shrinkage = 2.0 must be in")):
        load_config("S8", shrinkage=2.0)
    from warptan.sim.scenarios import scenario_likelihood

    config = load_config("S8")
    flat = wt.Terrain.synthetic("flat", size_m=4000.0, spacing=30.0, seed=1)
    lik = scenario_likelihood(config, flat)
    assert lik.sigma_m is None and lik.map_correlation == pytest.approx(3.0)  # 30 m posts / (100 m/s / 10 Hz)
    assert lik.sensor_sigma_m == config.sensor.range_sigma_m


# ---------------------------------------------------------------------- world ≠ map (issue 13)
def test_scenarios_fly_the_package_terrains(monkeypatch):
    """Without a DEM directory (WARPTAN_DEM_DIR) the scenarios fly the real tiles shipped with the package; the
    30 m tile is one switch away for S1–S9."""
    monkeypatch.delenv("WARPTAN_DEM_DIR", raising=False)
    monkeypatch.chdir("/")
    assert prepare("S8")[1].name == "rugged:thuringia_hilly_srtm3_crop44km.tif"
    assert prepare("S11")[1].name == "flat:ganges_plain_flat_srtm3_crop24km.tif"
    for sid in ("S1", "S5", "S8"):
        assert prepare(sid, terrain="rugged30")[1].name.startswith("rugged30:")


def test_map_errors_from_the_scenario_file():
    """map_spacing_m (block means), map_noise_m (map_seed), map_bias_m build the filter's map from the world in
    that order; the map-aware σ counts the map's interpolation error only when its grid is not the world's."""
    from warptan.sim.scenarios import map_terrain, scenario_likelihood

    config, world, _ = prepare("S8", terrain="rugged30", map_spacing_m=90.0, map_bias_m=2.5, map_noise_m=1.0,
                               map_seed=4)
    the_map = map_terrain(world, config, seed=0)
    assert the_map.dn == the_map.de == 90.0 and the_map is not world
    expected = world.coarsened(3).heights_m + 2.5
    resid = the_map.heights_m - expected
    assert abs(resid.mean()) < 0.05 and resid.std() == pytest.approx(1.0, rel=0.05)
    np.testing.assert_array_equal(map_terrain(world, config, seed=99).heights_m, the_map.heights_m)  # map_seed
    aware = scenario_likelihood(config, the_map, world)
    assert aware.map_sigma_m == pytest.approx(np.hypot(1.0, the_map.interpolation_sigma_m(1.0)))
    assert aware.map_sigma_m > 4.0  # the 90 m map of the 30 m tile: ≈ 5 m
    config = config.replace(likelihood={"map_aware": False})
    assert scenario_likelihood(config, the_map, world).map_sigma_m == 1.0
    same_grid, world2, _ = prepare("S8", terrain="rugged30", map_noise_m=1.0)
    assert scenario_likelihood(same_grid, map_terrain(world2, same_grid, 0), world2).map_sigma_m == 1.0
    plain, world3, _ = prepare("S8", terrain="rugged30")
    assert map_terrain(world3, plain, 0) is world3


def test_map_file_and_bad_map_settings(tmp_path):
    """map_path reads another DEM onto the world's frame; a bad map file or setting is a clear error before any
    run; per-seed map noise cannot be batched unless map_seed fixes one realisation."""
    from warptan.sim.scenarios import map_terrain, run_scenario_batch
    from warptan.terrain.grid import named_terrain_file

    config, world, _ = prepare("S8", terrain="rugged30", map_path=str(named_terrain_file("rugged30")))
    the_map = map_terrain(world, config, 0)
    assert the_map.origin_xy == world.origin_xy and the_map is not world
    bad = tmp_path / "not_a_dem.tif"
    bad.write_text("hello")
    config = config.replace(terrain={"map_path": str(bad)})
    with pytest.raises(ScenarioError, match=r"not_a_dem\.tif"):
        map_terrain(world, config, 0)
    with pytest.raises(ScenarioError, match="map_seed"):
        load_config("S8", map_seed=-2)
    with pytest.raises(ValueError, match="map_seed"):
        run_scenario_batch("S8", [0, 1], terrain="rugged30", map_noise_m=1.0, duration_s=2.0)
    with pytest.raises(ScenarioError, match="map_spacing_m"):  # found by prepare (what --check runs)
        prepare("S8", terrain="rugged30", map_spacing_m=1e6)


def test_world_not_map_run_reports_the_map():
    """A short S8 over the 30 m world with a 90 m map runs, names both, and records the map σ it used."""
    r = run_scenario("S8", terrain="rugged30", map_spacing_m=90.0, duration_s=3.0, particles=64)
    s = r.summary()
    assert s["terrain"].startswith("rugged30:") and "block mean 3×3" in s["map"] and s["map_sigma_m"] > 4.0
    assert np.isfinite(r.run.est_pos).all()


def test_surface_key_reaches_the_model():
    """``sensor.surface`` picks what the sliding model reads: on triangles (the world's own surface here) its
    calibrated σ has no bilinear-vs-triangles mismatch; a bad value is an error naming the key."""
    terrain = "synthetic:rugged,size_m=12000,spacing=40,seed=2"
    sig = {s: wt.run_scenario("S8", seed=1, terrain=terrain, particles=200, duration_s=1.0,
                                        surface=s).run.info["sigma_m"] for s in ("triangles", "bilinear")}
    assert sig["triangles"] < sig["bilinear"], sig
    with pytest.raises(wt.ScenarioError, match=re.escape("sensor.surface")):
        wt.sim.scenario_config.load_config("S8", surface="cubic")


def test_altimeter_runs_that_walked_off_along_the_contours_converge():
    """S9 over the 30 m tile (seeds 12 and 18) walked off along the contours by kilometres before the altimeter kept
    its jitter within one reading's resolution and scored each particle for its kernel (CPU: 4.3–6.6 km); now each
    converges within 5 m with its 3σ covering the error.

    S12 over flat ground is checked over 40 seeds, not pinned ones: which seed loses itself there re-rolls with any
    change to the random stream or the rounding (seed 17 ended 63 m off at the session-23 code, 180 m at the
    session-24 code, 510 m with the session-24 code and the old Gaussian draws). Measured (CPU, converged horizontal
    RMSE of ``run_scenario_batch("S12", range(200))`` in batches of 40): session-23 code 4 of 200 beyond 100 m
    (none beyond 1 km, the worst 775 m), be79477 also 4 (none beyond 1 km, the worst 766 m), c6533ef on the way 6
    (2 beyond 1 km). Such a seed locks onto a wrong place in its first seconds over the featureless plain, its 3σ then
    shrinking around it; before the fix 3 of seeds 0–39 went 2–4.6 km. The bound below (median under 25 m, at most
    4 of 40 beyond 100 m) guards the bulk of the runs; it does not separate the fix from its absence on this ground."""
    from warptan.sim.scenarios import run_scenario_batch

    for r in run_scenario_batch("S9", [12, 18], device="cpu", terrain="rugged30"):
        horiz = float(np.hypot(*r.rmse_converged[:2]))
        assert horiz < 5.0, (r.seed, horiz)
        assert min(r.run.coverage(30.0)[:2]) > 0.9, (r.seed, r.run.coverage(30.0))
    s12 = run_scenario_batch("S12", range(40), device="cpu")
    horiz = np.array([float(np.hypot(*r.rmse_converged[:2])) for r in s12])
    assert np.median(horiz) < 25.0, np.median(horiz)
    assert (horiz > 100.0).sum() <= 4, np.sort(horiz)[-6:]
