"""Bad input and faults (issue 15): every case gives one clear error naming the problem before any long work (exit
2 from the CLI, no traceback), or a correct result; nothing written is lost or mixed.

CLI cases run ``warptan.cli.main`` in-process and assert the exit status, the one-line message and the state of the
output folder afterwards; one case interrupts a real ``python -m warptan`` process with SIGINT mid-run.
"""

import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine

import warptan as wt
from warptan import cli, outputs
from warptan.sim.scenario_config import ScenarioError, scenario_path
from warptan.sim.scenarios import prepare, run_scenario
from warptan.terrain.grid import Terrain, TerrainError, TerrainWarning

HEIGHTS = 200.0 + 50.0 * np.random.default_rng(0).random((40, 50))


def _tif(path, transform, crs, data=HEIGHTS, **kw):
    with rasterio.open(path, "w", driver="GTiff", width=data.shape[1], height=data.shape[0], count=1,
                       dtype="float32", crs=crs, transform=transform, **kw) as dst:
        dst.write(data.astype("float32"), 1)
    return str(path)


def _vrt(path, source, geotransform="500000, 30, 0, 5000000, 0, -30", band_attrs="", source_xml=None):
    source_xml = source_xml or (f'<SimpleSource><SourceFilename relativeToVRT="0">{source}</SourceFilename>'
                                "<SourceBand>1</SourceBand></SimpleSource>")
    Path(path).write_text(
        f'<VRTDataset rasterXSize="50" rasterYSize="40"><SRS>EPSG:32632</SRS><GeoTransform>{geotransform}'
        f'</GeoTransform><VRTRasterBand dataType="Float32" band="1" {band_attrs}>{source_xml}</VRTRasterBand>'
        "</VRTDataset>")
    return str(path)


def _run_cli(capsys, *argv):
    """(exit status, stdout, stderr) of ``warptan ARGV``; argparse errors (SystemExit) give their status."""
    try:
        status = cli.main(list(argv))
    except SystemExit as exc:
        status = exc.code
    out, err = capsys.readouterr()
    return status, out, err


def _one_error_line(err: str, *fragments):
    lines = [line for line in err.splitlines() if line.strip() and "CUDA" not in line]
    assert len(lines) == 1 and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _scenario_file(tmp_path, name="edited", base="S8", **changes):
    """A copy of a shipped scenario with ``key = value`` lines replaced (keys unique in the file)."""
    lines = scenario_path(base).read_text().splitlines()
    for key, value in changes.items():
        hits = [i for i, line in enumerate(lines) if line.split("=")[0].strip() == key]
        assert len(hits) == 1, key
        lines[hits[0]] = f"{key} = {value}"
    path = tmp_path / f"{name}.toml"
    path.write_text("\n".join(lines) + "\n")
    return str(path)


# ---------------------------------------------------------------------------------------------------- rasters
def test_south_up_and_mirrored_rasters_load_as_their_north_up_twins(tmp_path):
    """A south-up geographic GeoTIFF (it raised GDAL's "latitude max < latitude min") and an east-to-west UTM one
    (it asked for 96249×164857 posts) are flipped on reading: the same grid as the north-up file."""
    north = Terrain.load(_tif(tmp_path / "n.tif", Affine(1 / 1200, 0, 10, 0, -1 / 1200, 50), "EPSG:4326"))
    south = Terrain.load(_tif(tmp_path / "s.tif", Affine(1 / 1200, 0, 10, 0, 1 / 1200, 50 - 40 / 1200), "EPSG:4326",
                              data=HEIGHTS[::-1]))
    assert south.shape == north.shape and np.array_equal(south.heights_m, north.heights_m, equal_nan=True)
    utm = Terrain.load(_tif(tmp_path / "u.tif", Affine(30, 0, 500000, 0, -30, 5000000), "EPSG:32632"))
    mirrored = Terrain.load(_tif(tmp_path / "m.tif", Affine(-30, 0, 500000 + 50 * 30, 0, -30, 5000000), "EPSG:32632",
                                 data=HEIGHTS[:, ::-1]))
    assert mirrored.shape == utm.shape == (40, 50)
    assert np.array_equal(mirrored.heights_m, utm.heights_m) and (mirrored.n0, mirrored.e0) == (utm.n0, utm.e0)


def test_broken_georeferencing_is_refused(tmp_path):
    """Zero pixel size (it raised ZeroDivisionError), latitudes beyond the pole, a 1-pixel-wide raster."""
    good = _tif(tmp_path / "u.tif", Affine(30, 0, 500000, 0, -30, 5000000), "EPSG:32632")
    with pytest.raises(TerrainError, match="degenerate geotransform"):
        Terrain.load(_vrt(tmp_path / "zero.vrt", good, geotransform="500000, 0, 0, 5000000, 0, -30"))
    beyond = _tif(tmp_path / "pole.tif", Affine(0.5, 0, 10, 0, -0.5, 100), "EPSG:4326")
    with pytest.raises(TerrainError, match="outside the Earth"):
        Terrain.load(beyond)
    thin = _tif(tmp_path / "thin.tif", Affine(30, 0, 500000, 0, -30, 5000000), "EPSG:32632", data=HEIGHTS[:1])
    with pytest.raises(TerrainError, match="at least 2×2"):
        Terrain.load(thin)
    text = tmp_path / "notes.tif"
    text.write_text("not a raster")
    with pytest.raises(TerrainError, match=r"notes\.tif"):
        Terrain.load(str(text))


def test_vrt_raw_bands_and_network_paths_are_refused_unless_allowed(tmp_path):
    """A VRT raw band turned /etc/passwd into heights, and a VRT or a path could read a URL; a VRT mosaic of local
    files still loads."""
    good = _tif(tmp_path / "u.tif", Affine(30, 0, 500000, 0, -30, 5000000), "EPSG:32632")
    raw = _vrt(tmp_path / "raw.vrt", "", band_attrs='subClass="VRTRawRasterBand"',
               source_xml='<SourceFilename relativetoVRT="0">/etc/passwd</SourceFilename>')
    with pytest.raises(TerrainError, match=r"VRTRawRasterBand.*allow_raw_vrt"):
        Terrain.load(raw)
    nested = _vrt(tmp_path / "nested.vrt", raw)  # a VRT whose source is the raw VRT
    with pytest.raises(TerrainError, match="VRTRawRasterBand"):
        Terrain.load(nested)
    for source in ("/vsicurl/https://example.com/dem.tif", "https://example.com/dem.tif"):
        with pytest.raises(TerrainError, match=r"network.*allow_network"):
            Terrain.load(_vrt(tmp_path / "net.vrt", source))
        with pytest.raises(TerrainError, match=r"network.*allow_network"):
            Terrain.load(source)
    wms = tmp_path / "tiles.xml"  # a WMS description is a "file" GDAL fetches over the network
    wms.write_text("<GDAL_WMS><Service name=\"TMS\"><ServerUrl>https://example.com/${z}/${x}/${y}.png</ServerUrl>"
                   "</Service><DataWindow><TileLevel>3</TileLevel></DataWindow></GDAL_WMS>")
    with pytest.raises(TerrainError, match="web-service description"):
        Terrain.load(str(wms))
    mosaic = Terrain.load(_vrt(tmp_path / "mosaic.vrt", good))
    assert np.allclose(mosaic.heights_m, Terrain.load(good).heights_m)


def test_implausible_heights_become_nodata_with_a_warning(tmp_path):
    """One post of 1e30 m without a nodata tag used to load (and put the S8 flight at 1e30 m)."""
    spiked = HEIGHTS.copy()
    spiked[5, 5] = 1e30
    path = _tif(tmp_path / "spike.tif", Affine(30, 0, 500000, 0, -30, 5000000), "EPSG:32632", data=spiked)
    with pytest.warns(TerrainWarning, match=r"1 post\(s\) outside the plausible -500…9000 m"):
        t = Terrain.load(path)
    assert t.h_max < 300.0 and np.isnan(t.heights_m).sum() == 1
    with pytest.raises(TerrainError, match="every post is nodata"), warnings.catch_warnings():
        warnings.simplefilter("ignore", TerrainWarning)
        Terrain.from_grid(np.full((3, 3), 1e4), 30.0)
    sea = Terrain.from_grid(np.full((3, 3), -4000.0), 30.0, valid_range_m=(-11000.0, 9000.0))  # bathymetry
    assert sea.h_min == -4000.0
    with pytest.raises(TerrainError, match="a terrain is a name"):
        Terrain.load(42)


# ---------------------------------------------------------------------------------------------------- CLI
def test_cli_arguments_out_of_range_exit_2_before_work(capsys, tmp_path):
    """--seeds 0 ran 1 seed, --duration-s 0 ran the file's 120 s, 0.05 s ended in an IndexError."""
    out = tmp_path / "o"
    for argv, fragment in ((["--seeds", "0"], "--seeds"), (["--duration-s", "0"], "--duration-s"),
                           (["--duration-s", "nan"], "--duration-s"), (["--particles", "-3"], "--particles"),
                           (["--sim-map-noise-m", "-1"], "--sim-map-noise-m")):
        status, _, err = _run_cli(capsys, "run", "S8", "--out", str(out), *argv)
        assert status == 2 and fragment in err
    status, _, err = _run_cli(capsys, "run", "S8", "--duration-s", "0.05", "--out", str(out))
    assert status == 2
    _one_error_line(err, "duration_s = 0.05 is shorter than one measurement interval")
    assert not out.exists()


def test_cli_refuses_unusable_output_folders_before_work(capsys, tmp_path, monkeypatch):
    """An existing file, a folder of other things, and a parent where nothing can be created: refused at once
    (they were found only after the run, which was lost), and left as they were."""
    a_file = tmp_path / "taken"
    a_file.write_text("mine")
    status, _, err = _run_cli(capsys, "run", "S8", "--out", str(a_file))
    assert status == 2 and a_file.read_text() == "mine"
    _one_error_line(err, "is a file, not a folder")

    project = tmp_path / "project"
    project.mkdir()
    (project / "thesis.tex").write_text("years of work")
    status, _, err = _run_cli(capsys, "run", "S8", "--out", str(project))
    assert status == 2 and _snapshot(project) == {"thesis.tex": b"years of work"}
    _one_error_line(err, "holds files that are not a warptan run", "thesis.tex")

    def no_permission(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(outputs.tempfile, "mkdtemp", no_permission)  # a read-only parent (even for root)
    status, _, err = _run_cli(capsys, "run", "S8", "--check", "--out", str(tmp_path / "new"))
    assert status == 2
    _one_error_line(err, "cannot create a folder in", "Permission denied")


def test_cli_check_runs_the_same_validation_as_a_run(capsys, tmp_path):
    """--check passed a 100000×100000 scan (MemoryError traceback in the run), a singular N_k, and called a
    1e308 m/s flight "over nodata"."""
    cases = (
        (dict(scan_nx=100000, scan_ny=100000), "10000000000 points", "more than 65536 per scan"),
        (dict(kalman_pos_noise_m_rthz=0.0, vel_mps=0.0), "N_k singular"),
        (dict(speed_mps=1e308), "speed_mps = 1e+308 must be in (0, 1000]"),
        (dict(particles=100_000_000), "needs about"),
        (dict(pos_m="[1e39, 100.0, 20.0]"), "initial_error.pos_m", "must be in [0, 100000] m"),  # float32 overflow
    )
    for changes, *fragments in cases:
        status, out, err = _run_cli(capsys, "run", _scenario_file(tmp_path, **changes), "--check")
        assert status == 2 and "ok" not in out
        _one_error_line(err, *fragments)
    status, out, _ = _run_cli(capsys, "run", "S8", "--check", "--seeds", "3", "--out", str(tmp_path / "fine"))
    assert status == 0 and "S8: ok" in out and "3 seed(s)" in out and not (tmp_path / "fine").exists()


def test_cli_refuses_repeated_scenarios(capsys, tmp_path):
    """`warptan run S8 S8` reported "2 seeds, ±0.00"; a file with S8's id would overwrite S8's results."""
    for argv in (["S8", "S8"], ["S8", "s8"], ["S8", "all"]):
        status, _, err = _run_cli(capsys, "run", *argv, "--check")
        assert status == 2 and "Traceback" not in err
    status, _, err = _run_cli(capsys, "run", "S8", _scenario_file(tmp_path, particles=100), "--check")
    assert status == 2
    _one_error_line(err, "two scenarios have the id S8")


def test_outputs_are_strict_json_and_a_rerun_replaces_the_whole_run(capsys, tmp_path):
    """A run shorter than converged_after_s wrote bare NaN; a second run into the folder mixed with the first's
    plots; files the user put there survive a rerun."""
    out = tmp_path / "res"
    status, _, err = _run_cli(capsys, "run", "S8", "--duration-s", "0.1", "--particles", "16", "--out", str(out),
                              "--quiet")
    assert status == 0, err
    data = json.loads((out / "results.json").read_text(),
                      parse_constant=lambda c: pytest.fail(f"results.json holds {c}"))
    assert data["runs"][0]["rmse_converged_m"] == [None, None, None]  # undefined, not NaN
    assert "–" in (out / "results.md").read_text()
    first = set(_snapshot(out))
    (out / "notes.txt").write_text("my notes")
    (out / "extra").mkdir()
    (out / "extra" / "a.csv").write_text("1,2")
    status, _, err = _run_cli(capsys, "run", "S7", "--duration-s", "0.1", "--particles", "16", "--out", str(out),
                              "--quiet", "--no-plots")
    assert status == 0, err
    after = _snapshot(out)
    assert after["notes.txt"] == b"my notes" and after["extra/a.csv"] == b"1,2"
    assert not any(name.startswith("S8_") for name in after), "the first run's plots were kept"
    assert set(json.loads((out / "results.json").read_text())["scenarios"]) == {"S7"}
    assert set(json.loads(after[outputs.MANIFEST])["files"]) == {"results.json", "results.md"}
    assert any(n.startswith("S8_") for n in first)
    assert not [p for p in tmp_path.iterdir() if ".warptan-" in p.name], "temporary folders left behind"


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "two-renames"])
def test_an_interrupt_while_writing_leaves_the_previous_run(capsys, tmp_path, monkeypatch, exchange):
    """Ctrl-C after results.json is written but before the plots: the folder still holds the previous run, whole;
    then a run completes with the swap (atomic exchange, or the two-rename fallback) and replaces it."""
    from warptan.sim import report

    out = tmp_path / "res"
    args = ["run", "S8", "--duration-s", "0.1", "--particles", "16", "--out", str(out), "--quiet"]
    assert _run_cli(capsys, *args)[0] == 0
    before = _snapshot(out)

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(report, "plot_run", interrupted)
        status, _, err = _run_cli(capsys, *args, "--seeds", "2")
    assert status == 130 and "as it was before" in err
    assert _snapshot(out) == before
    assert not [p for p in tmp_path.iterdir() if ".warptan-" in p.name]
    if not exchange:
        monkeypatch.setattr(outputs, "_rename_exchange", lambda a, b: False)
    assert _run_cli(capsys, *args, "--seeds", "2", "--no-plots")[0] == 0
    assert json.loads((out / "results.json").read_text())["scenarios"]["S8"]["seeds"] == [0, 1]
    assert not [p for p in tmp_path.iterdir() if ".warptan-" in p.name]


def test_a_crash_between_the_fallback_renames_is_recovered(tmp_path):
    """The two-rename swap killed between its renames leaves the previous run as .NAME.warptan-old-*: the next
    OutputFolder on that name puts it back before anything else."""
    out = tmp_path / "res"
    with outputs.OutputFolder(out) as tmp:
        (tmp / "results.md").write_text("run 1")
    os.rename(out, tmp_path / ".res.warptan-old-deadbeef")
    outputs.OutputFolder(out)
    assert (out / "results.md").read_text() == "run 1"


@pytest.mark.parametrize("signum, status, words", [
    (signal.SIGINT, 130, b"interrupted; the output folder is as it was"),
    (signal.SIGTERM, 143, b"terminated (SIGTERM); the output folder is as it was")], ids=["SIGINT", "SIGTERM"])
def test_a_signal_mid_run_exits_and_keeps_the_old_outputs(tmp_path, signum, status, words):
    """A real interrupt (Ctrl-C) or SIGTERM of `python -m warptan run` while it runs: exit 130 / 143, one line, the
    folder unchanged, no hidden partial folder left (SIGTERM left one, never cleaned up)."""
    out = tmp_path / "res"
    out.mkdir()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    # the run's SIGINT as at a terminal: a process started with SIGINT ignored (pytest in a shell's background job)
    # keeps it ignored, as Python and every program that respects its parent's choice do
    proc = subprocess.Popen([sys.executable, "-m", "warptan", "run", "S7", "--seeds", "50", "--particles", "64",
                             "--out", str(out), "--no-plots"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env=env, cwd=tmp_path, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = b""
    deadline = time.monotonic() + 120
    while b"update" not in seen and time.monotonic() < deadline:  # the progress bar: the run is under way
        chunk = os.read(proc.stderr.fileno(), 4096)
        if not chunk:  # the process ended before its run started
            break
        seen += chunk
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == status, (seen + err).decode()[-2000:]
    assert words in err and b"Traceback" not in err
    assert list(out.iterdir()) == [] and not [p for p in tmp_path.iterdir() if ".warptan-" in p.name]


def test_other_expected_failures_are_one_line(capsys, tmp_path):
    """Missing files, unknown names and unwritable export targets: exit 2, one line."""
    cases = (
        (["terrain", "info", str(tmp_path / "absent.tif")], "DEM file not found"),
        (["terrain", "export", "synthetic:flat,size_m=2000,spacing=100", str(tmp_path / "x.xyz")],
         "unsupported mesh format"),
        (["terrain", "export", "synthetic:flat,size_m=2000,spacing=100", str(tmp_path / "no" / "x.ply")],
         "does not exist"),
        (["run", "S99", "--check"], "unknown scenario"),
        (["run", "S8", "--backend", "foo", "--check"], "sensor.backend = 'foo'"),
        (["run", "S8", "--map", str(tmp_path / "absent.tif"), "--check"], "absent.tif"),
        (["run", "S8", "--terrain", "synthetic:rugged,size_m=500", "--check"], "leaves the DEM"),
        (["run", "S8", "--out", "", "--check"], "output folder name is empty"),
        (["run", "S8", "--batch", "--seeds", "2", "--sim-map-noise-m", "1", "--check"], "own map"),
    )
    for argv, fragment in cases:
        status, _, err = _run_cli(capsys, *argv)
        assert status == 2, (argv, err)
        _one_error_line(err, fragment)


# ---------------------------------------------------------------------------------------------------- API
def test_seeds_and_terrain_arguments_are_checked():
    """seed 2**63 raised OverflowError, 1.7 silently ran seed 1, terrain=42 a bare TypeError."""
    for seed, fragment in ((1.7, "whole number"), (2**63, "must be in"), (-1, "≥ 0, got -1"), (True, "whole number")):
        with pytest.raises(ScenarioError, match=fragment):
            run_scenario("S8", seed=seed, duration_s=0.1)
    with pytest.raises(ScenarioError, match=r"terrain=42 \(int\)"):
        prepare("S8", terrain=42)
    with pytest.raises(ScenarioError, match="given more than once"):
        prepare("S8", seeds=[0, 0])
    with pytest.raises(ValueError, match="whole number"):
        wt.ImuModel("navigation", 100.0, seed=1.7)


def _filter(terrain, **kwargs):
    truth = wt.Trajectory.build([wt.Straight(2.0)], 100.0, [0.0, 0.0, -(terrain.h_max + 600.0)])
    model = wt.SlidingModel(terrain)
    mpf = wt.MarginalizedParticleFilter(model, truth.state(0), "navigation", 100.0, [20.0, 20.0, 5.0],
                                        np.full(12, 1e-3), n_particles=32, **kwargs)
    return truth, mpf


def test_implausible_imu_samples_are_refused_or_held():
    """A 1e20 m/s² sample moved the nominal by 3e18 m (at 1e300 estimate() called it a bug): refused by default;
    with bad_imu="hold" integrated as the last good sample (the same bits as feeding that sample) and counted."""
    terrain = Terrain.synthetic("rugged", size_m=20_000.0, spacing=100.0)
    truth, mpf = _filter(terrain)
    mpf.predict(truth.f_b[0], truth.w_b[0])
    for f in ([0.0, 0.0, 1e20], [0.0, 0.0, 1e300], [np.nan, 0.0, 0.0]):
        with pytest.raises(ValueError, match="IMU sample 1: specific force"):
            mpf.predict(f, truth.w_b[1])
    with pytest.raises(ValueError, match="body rate"):
        mpf.predict(truth.f_b[1], [0.0, 25.0, 0.0])
    _, held = _filter(terrain, bad_imu="hold")
    _, ref = _filter(terrain)
    for i in range(10):
        f, w = truth.f_b[i], truth.w_b[i]
        ref.predict(truth.f_b[i - 1] if i in (4, 5) else f, truth.w_b[i - 1] if i in (4, 5) else w)
        if i == 4:
            f = [0.0, 0.0, 1e20]
        if i == 5:
            w = [np.nan, 0.0, 0.0]
        held.predict(f, w)
    ref.flush()
    held.flush()
    assert held.n_imu_held.tolist() == [2]
    assert np.array_equal(held.nominal().pos_n, ref.nominal().pos_n)
    assert np.isfinite(held.estimate().nav.pos_n).all()
    _, first_bad = _filter(terrain, bad_imu="hold")
    with pytest.raises(ValueError, match="non-finite IMU sample 0"):
        first_bad.predict([np.nan, 0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="bad_imu"):
        _filter(terrain, bad_imu="skip")
    with pytest.raises(ValueError, match="seed"):
        _filter(terrain, seed=1.7)


def test_inputs_beyond_float32_are_refused_not_nan():
    """A ray origin at z = -1e39 (finite in float64, inf in float32) returned NaN silently."""
    terrain = Terrain.synthetic("rugged", size_m=20_000.0, spacing=100.0)
    with pytest.raises(ValueError, match="float32"):
        wt.raycast(terrain, np.array([[0.0, 0.0, -1e39]]), np.array([[0.0, 0.0, 1.0]]))
    assert np.isfinite(wt.raycast(terrain, np.array([[0.0, 0.0, -3000.0]]), np.array([[0.0, 0.0, 1.0]]))).all()
    with pytest.raises(ValueError, match="NED origin"):
        wt.NavState([0.0, 0.0, -1e39], [100.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    nominal = wt.NavState([0.0, 0.0, -1000.0], [100.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="float32"):
        wt.MarginalizedParticleFilter(wt.SlidingModel(terrain), nominal, "navigation", 100.0, [1e39, 1.0, 1.0],
                                      np.full(12, 1e-3), n_particles=8)
    cloud = wt.PointCloud(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]), np.array([1e39, 500.0]))
    assert cloud.valid.tolist() == [False, True]
    assert not wt.AltimeterReading(1e39, 100.0).valid
    with pytest.raises(ValueError, match="not an altitude"):
        wt.AltimeterReading(500.0, 1e39)


def test_each_layer_raises_its_own_error_type(tmp_path):
    """FilterError (navigation layer), TerrainError, ScenarioError, OutputError: all ValueErrors (the CLI's exit 2),
    each caught by its own type."""
    terrain = Terrain.synthetic("flat", size_m=2000.0, spacing=100.0)
    _, mpf = _filter(terrain)
    with pytest.raises(wt.FilterError):
        mpf.predict([0.0, 0.0, 1e20], [0.0, 0.0, 0.0])
    with pytest.raises(wt.FilterError):
        wt.ScanPattern.grid(0, 3)
    with pytest.raises(wt.TerrainError):
        Terrain.synthetic("mars")
    with pytest.raises(wt.ScenarioError):
        prepare("S8", seeds=[1.5])
    (tmp_path / "f").write_text("")
    with pytest.raises(wt.OutputError):
        outputs.OutputFolder(tmp_path / "f")
    assert all(issubclass(e, ValueError) for e in (wt.FilterError, wt.TerrainError, wt.ScenarioError, wt.OutputError))
