"""INS, IMU grades and truth trajectories (design notes §3, §4): truth first, then the INS against it (pyins style)."""

import math

import numpy as np
import pytest

from warptan.nav.frames import quat_to_euler
from warptan.nav.imu import IMU_GRADES, ImuModel, imu_grade
from warptan.nav.ins import (
    Ins,
    NavState,
    error_transition,
    mechanize,
    process_noise,
    state_difference,
    state_plus,
)
from warptan.nav.trajectory import Climb, Orbit, Straight, Trajectory, Turn


def _ten_minutes():
    return Trajectory.build(
        [Straight(60), Turn(90, bank_deg=30), Climb(60, 5.0), Straight(40), Turn(-180, bank_deg=60),
         Climb(50, -4.0), Orbit(150, bank_deg=30), Turn(45, bank_deg=60), Straight(180)],
        speed_mps=100.0, start_pos_n=[0.0, 0.0, -1500.0], heading_deg=30.0, rate_hz=100.0)


def test_perfect_imu_reproduces_truth():
    """Ideal samples through the mechanization reproduce the truth to < 1 mm after 10 min at 100 Hz,
    through 30° and 60° turns and climbs; the flight really banks, turns and climbs."""
    tr = _ten_minutes()
    assert tr.duration_s >= 600.0
    out = Ins(tr.state(0), tr.rate_hz).run(tr.f_b, tr.w_b)
    assert np.max(np.linalg.norm(out["pos_n"] - tr.pos_n, axis=1)) < 1e-3
    assert np.max(np.abs(out["vel_n"] - tr.vel_n)) < 1e-6
    eul = np.degrees(quat_to_euler(tr.quat_nb))
    assert eul[:, 0].max() == pytest.approx(60.0, abs=1e-6) and eul[:, 0].min() == pytest.approx(-60.0, abs=1e-6)
    assert np.any(np.abs(eul[:, 0] - 30.0) < 1e-6)  # the 30° turn
    assert eul[:, 1].max() == pytest.approx(5.0, abs=1e-6)
    assert np.ptp(tr.pos_n[:, 2]) > 300.0


def test_coordinated_turn_rate_and_speed():
    """In the held part of a turn, yaw rate = g tan(bank) / V; speed stays V; no side force (coordinated)."""
    tr = Trajectory.build([Orbit(60, bank_deg=45, roll_time_s=3)], 120.0, [0, 0, -1000.0])
    yaw = np.unwrap(quat_to_euler(tr.quat_nb)[:, 2])
    mid = slice(1000, 5000)
    rate = np.diff(yaw)[mid] * tr.rate_hz
    np.testing.assert_allclose(rate, 9.80665 * math.tan(math.radians(45)) / 120.0, rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(tr.vel_n, axis=1), 120.0, rtol=1e-12)
    assert np.max(np.abs(tr.f_b[mid, 1])) < 1e-3


def test_turn_reaches_its_heading_change():
    """A Turn segment changes the heading by the requested amount, roll-in and roll-out included."""
    tr = Trajectory.build([Straight(5), Turn(-120, bank_deg=30, roll_time_s=4), Straight(5)], 100.0, [0, 0, -500.0],
                          heading_deg=10.0)
    yaw = np.degrees(np.unwrap(quat_to_euler(tr.quat_nb)[:, 2]))
    assert yaw[-1] - yaw[0] == pytest.approx(-120.0, abs=0.2)


def _dx_scaled(scale, seed=0):
    rng = np.random.default_rng(seed)
    return scale * np.concatenate([rng.normal(0, 1, 3), rng.normal(0, 0.1, 3), rng.normal(0, 0.01, 3),
                                   rng.normal(0, 0.01, 3), rng.normal(0, 1e-4, 3)])


def test_error_transition_is_the_jacobian():
    """x' ⊖ x_nom' vs F dx after one step from a banked, climbing state: the mismatch shrinks quadratically
    with the perturbation (exact Jacobian); the design notes' first-order F (§3) differs from it only by O(dt²)
    terms."""
    nominal = NavState([10.0, -5.0, -800.0], [90.0, 30.0, -5.0], [0.9, 0.2, -0.1, 0.37] / np.linalg.norm(
        [0.9, 0.2, -0.1, 0.37]), [0.01, -0.02, 0.005], [1e-4, -2e-4, 5e-5])
    f, w, dt = np.array([0.5, 2.0, -9.0]), np.array([0.05, -0.1, 0.2]), 0.01
    nominal_next = mechanize(nominal, f, w, dt)
    F = error_transition(nominal, f, w, dt)
    mismatch = []
    for scale in (1.0, 0.5, 0.25, 0.125):
        dx = _dx_scaled(scale)
        actual = state_difference(mechanize(state_plus(nominal, dx), f, w, dt), nominal_next)
        mismatch.append(np.linalg.norm(actual - F @ dx))
    ratios = np.array(mismatch[:-1]) / np.array(mismatch[1:])
    assert np.all((ratios > 3.5) & (ratios < 4.5)), ratios  # quadratic: halving dx quarters the mismatch
    F_spec = error_transition(nominal, f, w, dt, exact=False)
    assert np.max(np.abs(F - F_spec)) < 10 * dt * dt


def test_process_noise_blocks():
    """Q holds Na² dt, Ng² dt, Ba² dt, Bg² dt on the dv, dth, dba, dbg diagonals and nothing on dp."""
    g = imu_grade("tactical")
    q = process_noise(g, 0.01)
    np.testing.assert_allclose(np.diag(q), np.repeat([0.0, g.accel_noise**2, g.gyro_noise**2, g.accel_bias_walk**2,
                                                      g.gyro_bias_walk**2], 3) * 0.01)


def test_grade_units():
    """Datasheet units convert to SI: 0.1 mg, 0.01 deg/h, 20 µg/√Hz, 0.002 deg/√h for navigation grade."""
    g = imu_grade("navigation")
    assert g.accel_bias == pytest.approx(0.1e-3 * 9.80665)
    assert g.gyro_bias == pytest.approx(math.radians(0.01) / 3600)
    assert g.accel_noise == pytest.approx(20e-6 * 9.80665)
    assert g.gyro_noise == pytest.approx(math.radians(0.002) / 60)
    assert list(IMU_GRADES) == ["consumer", "tactical_low", "tactical", "intermediate", "navigation", "marine"]


def test_imu_model_statistics_and_determinism():
    """Same seed, same errors; white-noise σ = density/√dt; turn-on biases spread with the grade's σ."""
    g = imu_grade("tactical")
    a = ImuModel(g, 100.0, seed=3).errors(20000)
    b = ImuModel(g, 100.0, seed=3).errors(20000)
    np.testing.assert_array_equal(a.accel_noise, b.accel_noise)
    assert np.std(a.accel_noise) == pytest.approx(g.accel_noise * 10.0, rel=0.03)
    assert np.std(a.gyro_noise) == pytest.approx(g.gyro_noise * 10.0, rel=0.03)
    biases = np.array([ImuModel(g, 100.0, seed=s).errors(1).gyro_bias[0] for s in range(400)])
    assert np.std(biases) == pytest.approx(g.gyro_bias, rel=0.1)


def _dead_reckoning(grade, seed, duration=120.0):
    tr = Trajectory.build([Straight(duration)], 100.0, [0, 0, -1000.0], heading_deg=0.0)
    f, w, err = ImuModel(grade, tr.rate_hz, seed=seed).corrupt(tr.f_b, tr.w_b)
    out = Ins(tr.state(0), tr.rate_hz).run(f, w)
    drift = out["pos_n"][-1, :2] - tr.pos_n[-1, :2]
    # Bias-driven growth, heading north, level: 0.5 b_a t² plus the tilt from the gyro bias, g b_g t³ / 6.
    ba, bg = err.accel_bias[0], err.gyro_bias[0]
    t = duration
    predicted = 0.5 * ba[:2] * t**2 + 9.80665 * t**3 / 6.0 * np.array([-bg[1], bg[0]])
    return drift, predicted


def test_dead_reckoning_drift_is_ordered_and_bias_driven():
    """Over 120 s: navigation ≪ tactical_low ≪ consumer, and each grade's drift matches the bias-driven
    0.5·b·t² (+ g·b_g·t³/6 from the tilt) prediction to within 20 % (mean over 8 seeds)."""
    medians = {}
    for grade in ("navigation", "tactical_low", "consumer"):
        drifts, preds = zip(*(_dead_reckoning(grade, s) for s in range(8)), strict=True)
        drifts, preds = np.array(drifts), np.array(preds)
        medians[grade] = np.median(np.linalg.norm(drifts, axis=1))
        rel = np.mean(np.linalg.norm(drifts - preds, axis=1)) / np.mean(np.linalg.norm(preds, axis=1))
        assert rel < 0.2, (grade, rel)
    assert 1.0 < medians["navigation"] < 30.0
    assert medians["tactical_low"] > 10 * medians["navigation"]
    assert medians["consumer"] > 2 * medians["tactical_low"]


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_samples_are_rejected(bad):
    """A NaN or inf IMU sample raises; the state is not advanced with it."""
    tr = Trajectory.build([Straight(1.0)], 100.0, [0, 0, -100.0])
    ins = Ins(tr.state(0), 100.0)
    f = tr.f_b.copy()
    f[50, 1] = bad
    with pytest.raises(ValueError, match="not finite"):
        ins.run(f, tr.w_b)
    np.testing.assert_array_equal(ins.state.pos_n, tr.pos_n[0])
    with pytest.raises(ValueError, match="non-finite IMU sample"):
        ins.step([0, 0, bad], [0, 0, 0])
    with pytest.raises(ValueError, match="NaN or inf"):
        ImuModel("navigation", 100.0).corrupt(f, tr.w_b)


@pytest.mark.parametrize(("call", "message"), [
    (lambda: NavState([0, 0, 0], [0, 0, 0], [1, 0, 0, 0.1]), "not a unit quaternion"),
    (lambda: NavState([0, 0, 0], [0, 0, 0], [0, 0, 0, 0]), "not a unit quaternion"),
    (lambda: NavState([0, 0, np.nan], [0, 0, 0], [1, 0, 0, 0]), "pos_n"),
    (lambda: Ins(NavState([0, 0, 0], [0, 0, 0], [1, 0, 0, 0]), 0.0), "rate_hz"),
    (lambda: ImuModel("automotive", 100.0), "unknown IMU grade 'automotive'"),
    (lambda: Trajectory.build([Straight(0.0)], 100.0, [0, 0, 0]), "duration_s"),
    (lambda: Trajectory.build([Straight(10.0)], -1.0, [0, 0, 0]), "speed_mps"),
    (lambda: Trajectory.build([Straight(10.0)], 100.0, [0, 0, 0], rate_hz=0), "rate_hz"),
    (lambda: Trajectory.build([Turn(90, bank_deg=90)], 100.0, [0, 0, 0]), "bank angle"),
    (lambda: Trajectory.build([Orbit(60, bank_deg=95)], 100.0, [0, 0, 0]), "bank angle"),
    (lambda: Trajectory.build([Turn(2, bank_deg=30, roll_time_s=5)], 100.0, [0, 0, 0]), "shorter than its roll"),
    (lambda: Trajectory.build([], 100.0, [0, 0, 0]), "at least one segment"),
])
def test_bad_input_is_a_clear_error(call, message):
    """Non-unit quaternions, bad rates and durations, unknown grades and banks ≥ 90° raise ValueError."""
    with pytest.raises(ValueError, match=message):
        call()
