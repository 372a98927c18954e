"""Nothing lost, nothing silent (issue 37): output folders that never delete inputs or another writer's work, maps
that must cover the flight, runs that say when they navigated nothing, limits checked before work, and one clear
line for every mistake of the 65-case probe that was not already right.

CLI cases run ``warptan.cli.main`` in-process (exit status, the one-line message, the files afterwards); the lock,
SIGTERM and full-disk cases run real ``python -m warptan`` processes.
"""

import json
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import time
import warnings
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import rasterio
import warp as wp
from rasterio.transform import Affine

import warptan as wt
from warptan import cli, outputs
from warptan.io.flightlog import LogError, read_log, write_log
from warptan.sim.scenario_config import ScenarioError, check_seeds, scenario_path
from warptan.sim.scenarios import prepare

QUICK = ["--duration-s", "0.5", "--particles", "16", "--quiet", "--no-plots"]
RUGGED_TIF = str(resources.files("warptan") / "data" / "dem" / "thuringia_hilly_srtm3_crop44km.tif")


def _cli(capsys, *argv):
    try:
        status = cli.main([str(a) for a in argv])
    except SystemExit as exc:
        status = exc.code
    out, err = capsys.readouterr()
    return status, out, err


def _error_line(err: str, *fragments) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip() and "CUDA" not in ln and "warning:" not in ln]
    assert len(lines) == 1 and "Traceback" not in err and "Errno" not in err, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if ".warptan-" in p.name]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """`warptan run S8 --export-log L --out R`: a flight-log folder and a run folder."""
    base = tmp_path_factory.mktemp("exported")
    status = cli.main(["run", "S8", *QUICK, "--export-log", str(base / "L"), "--out", str(base / "R")])
    assert status == 0
    return base / "L", base / "R"


def _copy(folder: Path, to: Path) -> Path:
    shutil.copytree(folder, to)
    return to


# ------------------------------------------------------------------------------------------- outputs only
def test_an_export_folder_is_never_replaced_by_a_run_or_a_replay(capsys, exported, tmp_path):
    """`warptan replay L/S8_seed0.h5 --out L` deleted the log; `warptan run S8 --out L` did the same."""
    logs = _copy(exported[0], tmp_path / "L")
    before = _snapshot(logs)
    status, _, err = _cli(capsys, "replay", logs / "S8_seed0.h5", "--out", logs, "--quiet", "--no-plots")
    assert status == 2 and _snapshot(logs) == before
    _error_line(err, "--out", "flight logs")
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--out", logs)
    assert status == 2 and _snapshot(logs) == before
    _error_line(err, "flight logs written by --export-log")
    assert not _leftovers(tmp_path)


def test_a_campaign_does_not_replace_a_run_and_a_run_not_a_campaign(capsys, exported, tmp_path):
    run_folder = _copy(exported[1], tmp_path / "R")
    before = _snapshot(run_folder)
    campaign = tmp_path / "c.toml"
    campaign.write_text('scenarios = ["S8"]\nseeds = 1\n[overrides]\nduration_s = 0.5\nparticles = 16\n')
    status, _, err = _cli(capsys, "campaign", campaign, "--out", run_folder, "--check")
    assert status == 2 and _snapshot(run_folder) == before
    _error_line(err, "a warptan run's results", "a campaign does not replace")
    status, _, err = _cli(capsys, "campaign", campaign, "--out", tmp_path / "C", "--quiet", "--no-plots")
    assert status == 0, err
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--out", tmp_path / "C")
    assert status == 2
    _error_line(err, "a warptan campaign's results")


def test_an_output_folder_that_is_holds_or_lies_in_an_input_is_refused(capsys, exported, tmp_path):
    """--out on the folder of the DEM, the scenario file or the campaign file; --out inside a bag folder."""
    dem_dir = tmp_path / "dems"
    dem_dir.mkdir()
    shutil.copy(RUGGED_TIF, dem_dir / "world.tif")
    (dem_dir / outputs.MANIFEST).write_text('{"kind": "run", "files": ["results.json"]}')  # an old run's folder
    status, _, err = _cli(capsys, "run", "S8", "--terrain", dem_dir / "world.tif", "--check", "--out", dem_dir)
    assert status == 2 and sorted(os.listdir(dem_dir)) == [outputs.MANIFEST, "world.tif"]
    _error_line(err, "contains the input", "world.tif")
    status, _, err = _cli(capsys, "run", "S8", "--map", dem_dir / "world.tif", "--check", "--out", dem_dir)
    assert status == 2
    _error_line(err, "contains the input")
    scen = tmp_path / "mine"
    scen.mkdir()
    shutil.copy(scenario_path("S8"), scen / "S8b.toml")
    (scen / outputs.MANIFEST).write_text('{"kind": "run", "files": ["results.json"]}')  # an old run's folder
    status, _, err = _cli(capsys, "run", scen / "S8b.toml", *QUICK, "--out", scen)
    assert status == 2 and (scen / "S8b.toml").exists()
    _error_line(err, "contains the input", "S8b.toml")
    camp = tmp_path / "camp"
    camp.mkdir()
    (camp / "c.toml").write_text('scenarios = ["S8"]\nseeds = 1\n')
    (camp / outputs.MANIFEST).write_text('{"kind": "campaign", "files": ["campaign.json"]}')  # a campaign's folder
    status, _, err = _cli(capsys, "campaign", camp / "c.toml", "--out", camp, "--check")
    assert status == 2
    _error_line(err, "contains the input", "c.toml")
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (bag / "bag.mcap").write_bytes(b"")
    status, _, err = _cli(capsys, "replay", bag / "bag.mcap", "--out", bag / "results")
    assert status == 2 and not (bag / "results").exists()
    _error_line(err, "lies inside the input", str(bag))
    (tmp_path / "o").mkdir()
    status, _, err = _cli(capsys, "run", "S8", "--check", "--out", tmp_path / "o", "--export-log", tmp_path / "o" / "L")
    assert status == 2
    _error_line(err, "--export-log", "neither inside the other")


def test_a_rerun_removes_only_what_the_previous_run_listed(tmp_path):
    """A file the user put inside a sub-folder of a previous output survives the rerun (it was deleted with the
    sub-folder); a user's file with the name of a new output stops the swap, and the new outputs are kept."""
    out = tmp_path / "res"
    with outputs.OutputFolder(out) as tmp:
        (tmp / "results.json").write_text("1")
        (tmp / "plots").mkdir()
        (tmp / "plots" / "a.png").write_text("old plot")
    (out / "plots" / "my_notes.txt").write_text("mine")
    (out / "plots" / "deep").mkdir()
    (out / "plots" / "deep" / "x.csv").write_text("1,2")
    with outputs.OutputFolder(out) as tmp:
        (tmp / "results.json").write_text("2")
    after = _snapshot(out)
    assert after["results.json"] == b"2" and "plots/a.png" not in after
    assert after["plots/my_notes.txt"] == b"mine" and after["plots/deep/x.csv"] == b"1,2"
    (out / "results.md").write_text("the user's own file")
    with pytest.raises(outputs.OutputError, match=r"results\.md was not written by the previous run") as err, \
            outputs.OutputFolder(out) as tmp:
        (tmp / "results.json").write_text("3")
        (tmp / "results.md").write_text("new")
    assert _snapshot(out) == {**after, "results.md": b"the user's own file"}
    kept = Path(str(err.value).rsplit("the new outputs are in ", 1)[1])
    assert (kept / "results.json").read_text() == "3"


# ------------------------------------------------------------------------------------------- one writer
_HOLDER = """
import sys, time
from warptan.outputs import OutputFolder
folder = OutputFolder(sys.argv[1])
print("locked", flush=True)
time.sleep(120)
"""


def test_a_second_writer_is_refused_at_once_naming_the_first(capsys, tmp_path):
    """Two runs on one --out 0.5 s apart both said "wrote"; only the second's results existed. The lock dies with
    its process, even a SIGKILLed one."""
    out = tmp_path / "res"
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(out)], stdout=subprocess.PIPE, text=True,
                              cwd=tmp_path)
    try:
        assert holder.stdout.readline().strip() == "locked"
        t0 = time.monotonic()
        status, _, err = _cli(capsys, "run", "S8", *QUICK, "--out", out)
        assert status == 2 and time.monotonic() - t0 < 30
        _error_line(err, "being written by another warptan process", f"pid {holder.pid}")
        assert not out.exists()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--out", out)
    assert status == 0, err
    assert (out / "results.json").exists() and not _leftovers(tmp_path)


def test_a_killed_writers_partial_folder_is_removed_by_the_next(tmp_path):
    """SIGTERM and SIGINT clean up (tests/test_bad_inputs.py); a SIGKILL during a write cannot: the next holder of
    the folder's lock removes what it left."""
    out = tmp_path / "res"
    stale = tmp_path / ".res.warptan-partial-deadbeef"  # what a SIGKILL during a write leaves
    stale.mkdir()
    (stale / "results.json").write_text("{")
    outputs.OutputFolder(out).release()
    assert not stale.exists()


# ------------------------------------------------------------------------------------------- failed writes
def _fsize_limit(limit):
    def apply():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def test_a_full_disk_names_the_file_and_keeps_the_previous_run(tmp_path):
    """ulimit -f as a stand-in for a full disk: it was a raw "[Errno 27] File too large" naming no file."""
    out = tmp_path / "res"
    argv = [sys.executable, "-m", "warptan", "run", "S8", *QUICK, "--out", str(out)]
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    first = subprocess.run(argv, capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert first.returncode == 0, first.stderr
    before = _snapshot(out)
    proc = subprocess.run([*argv, "--seeds", "2"], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                          env=env, preexec_fn=_fsize_limit(1500))
    assert proc.returncode == 2, proc.stderr
    line = _error_line(proc.stderr, f"writing {out / 'results.json'} failed", "File too large",
                       "is as it was before this run")
    assert ".warptan-partial" not in line
    assert _snapshot(out) == before and not _leftovers(tmp_path)


def test_a_read_only_or_immutable_output_folder_is_refused_by_check(capsys, tmp_path, monkeypatch):
    """--check said ok for an immutable empty folder; the run failed at its end with a raw errno naming a hidden
    folder."""
    out = tmp_path / "frozen"
    out.mkdir()
    immutable = subprocess.run(["chattr", "+i", str(out)], capture_output=True).returncode == 0 \
        if shutil.which("chattr") else False
    try:
        if not immutable:  # a file system without attributes: the same refusal, as os.access reports it
            real = os.access
            monkeypatch.setattr(outputs.os, "access",
                                lambda p, mode: False if Path(p) == out and mode & os.W_OK else real(p, mode))
        status, out_text, err = _cli(capsys, "run", "S8", "--check", "--out", out)
        assert status == 2 and "ok" not in out_text
        _error_line(err, "read-only or immutable", str(out))
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(out)], check=True)


def test_export_log_errors_name_export_log(capsys, tmp_path):
    (tmp_path / "afile").write_text("x")
    status, _, err = _cli(capsys, "run", "S8", "--check", "--out", tmp_path / "o", "--export-log", tmp_path / "afile")
    assert status == 2
    line = _error_line(err, "--export-log", "is a file")
    assert "--out" not in line


def test_terrain_export_never_overwrites_silently_and_names_a_missing_folder(capsys, tmp_path):
    spec = "synthetic:flat,size_m=2000,spacing=100"
    status, _, err = _cli(capsys, "terrain", "export", spec, tmp_path / "missing" / "t.ply")
    assert status == 2
    line = _error_line(err, "missing", "does not exist")
    assert ".warptan-export" not in line
    target = tmp_path / "t.ply"
    target.write_text("my mesh")
    status, _, err = _cli(capsys, "terrain", "export", spec, target)
    assert status == 2 and target.read_text() == "my mesh"
    _error_line(err, "exists", "--overwrite")
    assert _cli(capsys, "terrain", "export", spec, target, "--overwrite")[0] == 0
    assert target.read_bytes().startswith(b"ply")


# ------------------------------------------------------------------------------------------- maps and skips
def _shifted_dem(path: Path, east_deg: float) -> str:
    """The package's Thuringia crop with its georeferencing moved ``east_deg`` degrees east: another place."""
    with rasterio.open(RUGGED_TIF) as src:
        profile, data = src.profile, src.read()
        t = src.transform
    profile.update(transform=Affine(t.a, t.b, t.c + east_deg, t.d, t.e, t.f))
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data)
    return str(path)


def test_a_map_of_another_place_is_refused_by_check(capsys, tmp_path):
    """`--map F`, F a DEM of another place: exit 0 with every update skipped; --check said ok."""
    elsewhere = _shifted_dem(tmp_path / "elsewhere.tif", 3.0)
    for extra in (["--check"], QUICK):
        status, _, err = _cli(capsys, "run", "S8", "--map", elsewhere, "--out", tmp_path / "o", *extra)
        assert status == 2
        _error_line(err, "the filter's map does not cover the flight", "elsewhere.tif")
    assert not (tmp_path / "o").exists()
    with pytest.raises(ScenarioError, match="does not cover the flight"):
        prepare("S8", map_path=elsewhere)


def test_a_run_whose_updates_were_all_skipped_exits_non_zero(capsys, tmp_path):
    """A map that covers only a thin strip under the track: every scan is unpredictable. The results are written
    (marked), the summary says so, and the exit status is 1; a map of the ground itself runs clean."""
    with rasterio.open(RUGGED_TIF) as src:
        profile, data = src.profile, src.read(1).astype("float32")
    strip = np.full_like(data, -32768.0)
    c = data.shape[1] // 2
    strip[:, c - 2:c + 3] = data[:, c - 2:c + 3]
    profile.update(nodata=-32768.0, dtype="float32")
    with rasterio.open(tmp_path / "strip.tif", "w", **profile) as dst:
        dst.write(strip, 1)
    out = tmp_path / "o"
    status, _, err = _cli(capsys, "run", "S8", "--map", tmp_path / "strip.tif", "--out", out, *QUICK)
    assert status == 1
    assert "every update was skipped" in err and "navigated nothing" in err and "Traceback" not in err
    run = json.loads((out / "results.json").read_text())
    assert run["runs"][0]["updates_used"] == 0 and run["runs"][0]["skipped_updates"] == run["runs"][0]["updates"] > 0
    assert run["scenarios"]["S8"]["runs_without_any_update"] == 1
    campaign = tmp_path / "c.toml"
    campaign.write_text('scenarios = ["S8"]\nseeds = 1\n[overrides]\nmap_path = "strip.tif"\nduration_s = 0.5\n'
                        'particles = 16\n')
    status, _, err = _cli(capsys, "campaign", campaign, "--out", tmp_path / "c", "--quiet", "--no-plots")
    assert status == 1 and "every update was skipped" in err
    rows = json.loads((tmp_path / "c" / "campaign.json").read_text())["rows"]
    assert rows[0]["seeds_without_any_update"] == [0]
    status, text, err = _cli(capsys, "run", "S8", "--map", RUGGED_TIF, "--out", tmp_path / "ok", *QUICK)
    assert status == 0, err
    assert "updates were not used" not in text + err


def test_partly_skipped_runs_are_named_in_the_summary(capsys):
    class Run:  # the prior epoch, then 200 updates: 12 skipped, 3 without a valid received point
        t_s = np.arange(201.0)
        skipped = np.r_[False, np.arange(200) < 12]
        all_points_invalid = np.r_[False, (np.arange(200) >= 12) & (np.arange(200) < 15)]

    class Partly:
        scenario, seed, run = "S8", 3, Run()

    assert cli.commands._report_skipped([Partly()]) == 0
    out, _ = capsys.readouterr()
    assert "S8 seed 3: 15 of 200 updates were not used (12 skipped" in out and "3 without a valid measurement" in out


# ------------------------------------------------------------------------------------------- limits
def test_a_sparse_giant_geotiff_is_refused_before_reading(capsys, tmp_path):
    """12 000 × 12 000 posts in an 18 kB sparse file: it loaded as flat 0 m terrain, 9.7 GB resident."""
    path = tmp_path / "sparse.tif"
    with rasterio.open(path, "w", driver="GTiff", width=12000, height=12000, count=1, dtype="float32",
                       crs="EPSG:32632", transform=Affine(30, 0, 500000, 0, -30, 5000000), tiled=True,
                       SPARSE_OK=True) as dst:
        dst.write(np.ones((256, 256), "float32"), 1, window=rasterio.windows.Window(0, 0, 256, 256))
    assert path.stat().st_size < 1_000_000
    t0 = time.monotonic()
    with pytest.raises(wt.TerrainError, match=r"12000×12000 = 144000000 posts \(limit 60000000 at native"):
        wt.Terrain.load(str(path))
    status, _, err = _cli(capsys, "run", "S8", "--terrain", path, "--check")
    assert status == 2 and time.monotonic() - t0 < 20
    _error_line(err, "144000000 posts")


def test_a_truncated_geotiff_is_called_truncated(tmp_path):
    """A GeoTIFF cut to its first 200 bytes was "no CRS"."""
    data = 200.0 + np.arange(40 * 50, dtype=np.float32).reshape(40, 50) % 17
    full = tmp_path / "full.tif"
    with rasterio.open(full, "w", driver="GTiff", width=50, height=40, count=1, dtype="float32",
                       crs="EPSG:32632", transform=Affine(30, 0, 500000, 0, -30, 5000000)) as dst:
        dst.write(data, 1)
    for size in (200, 2000):
        cut = tmp_path / f"cut{size}.tif"
        cut.write_bytes(full.read_bytes()[:size])
        with pytest.raises(wt.TerrainError, match=rf"cut{size}\.tif: the file is truncated: it has {size} bytes"):
            wt.Terrain.load(str(cut))
    assert wt.Terrain.load(str(full)).shape == (40, 50)


def test_seeds_beyond_the_generators_range_fail_at_once(capsys):
    """--seeds 5000000000 --check hung; --seeds 100000000 --batch --check took 126 s to its memory error; a 40 000
    seed list with one repeat took 20 s."""
    t0 = time.monotonic()
    status, _, err = _cli(capsys, "run", "S8", "--seeds", "5000000000", "--check")
    assert status == 2
    _error_line(err, "5000000000 seeds", "4294967295")
    status, _, err = _cli(capsys, "run", "S8", "--seeds", "100000000", "--batch", "--check")
    assert status == 2
    _error_line(err, "needs about", "memory")
    seeds = [*range(40_000), 17]
    with pytest.raises(ScenarioError, match=r"seed\(s\) \[17\] given more than once"):
        check_seeds(seeds)
    assert time.monotonic() - t0 < 15
    assert check_seeds(range(3, 10)) == range(3, 10)
    with pytest.raises(ScenarioError, match="must lie in"):
        check_seeds(range(2**32 - 2, 2**32 + 1))


# ------------------------------------------------------------------------------------------- API
def _model_and_poses(n=8):
    terrain = wt.Terrain.synthetic("rugged", size_m=6000.0, spacing=30.0, seed=1)
    model = wt.SlidingModel(terrain)
    pos = np.tile([0.0, 0.0, -(terrain.h_max + 500.0)], (n, 1))
    pos[:, 0] += np.arange(n) * 20.0
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    cloud = wt.PointCloud(np.tile([0.0, 0.0, 1.0], (4, 1)), np.full(4, 500.0))
    return model, pos, quat, cloud


def test_evaluate_returns_arrays_the_caller_may_keep():
    """loglik.numpy() kept by the caller was overwritten by the next evaluate on the CPU (shared memory)."""
    model, pos, quat, cloud = _model_and_poses()
    first = model.evaluate(wp.array(pos, dtype=wp.vec3), wp.array(quat, dtype=wp.vec4), cloud)
    kept, kept_res = first.loglik.numpy(), first.residual_m.numpy()
    copy, copy_res = kept.copy(), kept_res.copy()
    moved = pos + np.array([100.0, 50.0, 0.0])
    second = model.evaluate(wp.array(moved, dtype=wp.vec3), wp.array(quat, dtype=wp.vec4), cloud)
    assert not np.array_equal(second.loglik.numpy(), copy)  # the second call did compute something else
    np.testing.assert_array_equal(kept, copy)
    np.testing.assert_array_equal(kept_res, copy_res)


@pytest.mark.parametrize("bad, fragment", [([0.0, 0.0, 0.0, 0.0], "not a unit quaternion"),
                                           ([np.nan, 0.0, 0.0, 1.0], "not a unit quaternion"),
                                           ([2.0, 0.0, 0.0, 0.0], "not a unit quaternion")])
def test_evaluate_refuses_a_zero_or_nan_quaternion(bad, fragment):
    model, pos, quat, cloud = _model_and_poses()
    quat[3] = bad
    with pytest.raises(wt.FilterError, match=rf"quat_nb\[3\].*{fragment}"):
        model.evaluate(wp.array(pos, dtype=wp.vec3), wp.array(quat, dtype=wp.vec4), cloud)
    pos[2, 0] = np.nan
    with pytest.raises(wt.FilterError, match=r"pos_n\[2\]"):
        model.evaluate(wp.array(pos, dtype=wp.vec3), wp.array(np.tile([1.0, 0, 0, 0], (8, 1)), dtype=wp.vec4), cloud)


def _mpf(**kw):
    terrain = wt.Terrain.synthetic("flat", size_m=4000.0, spacing=100.0)
    nominal = wt.NavState([0.0, 0.0, -1000.0], [100.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    args = {"p0_pos": [20.0, 20.0, 5.0], "n_particles": 32, **kw}
    return wt.MarginalizedParticleFilter(wt.SlidingModel(terrain), nominal, "navigation", 100.0,
                                         args.pop("p0_pos"), np.full(12, 1e-3), **args)


def test_p0_pos_with_nan_and_too_few_particles():
    with pytest.raises(wt.FilterError, match=r"p0_pos must be finite, got \[20.0, nan, 5.0\]"):
        _mpf(p0_pos=[20.0, np.nan, 5.0])
    with pytest.raises(wt.FilterError, match=r"got shape \(2,\)"):
        _mpf(p0_pos=[20.0, 5.0])
    with pytest.raises(wt.FilterError, match="n_particles must be a whole number ≥ 2"):
        _mpf(n_particles=1)
    with pytest.warns(wt.FilterWarning, match="n_particles = 2: too few particles"):
        _mpf(n_particles=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error", wt.FilterWarning)
        _mpf(n_particles=32)


def test_one_particle_is_refused_before_work(capsys, tmp_path):
    status, _, err = _cli(capsys, "run", "S8", "--particles", "1", "--check")
    assert status == 2
    _error_line(err, "filter.particles = 1 must be ≥ 2")


# ------------------------------------------------------------------------------------------- scenario files
def test_nan_in_a_scenario_or_campaign_file_is_not_finite_and_names_the_file(capsys, tmp_path):
    lines = scenario_path("S8").read_text().replace("map_noise_m = 0.0", "map_noise_m = nan")
    assert "map_noise_m = nan" in lines
    (tmp_path / "s.toml").write_text(lines)
    status, _, err = _cli(capsys, "run", tmp_path / "s.toml", "--check")
    assert status == 2
    _error_line(err, "terrain.map_noise_m = nan must be a finite number", "s.toml")
    campaign = tmp_path / "mine.toml"
    campaign.write_text('scenarios = ["S8"]\nseeds = 1\n[overrides]\nmap_bias_m = nan\n')
    status, _, err = _cli(capsys, "campaign", campaign, "--check")
    assert status == 2
    line = _error_line(err, "mine.toml", "map_bias_m", "must be a finite number")
    assert "S8.toml" not in line


# ------------------------------------------------------------------------------------------- replay
def test_replay_errors_are_one_clear_line(capsys, exported, tmp_path):
    """--model altimeter on a scan log was a traceback; a zero-length log and one whose scans all lie outside the
    IMU span were "cannot reshape array of size 0"; an IMU sample of 1e30 was blamed on the INS position."""
    log_path = exported[0] / "S8_seed0.h5"
    status, _, err = _cli(capsys, "replay", log_path, "--model", "altimeter", "--out", tmp_path / "o")
    assert status == 2
    _error_line(err, "the altimeter model needs altimeter readings")
    for argv, fragment in ((["--particles", "1"], "particles must be a whole number ≥ 2"),
                           (["--bag-config", tmp_path / "absent.toml"], "--bag-config: for ROS 2 bags"),
                           (["--terrain", tmp_path / "absent.tif"], "absent.tif")):
        status, _, err = _cli(capsys, "replay", log_path, "--out", tmp_path / "o", "--quiet", *argv)
        assert status == 2
        _error_line(err, fragment)
    log = read_log(log_path)
    import dataclasses

    empty = dataclasses.replace(log, imu_t=log.imu_t[:0], imu_f=log.imu_f[:0], imu_w=log.imu_w[:0])
    with pytest.raises(LogError, match=r"imu\.t must be a non-empty"):
        empty.validate()
    late = dataclasses.replace(log, scan_t=log.scan_t + 1000.0)
    write_log(late, tmp_path / "late.h5")
    status, _, err = _cli(capsys, "replay", tmp_path / "late.h5", "--out", tmp_path / "o", "--quiet")
    assert status == 2
    _error_line(err, "lies within the IMU's time span", "nothing to navigate with")
    for value, what in ((1e30, "1e+30"), (60 * 9.80665, "588.")):
        f = log.imu_f.copy()
        f[7, 2] = value
        spiked = dataclasses.replace(log, imu_f=f)
        with pytest.raises(LogError, match=rf"imu has 1 sample\(s\) beyond the navigation grade's range.*sample 7 "
                                            rf"at t = .*{re.escape(what)}"):
            spiked.validate()
    assert not (tmp_path / "o").exists()
