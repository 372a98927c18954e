"""Recorded flights: the flight-log format, replay with recorded timestamps, ROS 2 bags, bad logs."""

import copy
import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from warptan.filter.mpf import MarginalizedParticleFilter
from warptan.io.flightlog import FlightLog, LogError, read_log, write_log
from warptan.nav.frames import quat_to_euler
from warptan.sim.replay import replay, timeline
from warptan.sim.scenarios import run_scenario

RUN = {"duration_s": 3.0, "particles": 128}


@pytest.fixture(scope="module")
def simulated():
    """One short S8 run (sliding) and its flight log; one altimeter run likewise."""
    out = {}
    for key, extra in (("sliding", {}), ("altimeter", {"model": "altimeter"})):
        logs = []
        result = run_scenario("S8", seed=1, export_logs=logs, **RUN, **extra)
        out[key] = (result, logs[0])
    return out


def _same_run(a, b):
    for name in ("t_s", "est_pos", "sigma3_pos", "ess", "truth_pos", "ins_pos", "lin_err", "sigma3_lin", "stages"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.parametrize("kind", ["sliding", "altimeter"])
def test_exported_log_replays_bit_identically(simulated, kind, tmp_path):
    """run → flight log file → replay: the same estimate, σ, ESS and errors, bit for bit (same device)."""
    result, log = simulated[kind]
    path = write_log(log, tmp_path / "flight.h5")
    again = replay(read_log(path))
    assert again.scenario == "S8" and again.seed == 1
    _same_run(result.run, again.run)


def test_mounted_sensor_replays_to_the_same_estimate(simulated):
    """The same scans expressed in a sensor frame rotated 90° about z and 20° about y, 1.5 m from the body origin:
    replay with that mounting gives the run of the body-frame scans (to the rounding of re-expressing the points)."""
    from warptan.nav.frames import euler_to_mat, mat_to_quat

    result, log = simulated["sliding"]
    rot_bs = euler_to_mat(0.0, np.radians(20.0), np.radians(90.0))
    lever = np.array([1.5, -0.4, 0.3])
    points_b = log.scan_ranges[..., None] * log.scan_dirs
    points_s = (points_b - lever) @ rot_bs  # c_s = R_bsᵀ (c_b - l)
    ranges = np.linalg.norm(points_s, axis=2)
    mounted = dataclasses.replace(log, scan_dirs=points_s / ranges[..., None], scan_ranges=ranges,
                                  mount_quat=np.asarray(mat_to_quat(rot_bs)), mount_lever=lever)
    again = replay(mounted)
    np.testing.assert_allclose(again.run.est_pos, result.run.est_pos, rtol=0, atol=0.02)
    unmounted = replay(dataclasses.replace(mounted, mount_quat=log.mount_quat, mount_lever=log.mount_lever))
    assert np.abs(unmounted.run.est_pos - result.run.est_pos).max() > 1.0  # the mounting matters


def test_replay_without_truth_writes_estimate_and_trajectory(simulated, tmp_path):
    """A log without truth replays: errors NaN, the estimate and 3σ finite; the CLI writes results, trajectory CSV
    (lat/lon with the DEM's CRS) and GeoJSON."""
    _, log = simulated["sliding"]
    bare = dataclasses.replace(log, truth_t=None, truth_pos=None, truth_vel=None, truth_quat=None,
                               truth_accel_bias=None, truth_gyro_bias=None, settings={})
    path = write_log(bare, tmp_path / "bare.h5")
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "warptan", "replay", str(path), "--terrain", "rugged", "--out",
                           str(out), "--quiet", "--no-plots", "--particles", "128"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((out / "results.json").read_text())
    run = data["runs"][0]
    assert run["rmse_m"] == [None, None, None]
    header = (out / "replay_seed0_trajectory.csv").read_text().splitlines()[0].split(",")
    assert {"t_s", "north_m", "lat_deg", "lon_deg", "alt_m", "sigma3_north_m"} <= set(header)
    table = np.loadtxt(out / "replay_seed0_trajectory.csv", delimiter=",", skiprows=1)
    assert np.isfinite(table[:, :7]).all() and len(table) == 31
    geo = json.loads((out / "replay_seed0_trajectory.geojson").read_text())
    lon, lat, _ = geo["features"][0]["geometry"]["coordinates"][0]
    assert 9.0 < lon < 13.0 and 49.0 < lat < 52.0  # the rugged tile is in Thuringia


def test_timeline_splits_a_step_at_a_measurement():
    """IMU at 100 Hz with jitter; a scan between two samples splits the step; steps add up to the times."""
    t = np.array([0.0, 0.01, 0.02, 0.0305, 0.04])
    log = _tiny_log(t)
    sample, dt, ends, used = timeline(log, np.array([0.015, 0.02 + 1e-12, 0.045, 0.2]))
    assert used.tolist() == [True, True, True, False]
    np.testing.assert_array_equal(sample, [0, 1, 1, 2, 3, 4])
    np.testing.assert_allclose(dt, [0.01, 0.005, 0.005, 0.0105, 0.0095, 0.005], rtol=0, atol=1e-15)
    assert dt[0] == 0.01  # a nominal step is the nominal period exactly
    assert ends.tolist() == [2, 3, 6]
    np.testing.assert_allclose(np.cumsum(dt)[ends - 1], [0.015, 0.02, 0.045], atol=1e-15)


def _tiny_log(t, **changes) -> FlightLog:
    k = len(t)
    base = dict(imu_t=np.asarray(t, dtype=np.float64), imu_f=np.tile([0.0, 0.0, -9.80665], (k, 1)),
                imu_w=np.zeros((k, 3)), imu_rate_hz=100.0, imu_grade="navigation", t_end=float(t[-1]) + 0.01,
                init_t=float(t[0]), init_pos=np.array([0.0, 0.0, -1000.0]), init_vel=np.zeros(3),
                init_quat=np.array([1.0, 0.0, 0.0, 0.0]), init_sigma=np.r_[np.full(3, 10.0), np.full(12, 0.01)],
                alt_t=np.array([t[-1]]), alt_range=np.array([500.0]))
    base.update(changes)
    return FlightLog(**base)


@pytest.mark.parametrize("change, expect", [
    ({"imu_t": np.array([0.0, 0.01, 0.01, 0.03])}, "imu.t is not strictly increasing: t[2]"),
    ({"imu_f": np.array([[0, 0, -9.8], [np.nan, 0, 0], [0, 0, -9.8], [0, 0, -9.8]])},
     "imu.f_b has 1 non-finite sample(s) (first at index 1)"),
    ({"imu_t": np.array([0.0, 0.01, 1.5, 1.51]), "t_end": 1.52}, "imu has a gap of 1.490 s after t = 0.01 s"),
    ({"init_quat": np.array([1.0, 0.1, 0.0, 0.0])}, "initial.quat_nb has 1 quaternion(s) that are not unit"),
    ({"imu_grade": "superb"}, "imu.grade 'superb'"),
    ({"alt_t": None, "alt_range": None}, "neither scans nor altimeter readings"),
])
def test_bad_logs_name_every_problem(change, expect, tmp_path):
    log = _tiny_log(np.array([0.0, 0.01, 0.02, 0.03]), **change)
    with pytest.raises(LogError, match=None) as err:
        write_log(log, tmp_path / "bad.h5")
    assert expect in str(err.value)
    assert not any(tmp_path.iterdir())  # nothing written


def test_all_problems_at_once_and_not_a_log(tmp_path):
    log = _tiny_log(np.array([0.0, 0.01, 0.005, 0.03]), imu_grade="superb",
                    init_sigma=np.r_[np.full(3, -1.0), np.zeros(12)])
    assert len(log.problems()) == 3
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5 at all")
    with pytest.raises(LogError, match="not an HDF5 file"):
        read_log(junk)
    import h5py

    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.create_dataset("x", data=[1, 2])
    with pytest.raises(LogError, match="not a warptan flight log"):
        read_log(tmp_path / "other.h5")


def test_predict_refuses_a_bad_step():
    from warptan.nav.ins import NavState
    from warptan.sensing.measurement import make_model
    from warptan.terrain.grid import Terrain

    model = make_model("sliding", Terrain.synthetic(size_m=4000.0, spacing=90.0))
    mpf = MarginalizedParticleFilter(model, NavState([0, 0, -1000.0], [100.0, 0, 0], [1.0, 0, 0, 0]), "navigation",
                                     100.0, [10.0] * 3, np.eye(12) * 1e-4, n_particles=16)
    with pytest.raises(ValueError, match=r"IMU step dt\[1\] = 2.0 s"):
        mpf.predict_many(np.zeros((2, 3)), np.zeros((2, 3)), dt=[0.01, 2.0])


# ---------------------------------------------------------------------- ROS 2
def test_ros_frames():
    """FLU/ENU ↔ FRD/NED: a ROS body at identity faces east, level; the conversions invert each other."""
    pytest.importorskip("rosbags")
    from warptan.io.rosbag import ENU_NED, FLU_FRD, quat_ned_to_ros, quat_ros_to_ned

    q = quat_ros_to_ned([0.0, 0.0, 0.0, 1.0])[0]
    np.testing.assert_allclose(np.degrees(quat_to_euler(q)), [0.0, 0.0, 90.0], atol=1e-12)
    rng = np.random.default_rng(0)
    qs = rng.normal(size=(20, 4))
    qs /= np.linalg.norm(qs, axis=1, keepdims=True)
    back = quat_ros_to_ned(quat_ned_to_ros(qs))
    np.testing.assert_allclose(np.abs(np.sum(back * qs, axis=1)), 1.0, atol=1e-12)
    # at rest an accelerometer reads +g up (FLU) = -g down (FRD); east in ENU is east in NED
    np.testing.assert_array_equal(FLU_FRD @ [0.0, 0.0, 9.8], [0.0, 0.0, -9.8])
    np.testing.assert_array_equal(ENU_NED @ [1.0, 2.0, 3.0], [2.0, 1.0, -3.0])


def test_exported_bag_replays_to_the_same_result(simulated, tmp_path):
    """run → ROS 2 bag (FLU/ENU topics, float64 points, ns stamps) → replay: the same filter output up to the
    rounding of a point's range and direction recomputed from x, y, z (1e-13 m)."""
    pytest.importorskip("rosbags")
    from warptan.io.rosbag import read_bag, write_bag

    result, log = simulated["sliding"]
    write_bag(log, tmp_path / "bag")
    back = read_bag(tmp_path / "bag")
    assert back.frame == log.frame and back.frame is not None  # the geodetic frame through warptan.toml
    np.testing.assert_allclose(back.imu_f, log.imu_f, rtol=0, atol=0)
    np.testing.assert_allclose(back.scan_ranges, log.scan_ranges, rtol=1e-14)
    np.testing.assert_allclose(back.truth_pos, log.truth_pos, rtol=0, atol=1e-9)
    again = replay(back)
    np.testing.assert_allclose(again.run.est_pos, result.run.est_pos, rtol=0, atol=0.05)
    np.testing.assert_allclose(again.run.sigma3_pos, result.run.sigma3_pos, rtol=0.05)


def test_bag_missing_topics_is_one_error(simulated, tmp_path):
    pytest.importorskip("rosbags")
    from warptan.io.rosbag import BagConfig, read_bag, write_bag

    _, log = simulated["sliding"]
    write_bag(log, tmp_path / "bag")
    config = BagConfig.for_bag(tmp_path / "bag").with_overrides(imu="/imu_raw", cloud="/lidar")
    with pytest.raises(LogError) as err:
        read_bag(tmp_path / "bag", config)
    text = str(err.value)
    assert "IMU topic '/imu_raw' is not in the bag" in text and "'/lidar'" in text


def test_a_log_written_before_worlds_and_stated_accuracy_replays(simulated):
    """A log's stored settings without the [world] table and the likelihood's stated-accuracy keys (every log written
    before them) replay with another likelihood, which rebuilds the likelihood from the stored config."""
    _, log = simulated["sliding"]
    old = copy.deepcopy(log.settings)
    old["config"].pop("world")
    for key in ("map_error_rms_m", "map_error_corr_m"):
        old["config"]["likelihood"].pop(key)
    result = replay(dataclasses.replace(log, settings=old), likelihood="student_t", particles=64)
    assert np.isfinite(result.run.est_pos).all() and result.config.likelihood.map_error_rms_m == 0.0
