"""Nothing lost, round two (issue 66): the bad cases of a 380-case hostile probe. Folders without a manifest are
someone else's, an input is never an output, a full disk is one line, a metre is a metre, and sizes are checked
before work. Each test failed on the code before the fix.

CLI cases run ``warptan.cli.main`` in-process (exit status, the one-line message, the files afterwards); the
full-disk cases run real ``python -m warptan`` processes under ``ulimit -f``.
"""

import json
import os
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_nothing_lost import QUICK, RUGGED_TIF, _cli, _error_line, _snapshot

from warptan import cli, outputs

RUN_RESULTS = json.dumps({"meta": {"git_commit": "x"}, "scenarios": ["S8"], "runs": []})


# ------------------------------------------------------------------------------------------- user files
@pytest.mark.parametrize("files", [
    {"results.json": RUN_RESULTS, "results.md": "# my results", "vacation_seed2_beach.png": "a photo"},
    {"results.json": RUN_RESULTS, "README": "my analysis", "S8_seed0_track_annotated.png": "annotated",
     "compare_seed0_vs_seed1.png": "mine"},
], ids=["legacy-looking", "analysis-folder"])
def test_a_folder_without_a_manifest_is_someone_elses(capsys, tmp_path, files):
    """A folder holding a results.json but no manifest: its ``*_seed*_*.png`` were deleted and its results.json
    overwritten (exit 0). It is refused before any work, and nothing in it changes."""
    out = tmp_path / "legacy"
    out.mkdir()
    for name, text in files.items():
        (out / name).write_text(text)
    before = _snapshot(out)
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--out", out)
    assert status == 2
    _error_line(err, str(out), "no .warptan-run manifest", "nothing there is replaced")
    assert _snapshot(out) == before
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--out", out, "--check")
    assert status == 2 and "no .warptan-run manifest" in err
    assert _snapshot(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["legacy"]


# ------------------------------------------------------------------------------------------- inputs are not outputs
def _previous_output(path: Path, kind: str) -> Path:
    """A folder a previous warptan output of ``kind`` wrote (its manifest, one file)."""
    with outputs.OutputFolder(path, kind=kind) as tmp:
        (tmp / "results.json").write_text("{}")
    return path


@pytest.mark.parametrize("outs", [["dem.tif"], ["info.png", "dem.tif"], ["link.tif"]],
                         ids=["the-input", "second-out", "a-link-to-it"])
def test_overwrite_never_replaces_an_input(capsys, tmp_path, outs):
    """`terrain info dem.tif --information --out dem.tif --overwrite` replaced the input DEM with the information
    map (also as a second --out). --overwrite never applies to an input, whatever name reaches it."""
    dem = tmp_path / "dem.tif"
    dem.write_bytes(Path(RUGGED_TIF).read_bytes())
    (tmp_path / "link.tif").symlink_to(dem)
    before = dem.read_bytes()
    argv = ["terrain", "info", dem, "--information", "--scans", "1", "--stride", "40", "--overwrite"]
    for out in outs:
        argv += ["--out", tmp_path / out]
    status, _, err = _cli(capsys, *argv)
    assert status == 2
    _error_line(err, "is the input", "--overwrite never replaces an input")
    assert dem.read_bytes() == before and not (tmp_path / "info.png").exists()


def test_one_file_named_twice_by_out_is_refused(capsys, tmp_path):
    """Two --out of one file wrote it twice (the second over the first)."""
    dem = tmp_path / "dem.tif"
    dem.write_bytes(Path(RUGGED_TIF).read_bytes())
    status, _, err = _cli(capsys, "terrain", "info", dem, "--information", "--scans", "1", "--stride", "40",
                          "--out", tmp_path / "a.png", "--out", tmp_path / "a.png")
    assert status == 2
    _error_line(err, "names one file twice")
    assert not (tmp_path / "a.png").exists()


def test_inputs_hidden_behind_a_spec_are_still_inputs(capsys, tmp_path, monkeypatch):
    """A DEM given as `FILE#band=1`, a named terrain read from WARPTAN_DEM_DIR and a DEM named by a campaign's
    scenario file were not seen as inputs: an --out holding them was accepted."""
    out = _previous_output(tmp_path / "rA", "run")  # the user's DEM put in it
    dem = out / "mydem.tif"
    dem.write_bytes(Path(RUGGED_TIF).read_bytes())
    before = _snapshot(out)
    for command in (["run", "S8", *QUICK, "--terrain", f"{dem}#band=1", "--out", out],
                    ["run", "S8", *QUICK, "--terrain", f"{dem}#band=1", "--out", out, "--check"]):
        status, _, err = _cli(capsys, *command)
        assert status == 2
        _error_line(err, f"{out} contains the input {dem}")
    out = _previous_output(tmp_path / "cA", "campaign")
    dem = out / "mydem.tif"
    dem.write_bytes(Path(RUGGED_TIF).read_bytes())
    (tmp_path / "c.toml").write_text(f'scenarios = ["S8"]\nseeds = 1\n[overrides]\nduration_s = 0.5\n'
                                     f'particles = 16\nterrain = "{dem}#band=1"\n')
    status, _, err = _cli(capsys, "campaign", tmp_path / "c.toml", "--out", out, "--check")
    assert status == 2 and f"{out} contains the input {dem}" in err
    scenario = Path(__file__).resolve().parents[1] / "warptan" / "scenario_files" / "S8.toml"
    (tmp_path / "mine.toml").write_text(scenario.read_text().replace('id = "S8"', 'id = "MINE"').replace(
        'kind = "rugged"', 'kind = "path"').replace('path = ""', f'path = "{dem}"', 1))
    (tmp_path / "d.toml").write_text('scenarios = ["mine.toml"]\nseeds = 1\n[overrides]\nduration_s = 0.5\n'
                                     'particles = 16\n')
    status, _, err = _cli(capsys, "campaign", tmp_path / "d.toml", "--out", out, "--check")
    assert status == 2 and f"{out} contains the input {dem}" in err
    out = _previous_output(tmp_path / "rB", "run")
    before = _snapshot(out)
    (out / "thuringia_hilly_srtm3_crop44km.tif").write_bytes(dem.read_bytes())
    monkeypatch.setenv("WARPTAN_DEM_DIR", str(out))
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--out", out, "--check")
    assert status == 2
    _error_line(err, f"{out} contains the input {out / 'thuringia_hilly_srtm3_crop44km.tif'}")
    assert _snapshot(out) == {**before, "thuringia_hilly_srtm3_crop44km.tif": dem.read_bytes()}


# ------------------------------------------------------------------------------------------- a full disk
def _fsize_limit(limit):
    def apply():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return apply


def _warptan(cwd, *argv, limit=None):
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    return subprocess.run([sys.executable, "-m", "warptan", *map(str, argv)], capture_output=True, text=True,
                          timeout=300, cwd=cwd, env=env, preexec_fn=None if limit is None else _fsize_limit(limit))


def test_flight_logs_on_a_full_disk_are_one_line_and_leave_nothing(tmp_path):
    """`run --export-log` and `log import --out x.h5` under `ulimit -f` (a full disk's stand-in): dozens of h5py
    "Exception ignored" tracebacks, then a segmentation fault (rc 139), nothing written. Now one line naming the
    file, the previous outputs as they were and no partial file."""
    logs, res = tmp_path / "L", tmp_path / "R"
    first = _warptan(tmp_path, "run", "S8", *QUICK, "--export-log", logs, "--out", res)
    assert first.returncode == 0, first.stderr
    before = {folder: _snapshot(folder) for folder in (logs, res)}
    proc = _warptan(tmp_path, "run", "S8", *QUICK, "--seeds", "2", "--export-log", logs, "--out", res, limit=20000)
    assert proc.returncode == 2, proc.stderr[-2000:]
    _error_line(proc.stderr, f"writing {logs / 'S8_seed0.h5'} failed", "File too large", "disk is full",
                f"{logs} is as it was before this run")
    assert {folder: _snapshot(folder) for folder in (logs, res)} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["L", "R"]
    from warptan.io.flightlog import read_log
    from warptan.io.logcsv import write_tables

    layout = write_tables(read_log(logs / "S8_seed0.h5"), tmp_path / "tables")
    proc = _warptan(tmp_path, "log", "import", layout, "--out", tmp_path / "x.h5", limit=20000)
    assert proc.returncode == 2, proc.stderr[-2000:]
    _error_line(proc.stderr, f"--out {tmp_path / 'x.h5'}", "writing it failed: File too large", "nothing was written")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["L", "R", "tables"]


def test_a_full_disk_at_the_manifest_names_the_folder(tmp_path, monkeypatch):
    """The manifest's write was outside the write-failure handler: a raw "[Errno 28]" naming no file."""
    import errno

    out = _previous_output(tmp_path / "res", "run")
    before = _snapshot(out)
    plain = Path.write_text

    def full(self, *args, **kwargs):
        if self.name == outputs.MANIFEST:
            raise OSError(errno.ENOSPC, "No space left on device")
        return plain(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full)
    with pytest.raises(outputs.OutputError, match=rf"writing {out} failed: No space left on device \(the disk is "
                                                  rf"full or a file size limit was reached\); {out} is as it was"):
        with outputs.OutputFolder(out) as tmp:
            plain(tmp / "results.json", "new")
    assert _snapshot(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["res"]


# ------------------------------------------------------------------------------------------- a metre is a metre
def _write_dem(path, heights, crs, transform, units=None):
    import rasterio

    with rasterio.open(path, "w", driver="GTiff", width=heights.shape[1], height=heights.shape[0], count=1,
                       dtype="float32", crs=crs, transform=transform) as dst:
        dst.write(heights.astype(np.float32), 1)
        if units is not None:
            dst.set_band_unit(1, units)
    return path


def _hills(rows, cols):
    r, c = np.mgrid[0:rows, 0:cols]
    return 300.0 + 40.0 * np.sin(r / 7.0) * np.cos(c / 9.0) + 0.5 * r


def test_a_web_mercator_dem_is_put_on_metres_of_ground(tmp_path):
    """A DEM in EPSG:3857 (Web Mercator: 1.56 of its units per metre of ground at 50°N) was taken as a metric grid:
    a replay 1 km wrong at 0-4 % coverage, exit 0. Its posts are now reprojected onto a metric frame: the grid spans
    the ground it covers."""
    from rasterio.transform import from_origin

    import warptan as wt

    lat0, lon0, radius, pixel = 50.0, 10.0, 6378137.0, 90.0
    x0 = radius * np.radians(lon0)
    y0 = radius * np.log(np.tan(np.pi / 4 + np.radians(lat0) / 2))
    rows = cols = 80
    path = _write_dem(tmp_path / "merc.tif", _hills(rows, cols), "EPSG:3857", from_origin(x0, y0, pixel, pixel))
    terrain = wt.Terrain.load(str(path))
    lat_south = np.degrees(2 * np.arctan(np.exp((y0 - rows * pixel) / radius)) - np.pi / 2)
    ground_ns = np.radians(lat0 - lat_south) * 6371000.0  # (a sphere: within 0.5 % at this size)
    span = terrain.dn * (terrain.shape[0] - 1)
    assert abs(span / ground_ns - 1.0) < 0.03, (span, ground_ns)  # it was 1.56
    assert "reprojected" in terrain.description
    utm = _write_dem(tmp_path / "utm.tif", _hills(rows, cols), "EPSG:32632", from_origin(600000, 5540000, 90, 90))
    assert wt.Terrain.load(str(utm)).description.endswith("native posts")  # UTM in its zone keeps its posts


def test_heights_in_feet_are_metres_when_the_raster_says_feet_and_refused_when_it_says_nothing(tmp_path):
    """A DEM in US feet (CRS and heights): the heights were read as metres (the track 507 m below the surface, exit
    0). The unit its vertical CRS or band states converts them; a DEM in feet that states no height unit is refused."""
    from rasterio.transform import from_origin

    import warptan as wt

    feet = _hills(60, 60) * 3.28
    transform = from_origin(6_000_000, 2_100_000, 300, 300)
    us_foot = 1200.0 / 3937.0
    for name, crs, units in (("compound", "EPSG:2227+6360", None), ("tagged", "EPSG:2227", "ft")):
        terrain = wt.Terrain.load(str(_write_dem(tmp_path / f"{name}.tif", feet, crs, transform, units)))
        factor = us_foot if name == "compound" else 0.3048
        assert np.nanmean(terrain.heights_m) == pytest.approx(feet.mean() * factor, rel=0.01), name
    untagged = _write_dem(tmp_path / "untagged.tif", feet, "EPSG:2227", transform)
    with pytest.raises(wt.TerrainError, match=r"untagged\.tif: its CRS is in US survey foot and its heights' unit "
                                              r"is not stated"):
        wt.Terrain.load(str(untagged))
    weird = _write_dem(tmp_path / "fathoms.tif", feet, "EPSG:32632", from_origin(600000, 5540000, 90, 90), "fathom")
    with pytest.raises(wt.TerrainError, match=r"heights in 'fathom'"):
        wt.Terrain.load(str(weird))


# ------------------------------------------------------------------------------------------- sizes before work
def test_sizes_a_user_gives_are_checked_before_work(capsys, tmp_path):
    """`terrain info --information --scans 1000000000` grew past 10 GB; a scenario with scan_nx = 100000 passed
    --check and a 0.3 s flight was not done after 120 s; an .npz of 81 M posts (945 kB) was loaded whole (5.4 GB).
    Each is one line at once; --check states what a run holds and evaluates."""
    import time
    import zipfile

    t0 = time.monotonic()
    status, _, err = _cli(capsys, "terrain", "info", "rugged", "--information", "--scans", "1000000000")
    assert status == 2 and time.monotonic() - t0 < 30
    _error_line(err, "n_scans = 1000000000", "at most 10000")
    scenario = Path(__file__).resolve().parents[1] / "warptan" / "scenario_files" / "S8.toml"
    big = tmp_path / "big.toml"
    big.write_text(scenario.read_text().replace("scan_nx = 10", "scan_nx = 100000", 1))
    assert "scan_nx = 100000" in big.read_text()
    status, _, err = _cli(capsys, "run", big, "--duration-s", "0.3", "--check", "--out", tmp_path / "o")
    assert status == 2
    _error_line(err, "100000×10 = 1000000 points", "more than 65536 per scan")
    npz = tmp_path / "big.npz"  # the header of 9000 × 9000 float32 heights (the data need not be there: it is not read)
    header = {"descr": "<f4", "fortran_order": False, "shape": (9000, 9000)}
    with zipfile.ZipFile(npz, "w") as archive, archive.open("heights_m.npy", "w") as f:
        np.lib.format.write_array_header_1_0(f, header)
    status, _, err = _cli(capsys, "terrain", "export", npz, tmp_path / "big2.stl")
    assert status == 2
    _error_line(err, "(9000, 9000) (81000000 posts", "crop or coarsen it first")
    assert not (tmp_path / "big2.stl").exists()
    status, out, err = _cli(capsys, "run", "S8", "--check", "--out", tmp_path / "o")
    assert status == 0, err
    assert "1200 updates × 500 particles × 100 point(s), about" in out and "of host memory" in out


# ------------------------------------------------------------------------------------------- unclear: one clear line
def test_output_folders_that_cannot_be_one_are_refused_before_work(capsys, tmp_path, monkeypatch):
    """A 300-character --out (a raw "[Errno 36]"), an --out symlink loop (refused only after the run), a mount
    point (the run computed, then a raw "[Errno 16]"): one line before any work."""
    long = tmp_path / ("a" * 300)
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--check", "--out", long)
    assert status == 2
    _error_line(err, "the folder name is 300 bytes long; at most 200")
    (tmp_path / "loop1").symlink_to(tmp_path / "loop2")
    (tmp_path / "loop2").symlink_to(tmp_path / "loop1")
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--check", "--out", tmp_path / "loop1")
    assert status == 2
    _error_line(err, "is a symbolic link that leads nowhere")
    mounted = tmp_path / "mnt"
    mounted.mkdir()
    monkeypatch.setattr(outputs.os.path, "ismount", lambda p: os.fspath(p) == str(mounted))
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--check", "--out", mounted)
    assert status == 2
    _error_line(err, "is a mount point", "choose a folder inside it")


def test_a_replaced_folder_keeps_its_mode(tmp_path):
    """A chmod 555 output folder, replaced by a rerun, came back 0755."""
    out = _previous_output(tmp_path / "res", "run")
    os.chmod(out, 0o555)
    try:
        with outputs.OutputFolder(out) as tmp:
            (tmp / "results.json").write_text("2")
        assert oct(os.stat(out).st_mode & 0o777) == oct(0o555) and (out / "results.json").read_text() == "2"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]
    finally:
        os.chmod(out, 0o755)


@pytest.mark.parametrize("spec, fragment", [
    ("synthetic:rugged,seed=-1", "option seed must be a whole number ≥ 0, got -1"),
    ("synthetic:rugged,size_m=0", "option size_m must be a positive"),
    ("synthetic:flat,spacing=nan", "option spacing must be a positive"),
])
def test_a_synthetic_spec_names_its_bad_option(capsys, spec, fragment):
    """`synthetic:rugged,seed=-1` said "expected non-negative integer", naming nothing."""
    status, _, err = _cli(capsys, "terrain", "info", spec)
    assert status == 2
    _error_line(err, spec, fragment)


@pytest.mark.parametrize("argv, fragments", [
    (["run", "S8", "--map-error-corr-m", "1000"], ["--map-error-corr-m 1000", "give --map-error-m too"]),
    (["run", "S8", "--world-clutter-fraction", "0.2"], ["clutter needs a height and a fraction", "give both"]),
    (["run", "S8", "--world-clutter-m", "8"], ["clutter needs a height and a fraction"]),
    (["run", "S8", "--world-refine", "2"], ["--world-refine 2 refines a world", "this one is the map"]),
    (["run", "S8", "--world-bias-m", "inf"], ["must be a finite number, got 'inf'"]),
    (["terrain", "info", "rugged", "--information", "--heading-deg", "1e300"], ["within ±360, got '1e300'"]),
    (["terrain", "info", "rugged", "--information", "--stride", "1000000"], ["stride = 1000000 leaves fewer than 2×2"]),
], ids=["corr-alone", "clutter-fraction-alone", "clutter-height-alone", "refine-alone", "inf", "heading", "stride"])
def test_cli_values_that_would_do_nothing_or_nonsense_are_one_line(capsys, tmp_path, argv, fragments):
    """Options that silently did nothing (a correlation length without an RMS, clutter or refinement alone), a
    heading of 1e300° taken, a stride past the grid reported as "no fix", "must be a finite number ≥ -inf"."""
    extra = ["--check", "--out", tmp_path / "o"] if argv[0] == "run" else []
    status, _, err = _cli(capsys, *argv, *extra)
    assert status == 2
    if err.startswith("usage:"):  # (argparse: its usage, then the one error line)
        err = err.strip().splitlines()[-1]
    _error_line(err, *fragments)


@pytest.fixture(scope="module")
def a_log(tmp_path_factory):
    base = tmp_path_factory.mktemp("alog")
    assert cli.main(["run", "S8", *QUICK, "--export-log", str(base / "L"), "--out", str(base / "R")]) == 0
    return base / "L" / "S8_seed0.h5"


@pytest.mark.parametrize("argv, fragment", [
    (["--backend", "warp9"], "unknown backend 'warp9'"),
    (["--likelihood", "gausian"], "unknown likelihood 'gausian'"),
    (["--particles", "1000000000"], "1000000000 particles × 100 point(s) need about"),
], ids=["backend", "likelihood", "particles"])
def test_replay_values_are_checked_before_work(capsys, a_log, tmp_path, argv, fragment):
    """`replay --backend warp9` was accepted (the sliding model never reads it); `--particles 1000000000` was a raw
    allocation traceback (a run checks its memory first)."""
    status, _, err = _cli(capsys, "replay", a_log, *argv, "--out", tmp_path / "o")
    assert status == 2
    if err.startswith("usage:"):
        err = err.strip().splitlines()[-1]
    _error_line(err, fragment)
    assert not (tmp_path / "o").exists()


def test_a_scenario_files_relative_dem_is_relative_to_the_file(capsys, tmp_path, monkeypatch):
    """A relative `[terrain] path` in a scenario file resolved against the current folder: run from elsewhere, it
    read another file of that name (or none)."""
    scenario = Path(__file__).resolve().parents[1] / "warptan" / "scenario_files" / "S8.toml"
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "dem.tif").write_bytes(Path(RUGGED_TIF).read_bytes())
    (mine / "S8b.toml").write_text(scenario.read_text().replace('id = "S8"', 'id = "S8B"').replace(
        'kind = "rugged"', 'kind = "path"').replace('path = ""', 'path = "dem.tif"', 1))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "dem.tif").write_bytes(b"not the DEM the scenario means")
    monkeypatch.chdir(elsewhere)
    status, out, err = _cli(capsys, "run", mine / "S8b.toml", *QUICK, "--check", "--out", tmp_path / "o")
    assert status == 0, err
    assert "S8B: ok" in out


# ------------------------------------------------------------------------------------------- CSV tables and logs
def _edit_tables(folder: Path, how: str) -> None:
    """One hostile edit of the tables `write_tables` wrote in ``folder``."""
    def rows(name):
        return (folder / name).read_text().splitlines()

    def put(name, lines):
        (folder / name).write_text("\n".join(lines) + "\n")

    layout = rows("layout.toml")
    if how == "bom":
        (folder / "imu.csv").write_text("\ufeff" + (folder / "imu.csv").read_text())
    elif how == "misspelt-key":
        at = layout.index("[imu]") + 1
        put("layout.toml", [*layout[:at], 'unit = {t = "ms"}', *layout[at:]])
    elif how in ("gps-jump", "gps-radians"):
        lines = rows("gps.csv")
        for k in range(1, len(lines)):
            cells = lines[k].split(",")
            if how == "gps-radians":
                cells[1], cells[2] = (repr(float(np.radians(float(v)))) for v in cells[1:3])
            elif k == 40:
                cells[1] = repr(float(cells[1]) + 1.0)  # 111 km north in 0.01 s
            lines[k] = ",".join(cells)
        put("gps.csv", lines)
    elif how == "scans-after-imu":
        lines = rows("scans.csv")
        put("scans.csv", [lines[0]] + [",".join([repr(float(r.split(",")[0]) + 1000.0), *r.split(",")[1:]])
                                       for r in lines[1:]])
    elif how == "rate":
        put("layout.toml", [("imu_rate_hz = 1e12" if ln.startswith("imu_rate_hz") else ln) for ln in layout])
    elif how == "fifty":
        put("layout.toml", [('roll_deg = "fifty"' if ln.startswith("roll_deg") else ln) for ln in layout])
    elif how == "settings":
        put("layout.toml", [("settings_json = \"[1, 2]\"" if ln.startswith("settings_json") else ln)
                            for ln in layout])


@pytest.mark.parametrize("how, fragment", [
    ("misspelt-key", "[imu] unknown key(s) unit (keys: file, columns, units)"),
    ("gps-jump", "[gps] a jump of 111 km in 0.01 s"),
    ("gps-radians", "km from the first GPS fix"),
    ("scans-after-imu", "[scans] 500 of its 500 rows lie outside the IMU's time span"),
    ("rate", "imu.rate_hz = 1e+12 Hz, but the samples are 100 Hz apart"),
    ("fifty", "[initial] roll_deg = 'fifty' is not a number"),
    ("settings", "settings_json must be a JSON object"),
])
def test_hostile_tables_are_one_clear_line(a_log, tmp_path, how, fragment):
    """A misspelt `unit =` ignored (the default unit read), GPS jumps of 111 km taken as the filter's error, GPS in
    radians labelled degrees imported 5 500 km from [initial], scans 1 000 s after the IMU imported, an IMU rate of
    1e12 Hz over 100 Hz samples, 'could not convert string to float' naming nothing, settings_json unchecked."""
    from warptan.io.flightlog import LogError, read_log
    from warptan.io.logcsv import read_tables, write_tables

    layout = write_tables(read_log(a_log), tmp_path / "tables")
    _edit_tables(tmp_path / "tables", how)
    with pytest.raises(LogError) as err:
        read_tables(layout)
    assert fragment in str(err.value)


def test_a_byte_order_mark_is_not_part_of_the_first_column(a_log, tmp_path):
    """A spreadsheet's UTF-8 BOM made the header's first column '\\ufefft': "missing column 't'"."""
    from warptan.io.flightlog import read_log
    from warptan.io.logcsv import read_tables, write_tables

    log = read_log(a_log)
    layout = write_tables(log, tmp_path / "tables")
    _edit_tables(tmp_path / "tables", "bom")
    np.testing.assert_array_equal(read_tables(layout).imu_f, log.imu_f)


def test_a_run_that_used_fewer_than_half_its_updates_is_an_error_unless_gaps_are_allowed(capsys, monkeypatch):
    """A DEM with data only on a strip under the track: 199 of 200 updates skipped, exit 0 with a note."""
    from types import SimpleNamespace

    from warptan.cli import commands
    from warptan.sim import report

    monkeypatch.setattr(report, "update_counts", lambda run: (200, 199, 1))
    runs = [SimpleNamespace(run=None, scenario="S8", seed=0)]
    assert commands._report_skipped(runs) == 1
    _error_line(capsys.readouterr().err, "S8 seed 0 (199 of 200): most updates were not used", "--allow-gaps")
    assert commands._report_skipped(runs, allow_gaps=True) == 0
    assert "199 of 200 updates were not used" in capsys.readouterr().out


def test_log_export_is_whole_or_nothing_and_names_its_problem(capsys, a_log, tmp_path):
    """`log export --out` onto a file: a raw "[Errno 20]"; under `ulimit -f`: a raw "[Errno 27]", a truncated
    scans.csv and no layout.toml."""
    (tmp_path / "afile").write_text("mine")
    status, _, err = _cli(capsys, "log", "export", a_log, "--out", tmp_path / "afile")
    assert status == 2
    _error_line(err, "afile", "is a file")
    assert (tmp_path / "afile").read_text() == "mine"
    proc = _warptan(tmp_path, "log", "export", a_log, "--out", tmp_path / "tables", limit=20000)
    assert proc.returncode == 2, proc.stderr[-2000:]
    _error_line(proc.stderr, f"--out {tmp_path / 'tables'}", "failed: File too large", "nothing was written")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_two_writers_of_one_log_never_replace_each_other(a_log, tmp_path):
    """Two `log import --out x.h5` at once: both failed raw, and the loser's clean-up deleted the winner's partial
    file. Each writer has its own partial file; an exclusive write never replaces what another wrote."""
    from warptan.io.flightlog import read_log, write_log

    log = read_log(a_log)
    target = tmp_path / "x.h5"
    target.write_bytes(b"the winner's log")
    with pytest.raises(FileExistsError):
        write_log(log, target, exclusive=True)
    assert target.read_bytes() == b"the winner's log" and sorted(p.name for p in tmp_path.iterdir()) == ["x.h5"]
    write_log(log, tmp_path / "y.h5", exclusive=True)
    assert read_log(tmp_path / "y.h5").imu_f.shape == log.imu_f.shape


def test_a_log_declaring_more_samples_than_memory_is_refused_before_reading(a_log, tmp_path):
    """A 175 kB log whose IMU datasets declare 400 M samples was read whole (6.8 GB) before the refusal."""
    import shutil

    import h5py

    from warptan.checks import host_memory_available
    from warptan.io.flightlog import LogError, read_log

    big = tmp_path / "big.h5"
    shutil.copy(a_log, big)
    samples = int(host_memory_available() / 8 / 3)  # (three columns: the memory it has, declared, never written)
    with h5py.File(big, "r+") as f:
        del f["imu"]["f_b"]
        f["imu"].create_dataset("f_b", shape=(samples, 3), dtype="f8", chunks=(65536, 3), compression="gzip")
    assert big.stat().st_size < 5_000_000
    with pytest.raises(LogError, match=r"its datasets declare .* GB of samples but .* GB of memory is available"):
        read_log(big)


def test_a_campaigns_band_path_is_relative_to_the_campaign_file(tmp_path, monkeypatch):
    """`terrain = "dem.tif#band=1"` in a campaign was not made relative to the campaign file (a plain path was)."""
    from warptan.sim.campaign import Campaign

    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "dem.tif").write_bytes(Path(RUGGED_TIF).read_bytes())
    (tmp_path / "c" / "c.toml").write_text('scenarios = ["S8"]\nseeds = 1\n[overrides]\nterrain = "dem.tif#band=1"\n')
    monkeypatch.chdir(tmp_path)
    campaign = Campaign.load(tmp_path / "c" / "c.toml")
    assert campaign.overrides["terrain"] == f"{(tmp_path / 'c' / 'dem.tif').resolve()}#band=1"


def test_a_log_names_its_dem_by_absolute_path_and_checksum(capsys, tmp_path, monkeypatch):
    """A log stored its DEM as the relative path it was given: replayed from another folder it silently read another
    file of that name. It now stores the absolute path and the file's SHA-256, and a replay checks it."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "a" / "dem.tif").write_bytes(Path(RUGGED_TIF).read_bytes())
    (tmp_path / "b" / "dem.tif").write_bytes(b"another file of that name")
    monkeypatch.chdir(tmp_path / "a")
    status, _, err = _cli(capsys, "run", "S8", *QUICK, "--terrain", "dem.tif", "--export-log", "L", "--out", "R")
    assert status == 0, err
    log = tmp_path / "a" / "L" / "S8_seed0.h5"
    monkeypatch.chdir(tmp_path / "b")
    status, _, err = _cli(capsys, "replay", log, "--quiet", "--no-plots", "--out", tmp_path / "b" / "o")
    assert status == 0, err
    data = bytearray(Path(RUGGED_TIF).read_bytes())
    data[len(data) // 2] ^= 1  # the DEM changed since the flight
    (tmp_path / "a" / "dem.tif").write_bytes(bytes(data))
    status, _, err = _cli(capsys, "replay", log, "--quiet", "--no-plots", "--out", tmp_path / "b" / "o2")
    assert status == 2
    _error_line(err, f"the DEM file {tmp_path / 'a' / 'dem.tif'} it names is not the one it was recorded over")


def test_a_geographic_giant_is_refused_before_reading_and_a_headless_tiff_is_called_damaged(tmp_path):
    """A sparse geographic GeoTIFF of 144 M posts was read whole (3.2 GB, 16 s) before a refusal saying "spacing
    None m"; a GeoTIFF cut in half whose header was at its end was "not a raster"."""
    import time

    import rasterio
    from rasterio.transform import Affine

    import warptan as wt

    path = tmp_path / "sparse_geo.tif"
    with rasterio.open(path, "w", driver="GTiff", width=12000, height=12000, count=1, dtype="float32",
                       crs="EPSG:4326", transform=Affine(1 / 1200, 0, 10.0, 0, -1 / 1200, 51.0), tiled=True,
                       SPARSE_OK=True) as dst:
        dst.write(np.ones((256, 256), "float32"), 1, window=rasterio.windows.Window(0, 0, 256, 256))
    t0 = time.monotonic()
    with pytest.raises(wt.TerrainError, match=r"144000000 posts \(limit 60000000 at native resolution\)"):
        wt.Terrain.load(str(path))
    assert time.monotonic() - t0 < 10
    data = Path(RUGGED_TIF).read_bytes()
    cut = tmp_path / "cut.tif"
    cut.write_bytes(data[:8] + b"\0" * 8)  # the TIFF magic, its first directory's offset past the end
    with pytest.raises(wt.TerrainError, match=r"cut\.tif: a TIFF file GDAL cannot open: truncated or damaged"):
        wt.Terrain.load(str(cut))


@pytest.mark.parametrize("line, fragment", [
    ("vel_ned = [1.0, 2.0]", "[initial] vel_ned = [1.0, 2.0] must be a list of 3 finite numbers"),
    ('mount_quat_bs = "x"', "mount_quat_bs = 'x' must be a list of 4 finite numbers"),
])
def test_a_layouts_vectors_are_named_when_wrong(a_log, tmp_path, line, fragment):
    """"cannot reshape array of size 2 into shape (3)" and "could not convert string to float: 'x'" named nothing."""
    from warptan.io.flightlog import LogError, read_log
    from warptan.io.logcsv import read_tables, write_tables

    layout = write_tables(read_log(a_log), tmp_path / "tables")
    key = line.split(" =")[0]
    layout.write_text("\n".join(line if ln.startswith(f"{key} =") else ln
                                for ln in layout.read_text().splitlines()) + "\n")
    with pytest.raises(LogError) as err:
        read_tables(layout)
    assert fragment in str(err.value)


@pytest.mark.parametrize("edit, fragment", [
    (lambda s: s["likelihood"].update(bogus=1), "settings.likelihood: unknown key 'bogus'"),
    (lambda s: s.update(likelihood=[1, 2]), "settings.likelihood must be a JSON object, got [1, 2]"),
    (lambda s: s.update(config="S8"), "settings.config must be a JSON object"),
    (lambda s: s["config"].pop("filter"), "settings.config: missing section [filter]"),
    (lambda s: s.update(scenario_seed=1.5), "settings.scenario_seed must be a whole number ≥ 0, got 1.5"),
    (lambda s: s.update(seeed=3), "settings: unknown key 'seeed' (did you mean 'seed'?)"),
], ids=["likelihood-key", "likelihood-list", "config-string", "config-section", "seed-float", "misspelt"])
def test_a_logs_settings_are_checked_before_a_replay(a_log, edit, fragment):
    """`settings_json` (a log's /settings) was not validated: a hand-edited one was a raw TypeError ('unexpected
    keyword argument'), a raw KeyError or 'dictionary update sequence element' on replay, or silently ignored."""
    import copy
    import dataclasses

    from warptan.io.flightlog import LogError, read_log
    from warptan.sim.replay import replay_config

    log = read_log(a_log)
    settings = copy.deepcopy(log.settings)
    edit(settings)
    with pytest.raises(LogError) as err:
        replay_config(dataclasses.replace(log, settings=settings))
    assert fragment in str(err.value)
    replay_config(log)  # (the log as written passes)


def test_a_dem_grid_log_over_another_generated_terrain_names_both(capsys, tmp_path):
    """A log over `synthetic:rugged,seed=3` (a dem-grid frame) replayed over `synthetic:rugged,seed=4` was told it
    "cannot be placed on synthetic:rugged; replay it over its own DEM": a generated terrain's name dropped its
    options, so the message named neither the DEM given nor the log's own."""
    from warptan.terrain.grid import Terrain

    assert Terrain.load("synthetic:rugged,seed=4,size_m=10000").name == "synthetic:rugged,size_m=10000,seed=4"
    assert Terrain.load("synthetic:rugged").name == "synthetic:rugged"
    assert cli.main(["run", "S8", *QUICK, "--terrain", "synthetic:rugged,seed=3", "--export-log",
                     str(tmp_path / "L"), "--out", str(tmp_path / "R")]) == 0
    capsys.readouterr()
    status, _, err = _cli(capsys, "replay", tmp_path / "L" / "S8_seed0.h5", "--terrain", "synthetic:rugged,seed=4",
                          "--quiet", "--out", tmp_path / "o")
    assert status == 2
    _error_line(err, "cannot be placed on synthetic:rugged,seed=4",
                "replay it over its own DEM 'synthetic:rugged,seed=3' (leave out --terrain)")


def test_a_file_size_limit_names_the_file_that_hit_it(tmp_path):
    """Under `ulimit -f` a plot's failed write was reported as results.md (the newest file by modification time, a
    guess: files written within one clock tick tie). The last file opened for writing is the one named."""
    proc = _warptan(tmp_path, "run", "S8", "--duration-s", "0.5", "--particles", "16", "--quiet", "--out",
                    tmp_path / "R", limit=20000)
    assert proc.returncode == 2, proc.stderr[-2000:]
    _error_line(proc.stderr, f"writing {tmp_path / 'R' / 'S8_seed0_track.png'} failed: File too large")
    assert list(tmp_path.iterdir()) == []


def test_recording_the_commit_never_writes_the_users_repository(tmp_path, monkeypatch):
    """A run records its git commit with `git status`, which refreshed the checkout's index (writing
    .git/index.lock): under `ulimit -f` the write was cut and a stale lock blocked the user's next git command."""
    import shutil

    from warptan.meta import git_commit

    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@t"}
    (tmp_path / "a.txt").write_text("a")
    for argv in (["init", "-q"], ["add", "a.txt"], ["commit", "-q", "-m", "a"]):
        subprocess.run(["git", *argv], cwd=tmp_path, env=env, check=True, capture_output=True)
    monkeypatch.delenv("WARPTAN_GIT_COMMIT", raising=False)
    index = tmp_path / ".git" / "index"
    os.utime(tmp_path / "a.txt", ns=(1, 1))  # (its stat no longer matches the index: `git status` rewrites it)
    before = index.stat().st_mtime_ns, index.read_bytes()
    assert len(git_commit(tmp_path).split("+")[0]) == 40
    assert (index.stat().st_mtime_ns, index.read_bytes()) == before


@pytest.mark.parametrize("argv, fragment", [
    (["run", "S8", "--terrain", ""], "argument --terrain: must not be empty"),
    (["replay", "x.h5", "--terrain", ""], "argument --terrain: must not be empty"),
    (["terrain", "info", "synthetic:rugged,seed=1,seed=2"], "option seed given twice"),
    (["run", "S8", "--duration-s", "0.5", "--seeds", "100000000", "--check"],
     "the results of 100000000 seeds run one by one held"),
    (["run", "S8", "--world-error-corr-m", "0", "--check"], "--world-error-corr-m 0 is the correlation length of"),
    (["log", "import", "missing.toml", "--out", "x.h5"], "does not load: No such file or directory"),
    (["terrain", "info", "rugged", "--information", "--altitude-agl", "1e9"], "more than the DEM's"),
], ids=["empty-terrain", "replay-empty-terrain", "synthetic-twice", "seeds-held", "world-corr-alone",
        "missing-layout", "footprint-beyond-dem"])
def test_names_and_counts_that_mean_nothing_are_refused(capsys, tmp_path, monkeypatch, argv, fragment):
    """The wider probe (scripts/hostile_probe.py): `--terrain ""` silently ran the scenario's own DEM;
    `synthetic:rugged,seed=1,seed=2` took the last seed silently; `--seeds 100000000` of a 0.5 s flight passed the
    memory check (one seed at a time) and ran on for days, holding every seed's result; `--world-error-corr-m`
    alone did nothing; a missing layout said "[Errno 2]"; an information map 1e9 m up said "no fix" with exit 0."""
    monkeypatch.chdir(tmp_path)
    status, _, err = _cli(capsys, *argv)
    assert status == 2
    if err.startswith("usage:"):
        err = err.strip().splitlines()[-1]
    assert fragment in err and "Errno" not in err, err
    assert list(tmp_path.iterdir()) == []
