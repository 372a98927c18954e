"""Flight logs tied to the Earth (format version 2): the geodetic frame, its change into any DEM's frame, replay over
other crops and projections of the same ground, and what replay refuses (another place, nodata, no CRS)."""

import dataclasses
import subprocess
import sys
import warnings

import numpy as np
import pytest

from warptan.checks import FilterError
from warptan.io.flightlog import LogError, read_log, write_log
from warptan.nav.frames import quat_to_euler
from warptan.nav.geoframe import GeoFrame, corners, frame_change
from warptan.sim.replay import replay
from warptan.sim.scenarios import run_scenario
from warptan.terrain.grid import Terrain, named_terrain_file

rasterio = pytest.importorskip("rasterio")


@pytest.fixture(scope="module")
def dems(tmp_path_factory):
    """Copies of the package's rugged tile (geographic, SRTM3): shifted 3° east, with a nodata hole in the middle,
    cut by 40 posts on its west and north sides, projected to UTM 32N at 60 m, and a window of that UTM grid (the
    same posts, another origin)."""
    from rasterio.warp import Resampling, calculate_default_transform, reproject
    from rasterio.windows import Window

    folder = tmp_path_factory.mktemp("dems")
    out = {}
    with rasterio.open(named_terrain_file("rugged")) as src:
        data, prof, t = src.read(1).astype(np.float32), src.profile, src.transform
        prof.update(dtype="float32", nodata=-32768.0)
        shifted = dict(prof, transform=rasterio.Affine(t.a, t.b, t.c + 3.0, t.d, t.e, t.f))
        with rasterio.open(folder / "shifted.tif", "w", **shifted) as dst:
            dst.write(data, 1)
        hole = data.copy()
        r0, c0 = src.height // 2, src.width // 2
        hole[r0 - 30:r0 + 30, c0 - 30:c0 + 30] = -32768.0
        with rasterio.open(folder / "hole.tif", "w", **prof) as dst:
            dst.write(hole, 1)
        cut = dict(prof, width=src.width - 40, height=src.height - 40,
                   transform=t * rasterio.Affine.translation(40, 40))
        with rasterio.open(folder / "crop.tif", "w", **cut) as dst:
            dst.write(data[40:, 40:], 1)
        tr, w, h = calculate_default_transform(src.crs, "EPSG:32632", src.width, src.height, *src.bounds,
                                               resolution=60)
        utm = np.full((h, w), -32768.0, np.float32)
        reproject(data, utm, src_transform=t, src_crs=src.crs, dst_transform=tr, dst_crs="EPSG:32632",
                  resampling=Resampling.bilinear, src_nodata=-32768.0, dst_nodata=-32768.0)
        uprof = dict(prof, crs="EPSG:32632", transform=tr, width=w, height=h)
        with rasterio.open(folder / "utm.tif", "w", **uprof) as dst:
            dst.write(utm, 1)
        win = Window(50, 30, w - 70, h - 70)
        with rasterio.open(folder / "utm_crop.tif", "w", **dict(uprof, width=win.width, height=win.height,
                                                                 transform=rasterio.windows.transform(win, tr))) as d:
            d.write(utm[30:30 + win.height, 50:50 + win.width], 1)
    for name in ("shifted", "hole", "crop", "utm", "utm_crop"):
        out[name] = str(folder / f"{name}.tif")
    return out


@pytest.fixture(scope="module")
def s8():
    logs = []
    result = run_scenario("S8", seed=1, export_logs=logs, duration_s=3.0, particles=128)
    return result, logs[0]


def test_frame_change_between_tangent_frames_matches_latlon_and_convergence():
    """Two tangent frames 0.5° of longitude apart: positions agree through latitude/longitude (an independent PROJ
    call), the north axes differ by the meridian convergence Δλ·sin φ (to 1 %), and velocities and attitudes turn by
    it consistently with the positions (a displacement maps to the turned velocity times dt, to 1 mm)."""
    a, b = GeoFrame(50.0, 10.0), GeoFrame(50.1, 10.5)
    pos = np.array([[1000.0, -2000.0, -800.0], [-5000.0, 3000.0, -900.0]])
    change = frame_change(a, b, corners(pos))
    assert not change.identity
    moved = change.positions(pos)
    lat, lon = a.ne_to_latlon(pos[:, 0], pos[:, 1])
    n, e = b.latlon_to_ne(lat, lon)
    np.testing.assert_allclose(moved[:, :2], np.column_stack([n, e]), atol=1e-6)
    np.testing.assert_array_equal(moved[:, 2], pos[:, 2])
    angle, scale = change.angles(pos)
    np.testing.assert_allclose(np.abs(np.degrees(angle)), 0.5 * np.sin(np.radians(lat)), rtol=0.01)
    assert np.all(np.abs(scale - 1.0) < 2.5e-5)  # tangent frames 36 km apart: x²/2R² = 17 ppm
    vel = np.array([[80.0, 60.0, 1.0], [-30.0, 90.0, -2.0]])
    dt = 0.5
    ahead = change.positions(pos + vel * dt) - moved
    np.testing.assert_allclose(ahead, change.vectors(pos, vel) * dt, atol=1e-3)
    quat = np.array([[1.0, 0.0, 0.0, 0.0], [np.cos(0.2), 0.0, 0.0, np.sin(0.2)]])
    yaw = quat_to_euler(change.attitudes(pos, quat))[:, 2]
    np.testing.assert_allclose(yaw, quat_to_euler(quat)[:, 2] + angle, atol=1e-12)
    same = frame_change(a, GeoFrame(50.0, 10.0), corners(pos))
    assert same.identity and np.array_equal(same.positions(pos), pos)


def test_log_version_2_keeps_its_frame_and_reads_version_1(s8, tmp_path):
    import h5py

    _, log = s8
    assert log.frame is not None and abs(log.frame.origin_lat_deg - 50.5) < 0.01 and log.version == 2
    back = read_log(write_log(log, tmp_path / "v2.h5"))
    assert back.frame == log.frame and back.version == 2
    np.testing.assert_array_equal(back.dem_posts, log.dem_posts)  # the package tile's posts in the log's frame
    assert log.dem_posts[4:].tolist() == list(result_terrain(s8).heights_m.shape)
    v1 = tmp_path / "v1.h5"
    write_log(log, v1)
    with h5py.File(v1, "a") as f:
        f.attrs["version"] = 1
        del f["frame"]
    old = read_log(v1)
    assert old.version == 1 and old.frame is None
    with h5py.File(v1, "a") as f:
        f.attrs["version"] = 2
    with pytest.raises(LogError, match="group /frame is missing"):
        read_log(v1)


def result_terrain(s8):
    return s8[0].truth_terrain


def test_another_cut_of_the_logs_dem_is_resampled_onto_its_posts(s8, dems):
    """A geographic DEM is resampled to metres on load; another cut of it resampled on its own is another map (GDAL's
    bilinear warp weighs a post by the output's extent: measured 2.3 m against 0.37 m for S8 seeds 0–1 over the
    package tile cut by 40 posts, 30 s). Replay puts it onto the log's DEM posts instead: the same heights (but at
    the cut's edge), the same likelihood as over the log's own DEM, the same estimate within the filter's noise."""
    result, log = s8
    own, crop = replay(log), replay(log, dems["crop"])
    assert crop.run.info["same_posts"] and crop.run.info["frame_identity"]
    world, cut = result.truth_terrain, crop.truth_terrain
    i, j = round((cut.n0 - world.n0) / world.dn), round((cut.e0 - world.e0) / world.de)
    assert (i, j) == (0, 40)  # the cut's first post is the world's post 40 east of its first
    a = world.heights_m[i:i + cut.heights_m.shape[0], j:j + cut.heights_m.shape[1]]
    both = np.isfinite(a) & np.isfinite(cut.heights_m)
    assert np.mean(a[both] == cut.heights_m[both]) > 0.99
    assert crop.map_sigma_m == own.map_sigma_m  # no interpolation error counted: the map is the log's DEM
    np.testing.assert_allclose(crop.run.est_pos, own.run.est_pos, atol=2.0)
    other = Terrain.from_raster(dems["crop"], posts=(log.frame.crs_wkt, (0.0, 0.0),
                                                     (*log.dem_posts[:2], 30.0, 30.0, 100, 100)))
    assert "onto the posts" not in other.description  # another spacing: read on its own


def test_replay_is_told_the_dems_stated_accuracy(s8, tmp_path):
    """A real flight's DEM has a published accuracy: replay takes it (API and CLI) into the likelihood's map-error
    modes; half a statement, or an RMS without a correlation length, is one clear error before any work."""
    _, log = s8
    told = replay(log, map_error=(5.0, 1000.0))
    assert (told.config.likelihood.map_error_rms_m, told.config.likelihood.map_error_corr_m) == (5.0, 1e3)
    assert np.isfinite(told.run.est_pos).all()
    assert not np.array_equal(told.run.est_pos, replay(log).run.est_pos)  # the modes weigh the scans
    with pytest.raises(FilterError, match="stated accuracy must be"):
        replay(log, map_error=(5.0, 0.0))
    path = write_log(log, tmp_path / "flight.h5")
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "warptan", "replay", str(path), "--map-error-m", "5", "--out",
                           str(out), "--quiet"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "--map-error-m and --map-error-corr-m go together" in proc.stderr and not out.exists()


def test_bad_dem_posts_are_refused_before_writing(s8, tmp_path):
    _, log = s8
    bad = np.r_[log.dem_posts[:3], -1.0, log.dem_posts[4:]]
    with pytest.raises(LogError, match=r"dem\.posts must be 6 finite numbers"):
        write_log(dataclasses.replace(log, dem_posts=bad), tmp_path / "bad.h5")
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("frame, expect", [
    (GeoFrame(91.0, 10.0), "frame.origin_lat_deg must be a finite latitude"),
    (GeoFrame(50.0, float("nan")), "frame.origin_lon_deg must be a finite longitude"),
    (GeoFrame(50.0, 10.0, float("inf")), "frame.origin_height_m must be a finite height"),
])
def test_a_bad_frame_is_refused_before_writing(s8, frame, expect, tmp_path):
    _, log = s8
    with pytest.raises(LogError, match=expect):
        write_log(dataclasses.replace(log, frame=frame), tmp_path / "bad.h5")
    assert not any(tmp_path.iterdir())


def test_own_dem_replays_bit_identically_through_the_geodetic_frame(s8):
    result, log = s8
    again = replay(log)
    assert again.run.info["frame"] == "geodetic" and again.run.info["frame_identity"]
    np.testing.assert_array_equal(again.run.est_pos, result.run.est_pos)


def test_the_same_flight_over_another_crop_of_a_projected_dem(dems):
    """A flight simulated over a UTM DEM (its log in the tangent frame at the DEM's origin), replayed over its own
    DEM and over a window of it (the same posts, another origin, 1.16° of convergence from the log's frame): the
    converged horizontal RMSE within 1.25× + 1 m (measured 0.13–0.25 m both, 60 s flights)."""
    logs = []
    result = run_scenario("S8", seed=2, export_logs=logs, terrain=dems["utm"], duration_s=40.0, particles=256)
    log = logs[0]
    assert log.frame is not None
    own, crop = replay(log), replay(log, dems["utm_crop"])
    assert not crop.run.info["frame_identity"] and abs(crop.run.info["frame_turn_deg"]) > 1.0

    def horizontal(r):
        return float(np.hypot(*r.run.rmse(20.0)[:2]))

    assert abs(horizontal(own) - horizontal(result)) < 0.5  # the round trip through the frame: the filter's noise
    assert horizontal(crop) <= 1.25 * horizontal(own) + 1.0, (horizontal(own), horizontal(crop))
    np.testing.assert_allclose(crop.run.truth_pos[:, 2], own.run.truth_pos[:, 2], atol=1e-6)


def test_replay_refuses_another_place_nodata_and_no_crs(s8, dems, tmp_path):
    _, log = s8
    path = write_log(log, tmp_path / "flight.h5")
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "warptan", "replay", str(path), "--terrain", dems["shifted"],
                           "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    line = [x for x in proc.stderr.splitlines() if "error" in x]
    assert len(line) == 1 and "does not contain the flight" in line[0]
    assert "lon 10.5" in line[0] and "lon 13.1" in line[0]  # both extents, in latitude/longitude
    assert not out.exists()
    with pytest.raises(LogError, match=r"passes over nodata.*--allow-gaps"):
        replay(log, dems["hole"])
    gappy = replay(log, dems["hole"], allow_gaps=True)
    assert gappy.run.info["gaps_allowed"] and gappy.run.info["track_points_over_nodata"] > 0
    assert gappy.summary()["skipped_updates"] > 0
    with pytest.raises(LogError, match="has no CRS"):
        replay(log, Terrain.synthetic("rugged", size_m=50_000.0))


def test_a_dem_grid_log_flies_only_over_its_own_dem(s8):
    _, log = s8
    grid = dataclasses.replace(log, frame=None)
    with pytest.raises(LogError, match="frame kind dem-grid"):
        replay(grid, "flat")
    old = dataclasses.replace(grid, version=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            replay(old, "flat")
        except LogError:
            pass  # the flat tile need not contain the rugged flight's grid coordinates
    assert any("version 1 log's frame is the grid of its DEM" in str(w.message) for w in caught)


def test_geodetic_tables_round_trip_replays_as_the_run(s8, tmp_path):
    """run → log → CSV tables (latitude/longitude/height, true-north attitude) → import → replay: the same IMU,
    scans and initial state (to 1e-6 m / 1e-12), and the same estimate within the filter's noise."""
    from warptan.io.logcsv import read_tables, write_tables

    result, log = s8
    back = read_tables(write_tables(log, tmp_path / "tables"))
    np.testing.assert_array_equal(back.imu_f, log.imu_f)
    np.testing.assert_allclose(back.scan_ranges, log.scan_ranges, rtol=1e-12)
    assert back.frame != log.frame  # the tangent frame at the first fix
    again = replay(back)
    np.testing.assert_allclose(again.run.truth_pos, result.run.truth_pos, atol=1e-6)
    np.testing.assert_allclose(again.run.ins_pos, result.run.ins_pos, atol=1e-6)
    np.testing.assert_allclose(again.run.est_pos, result.run.est_pos, atol=1.0)


@pytest.mark.parametrize("edit, expect", [
    (("gps.csv", "lat", "91.5"), "gps latitude must be within ±90°"),
    (("gps.csv", "header", "t,latitude,lon"), "missing column(s) 'lat'"),
    (("layout.toml", "units", 'units = {t = "fortnights"}'), "unit 'fortnights' of t does not parse"),
    (("imu.csv", "backwards", None), "times go backwards at row 4"),
    (("layout.toml", "unknown", "colour = 3"), "unknown key 'colour'"),
])
def test_bad_tables_are_one_clear_error(s8, edit, expect, tmp_path):
    from warptan.io.logcsv import read_tables, write_tables

    _, log = s8
    layout = write_tables(log, tmp_path / "tables")
    file, what, value = edit
    path = tmp_path / "tables" / file
    lines = path.read_text().splitlines()
    if what == "lat":
        row = lines[3].split(",")
        row[1] = value
        lines[3] = ",".join(row)
    elif what == "header":
        lines[0] = lines[0].replace("t,lat,lon", value)
    elif what == "units":
        at = lines.index("[imu]")
        lines[at + 2] = value
    elif what == "backwards":
        lines[2], lines[3] = lines[3], lines[2]
    else:
        lines.insert(0, value)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogError) as err:
        read_tables(layout)
    assert expect in str(err.value)


def test_tables_without_a_prior_take_the_scenarios_prior_for_their_grade(s8, tmp_path):
    """A layout without ``initial_sigma`` gets the scenarios' prior with its IMU grade's turn-on biases
    (:func:`warptan.filter.prior.prior_sigma`): a tactical IMU's bias σ, not the navigation grade's."""
    from warptan.filter.prior import InitialErrors, prior_sigma
    from warptan.io.logcsv import read_tables, write_tables
    from warptan.nav.imu import IMU_GRADES

    _, log = s8
    layout = write_tables(log, tmp_path / "tables")
    lines = [line for line in layout.read_text().splitlines() if not line.startswith("initial_sigma")]
    lines = [line.replace(f'imu_grade = "{log.imu_grade}"', 'imu_grade = "tactical"') for line in lines]
    layout.write_text("\n".join(lines) + "\n")
    back = read_tables(layout)
    assert back.imu_grade == "tactical"
    np.testing.assert_array_equal(back.init_sigma, prior_sigma(InitialErrors(), IMU_GRADES["tactical"]))
    assert back.init_sigma[9] > prior_sigma(InitialErrors(), IMU_GRADES["navigation"])[9]


def test_a_multi_band_raster_names_its_bands(tmp_path):
    with rasterio.open(named_terrain_file("rugged")) as src:
        data, prof = src.read(1), src.profile
    prof.update(count=3)
    with rasterio.open(tmp_path / "rgb.tif", "w", **prof) as dst:
        for i in (1, 2, 3):
            dst.write(data, i)
    from warptan.terrain.raster import TerrainError

    with pytest.raises(TerrainError, match="raster has 3 bands"):
        Terrain.load(str(tmp_path / "rgb.tif"))
    assert Terrain.load(f"{tmp_path / 'rgb.tif'}#band=2").shape == Terrain.load("rugged").shape
    with pytest.raises(TerrainError, match="band 5 does not exist"):
        Terrain.load(f"{tmp_path / 'rgb.tif'}#band=5")
