"""The exact information floor under a correlated map error (``warptan.filter.floor.exact_pcrb``) against a dense
NumPy oracle (every point of every scan jointly, the field's covariance between all of them, no grid) and a
Monte-Carlo estimator that attains it."""

import numpy as np
import pytest

from warptan.filter.bound import pcrb, scan_rows
from warptan.filter.floor import exact_pcrb
from warptan.nav.imu import imu_grade
from warptan.nav.ins import error_transition, process_noise
from warptan.nav.trajectory import Straight, Trajectory
from warptan.sensing.sensors import ScanPattern

P0 = np.diag([100.0 ** 2] * 2 + [20.0 ** 2] + [0.1 ** 2] * 3 + [1e-3 ** 2] * 3 + [1e-3 ** 2] * 3 + [1e-6 ** 2] * 3)
GRADE = imu_grade("navigation")
BARO = 1.0


def _flight(terrain, seconds=12.0):
    truth = Trajectory.build([Straight(seconds)], 100.0, [-2000.0, -300.0, -(terrain.h_max + 300.0)])
    return truth, np.arange(100, len(truth.pos_n), 100)  # a scan a second (100 m apart)


def _dense(truth, terrain, epochs, dirs, sigma, rms, corr, bias):
    """The oracle's joint Gaussian: the states at every epoch X = T [x0, w1 … wK] and every point's residual
    Z = H X + b + f(P) + v, the field's covariance rms² exp(−|Δ|²/L²) between all points. Returns (Σ_X, H, Σ_Z, the
    scan of each row)."""
    dt = 1.0 / truth.rate_hz
    q = process_noise(GRADE, dt)
    phis, qds, k = [], [], 0
    for epoch in epochs:
        phi, qd = np.eye(15), np.zeros((15, 15))
        for i in range(k, epoch):
            f = error_transition(truth.state(i), truth.f_b[i], truth.w_b[i], dt)
            phi, qd = f @ phi, f @ qd @ f.T + q
        phis.append(phi)
        qds.append(qd)
        k = epoch
    n = len(epochs)
    t = np.zeros((15 * n, 15 * (n + 1)))
    for i in range(n):  # x_i = Φ_i x_{i-1} + w_i, unrolled
        prev = np.eye(15, 15 * (n + 1)) if i == 0 else t[15 * (i - 1):15 * i]
        t[15 * i:15 * (i + 1)] = phis[i] @ prev
        t[15 * i:15 * (i + 1), 15 * (i + 1):15 * (i + 2)] += np.eye(15)
    cov0 = np.zeros((15 * (n + 1), 15 * (n + 1)))
    cov0[:15, :15] = P0
    for i in range(n):
        cov0[15 * (i + 1):15 * (i + 2), 15 * (i + 1):15 * (i + 2)] = qds[i]
    sigma_x = t @ cov0 @ t.T
    rows, pts, scan, white = [], [], [], []
    for i, epoch in enumerate(epochs):
        pos = truth.pos_n[epoch]
        if dirs is None:  # the altimeter under the aircraft, and a barometer (σ 1 m) that reads no map
            gn, ge = terrain.gradient_at(pos[:1], pos[1:2])
            off, g = np.zeros((2, 2)), np.zeros((2, 15))
            g[0, :3] = (gn[0], ge[0], 1.0)
            g[1, 2] = 1.0
            white += [sigma ** 2, BARO ** 2]
        else:
            off, g = scan_rows(terrain, pos, truth.quat_nb[epoch], dirs)
            white += [sigma ** 2] * len(g)
        h = np.zeros((len(g), 15 * n))
        h[:, 15 * i:15 * (i + 1)] = g
        rows.append(h)
        pts.append(pos[:2] + off)
        scan += [i] * len(g)
    h, pts = np.vstack(rows), np.vstack(pts)
    d = pts[:, None, :] - pts[None, :, :]
    field = rms ** 2 * np.exp(-(d ** 2).sum(-1) / corr ** 2) + bias ** 2
    if dirs is None:  # (the barometer's rows carry no map error)
        field[1::2, :] = 0.0
        field[:, 1::2] = 0.0
    sigma_z = h @ sigma_x @ h.T + field + np.diag(white)
    return sigma_x, h, sigma_z, np.array(scan), field


@pytest.mark.parametrize("rms, corr, bias, cloud", [(5.0, 300.0, 0.0, True), (5.0, 1000.0, 3.0, True),
                                                    (2.0, 3000.0, 0.0, True), (5.0, 300.0, 2.0, False)])
def test_the_exact_floor_matches_the_dense_oracle(rugged_small, rms, corr, bias, cloud):
    """12 scans 100 m apart of 5 × 5 points over the rugged synthetic map (σ 0.5 m): the window of field nodes gives
    each epoch's 15 σ of the dense joint conditioning (the states of every epoch and every point's residual, the
    field's covariance between all 300 points) within 0.1 % (2e-4 measured), at 300 m (nodes enter and leave the
    window), 1 km with a 3 m bias, and 3 km; and for an altimeter with a barometer (a reading a second, 300 m with a
    2 m bias) within 0.2 % (1.2e-3 measured: one point a scan feels the nodes' interpolation more; at 0.3 L spacing
    2.5e-5)."""
    truth, epochs = _flight(rugged_small)
    dirs = ScanPattern.grid(5, 5, 30.0).dirs_s if cloud else None
    sigma_x, h, sigma_z, scan, _ = _dense(truth, rugged_small, epochs, dirs, 0.5, rms, corr, bias)
    stats = {}
    floor = exact_pcrb(truth, rugged_small, epochs, GRADE, P0, dirs_body=dirs, sigma_m=0.5, map_error_rms_m=rms,
                       map_error_corr_m=corr, map_bias_m=bias, stats=stats, baro_sigma_m=None if cloud else BARO)
    for i in range(len(epochs)):
        seen = scan <= i
        cross = sigma_x[15 * i:15 * (i + 1)] @ h[seen].T
        post = sigma_x[15 * i:15 * (i + 1), 15 * i:15 * (i + 1)] - cross @ np.linalg.solve(
            sigma_z[np.ix_(seen, seen)], cross.T)
        np.testing.assert_allclose(floor[i + 1], np.sqrt(np.diag(post)), rtol=1e-3 if cloud else 2e-3)
    if corr == 300.0 and dirs is not None:  # the window moved: 1.2 km flown against a 0.9 km leaving radius
        assert stats["nodes_left"] > 50
    assert stats["max_interp_var"] < 1e-4 * rms ** 2


def test_a_gls_estimator_attains_the_exact_floor(rugged_small):
    """The generalised least-squares (conditional mean) estimate of the last epoch's error from every point with the
    field's full covariance, over 3000 draws of the linear-Gaussian model (states, a 5 m / 300 m field, noise): its
    horizontal error variance is the floor's within three standard errors, and the fast per-scan bound (κ sharing)
    differs from it by more than that on this map (the rule is an approximation, not the floor)."""
    truth, epochs = _flight(rugged_small)
    dirs = ScanPattern.grid(5, 5, 30.0).dirs_s
    sigma_x, h, sigma_z, _, field = _dense(truth, rugged_small, epochs, dirs, 0.5, 5.0, 300.0, 0.0)
    rng = np.random.default_rng(7)
    n = 3000
    x = np.linalg.cholesky(sigma_x + 1e-9 * np.eye(len(sigma_x))) @ rng.normal(size=(len(sigma_x), n))
    f = np.linalg.cholesky(field + 1e-6 * np.eye(len(field))) @ rng.normal(size=(len(field), n))
    z = h @ x + f + 0.5 * rng.normal(size=(len(field), n))
    last = slice(len(sigma_x) - 15, len(sigma_x))
    est = sigma_x[last] @ h.T @ np.linalg.solve(sigma_z, z)
    err = est[:2] - x[last][:2]
    var = (err ** 2).mean(axis=1)
    floor = exact_pcrb(truth, rugged_small, epochs, GRADE, P0, dirs_body=dirs, sigma_m=0.5, map_error_rms_m=5.0,
                       map_error_corr_m=300.0)[-1, :2] ** 2
    np.testing.assert_allclose(var, floor, rtol=3.0 * np.sqrt(2.0 / n))
    fast = pcrb(truth, rugged_small, epochs, GRADE, P0, dirs_body=dirs, sigma_m=0.5, map_error_rms_m=5.0,
                map_error_corr_m=300.0)[-1, :2] ** 2
    assert np.abs(fast / floor - 1.0).max() > 3.0 * np.sqrt(2.0 / n), (fast, floor)


def test_the_floor_without_map_error_is_the_fast_bound(rugged_small):
    """No map error: the floor is the fast bound's Riccati (the same information, scan by scan), to 1e-6."""
    truth, epochs = _flight(rugged_small)
    dirs = ScanPattern.grid(5, 5, 30.0).dirs_s
    a = pcrb(truth, rugged_small, epochs, GRADE, P0, dirs_body=dirs, sigma_m=0.5)
    b = exact_pcrb(truth, rugged_small, epochs, GRADE, P0, dirs_body=dirs, sigma_m=0.5)
    np.testing.assert_allclose(b, a, rtol=1e-6)


@pytest.mark.parametrize("kw, message", [({"sigma_m": 0.0}, "sigma_m = 0.0 must be > 0"),
                                         ({"map_error_rms_m": -1.0}, "must be ≥ 0"),
                                         ({"map_error_rms_m": 5.0, "map_error_corr_m": 0.0}, "length > 0"),
                                         ({"map_bias_m": float("nan")}, "bias nan m")])
def test_a_nonsense_statement_is_refused(rugged_small, kw, message):
    truth, epochs = _flight(rugged_small, 2.0)
    args = {"sigma_m": 0.5, **kw}
    with pytest.raises(ValueError, match=message):
        exact_pcrb(truth, rugged_small, epochs, GRADE, P0, dirs_body=ScanPattern.grid(5, 5, 30.0).dirs_s, **args)


def test_a_filter_over_a_map_error_never_beats_the_exact_floor():
    """S8 over a world whose map error is 5 m RMS over 1 km, the filter told it (8 seeds as one batch, 200 particles,
    40 s): its horizontal mean squared error after convergence is not below the flight's exact floor
    (``run_scenario_batch(..., bound="exact")``) by more than twice its Monte-Carlo standard error, and the floor
    is finite and positive at every epoch (and below the fast κ-rule bound on this flight: 0.26 against 0.33 m over
    60 s of seed 0)."""
    import math

    from warptan.sim.scenarios import run_scenario_batch

    kw = {"world_error_rms_m": 5.0, "world_error_corr_m": 1000.0, "map_error_rms_m": 5.0, "map_error_corr_m": 1000.0,
          "world_seed": 2000, "duration_s": 40.0, "particles": 200}
    runs = run_scenario_batch("S8", list(range(8)), "cpu", bound="exact", **kw)
    first = runs[0]
    sel = first.run.t_s >= first.config.filter.converged_after_s
    mse = np.array([(r.run.error[sel, :2] ** 2).sum(axis=1).mean() for r in runs])
    floor2 = first.floor_converged_m ** 2
    assert np.isfinite(first.floor_sigma_m).all() and floor2 > 0.0
    assert first.floor_converged_m < first.pcrb_converged_m  # (on this flight the κ rule is pessimistic)
    assert mse.mean() >= floor2 - 2.0 * mse.std(ddof=1) / math.sqrt(len(mse)), (mse.mean(), floor2)
