"""Sensors and measurement models: analytic ranges, NumPy references of residuals and likelihoods."""

import numpy as np
import pytest
import warp as wp

import warptan as wt
from warptan.nav.frames import euler_to_quat, quat_to_mat


def _poses(pos, quat, device):
    pos = np.atleast_2d(pos)
    quat = np.atleast_2d(quat)
    return (wp.array(pos.astype(np.float32), dtype=wp.vec3, device=device),
            wp.array(quat.astype(np.float32), dtype=wp.vec4, device=device))


# ---------------------------------------------------------------- sensors
def test_scan_patterns():
    """Presets give unit directions: a 10×10 grid spanning ±30°, a ring on its cone, the nadir ray."""
    g = wt.ScanPattern.grid(10, 10, 30.0)
    assert g.m == 100
    np.testing.assert_allclose(np.linalg.norm(g.dirs_s, axis=1), 1.0)
    along = np.degrees(np.arctan2(g.dirs_s[:, 0], g.dirs_s[:, 2]))
    assert along.min() == pytest.approx(-30.0) and along.max() == pytest.approx(30.0)
    ring = wt.ScanPattern.ring(16, 20.0)
    np.testing.assert_allclose(np.degrees(np.arccos(ring.dirs_s[:, 2])), 20.0)
    np.testing.assert_array_equal(wt.ScanPattern.nadir().dirs_s, [[0.0, 0.0, 1.0]])


@pytest.mark.parametrize(("dirs", "message"), [
    (np.zeros((0, 3)), "empty"),
    ([[0.0, 0.0, 0.0]], "zero-length"),
    ([[np.nan, 0.0, 1.0]], "non-finite"),
    ([[1.0, 2.0]], r"shape \(M, 3\)"),
])
def test_bad_patterns(dirs, message):
    """Empty patterns and degenerate directions are ValueErrors."""
    with pytest.raises(ValueError, match=message):
        wt.ScanPattern(dirs)


def test_point_cloud_on_a_plane_is_analytic(device):
    """Over a flat plane, a banked and pitched sensor measures r_j = altitude / (R d_j)_z exactly."""
    terrain = wt.Terrain.from_grid(np.full((50, 50), 120.0), spacing=50.0, origin=(-1250.0, -1250.0))
    pos = np.array([10.0, -20.0, -520.0])
    q = euler_to_quat(0.3, -0.1, 1.0)
    sensor = wt.PointCloudSensor(wt.ScanPattern.grid(5, 7, (25.0, 35.0)), range_sigma_m=0.0)
    cloud = sensor.measure(terrain, pos, q, device=device)
    expected = 400.0 / (sensor.pattern.dirs_s @ quat_to_mat(q).T)[:, 2]
    np.testing.assert_allclose(cloud.ranges_m, expected, rtol=2e-6)
    np.testing.assert_allclose(cloud.points_s[:, 2], cloud.ranges_m * sensor.pattern.dirs_s[:, 2])


def test_point_cloud_noise_and_invalid_points():
    """Range noise has the stated σ; rays that leave the map are invalid (NaN), never a range."""
    terrain = wt.Terrain.from_grid(np.full((20, 20), 0.0), spacing=50.0, origin=(-500.0, -500.0))
    sensor = wt.PointCloudSensor(wt.ScanPattern.grid(30, 30, 20.0), range_sigma_m=0.5)
    clean = sensor.measure(terrain, [0, 0, -500.0], [1, 0, 0, 0])
    noisy = sensor.measure(terrain, [0, 0, -500.0], [1, 0, 0, 0], rng=np.random.default_rng(0))
    assert np.nanstd(noisy.ranges_m - clean.ranges_m) == pytest.approx(0.5, rel=0.1)
    edge = sensor.measure(terrain, [400.0, 0, -500.0], [1, 0, 0, 0])
    assert 0 < edge.valid.sum() < sensor.pattern.m


def test_altimeter_and_barometer():
    """The altimeter measures -p_z - h(p), the barometer -p_z, each with its σ."""
    terrain = wt.Terrain.synthetic("rugged", size_m=3000.0, spacing=30.0, seed=2)
    p = np.array([100.0, -200.0, -1500.0])
    a = wt.RadarAltimeter(sigma_m=0.0).measure(terrain, p)
    assert a == pytest.approx(1500.0 - float(terrain.height_at(100.0, -200.0)))
    rng = np.random.default_rng(1)
    baro = np.array([wt.Barometer(sigma_m=2.0).measure(p, rng) for _ in range(4000)])
    assert baro.mean() == pytest.approx(1500.0, abs=0.2) and baro.std() == pytest.approx(2.0, rel=0.1)
    assert np.isnan(wt.RadarAltimeter().measure(terrain, [1e5, 0, -1000.0]))


# ---------------------------------------------------------------- models at and around the truth
def _truth_setup(terrain, seed=0):
    rng = np.random.default_rng(seed)
    centre_n, centre_e = 0.5 * (terrain.bounds_ne[0] + terrain.bounds_ne[1]), 0.5 * (
        terrain.bounds_ne[2] + terrain.bounds_ne[3])
    pos = np.array([centre_n, centre_e, -(np.nanmax(terrain.heights_m) + 600.0)])
    q = euler_to_quat(rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(-3, 3))
    cloud = wt.PointCloudSensor(wt.ScanPattern.grid(), range_sigma_m=0.0).measure(terrain, pos, q)
    return pos, q, cloud


def _check_truth_minimum(terrain, device, sliding_tol):
    pos, q, cloud = _truth_setup(terrain)
    offsets = np.array([0.0, 25.0, 50.0, 100.0, 200.0])
    poses = pos + np.stack([offsets, 0.6 * offsets, 0.1 * offsets], axis=1)
    p_dev, q_dev = _poses(poses, np.tile(q, (len(poses), 1)), device)
    errors = {}
    for model in (wt.SlidingModel(terrain), wt.SlidingModel(terrain, surface=True),
                  wt.RaycastModel(terrain, caster=wt.RayCaster("dda")),
                  wt.RaycastModel(terrain, caster=wt.RayCaster("mesh"))):
        err = model.evaluate(p_dev, q_dev, cloud).error_m.numpy()
        errors[(model.name, getattr(model, "surface", False))] = err
        assert np.all(np.diff(err) > 0), (model.name, err)  # grows with the pose error
        assert err[-1] > 5.0
    assert errors[("raycast", False)][0] < 0.01
    assert errors[("sliding", True)][0] < 0.01  # same surface as the ray casts: exact
    assert errors[("sliding", False)][0] < sliding_tol  # bilinear vs the triangulated truth


def test_sliding_and_raycast_vanish_at_the_truth_generated(device):
    """Zero noise: both errors are ~0 at the true pose and grow as the pose moves away (generated terrain)."""
    _check_truth_minimum(wt.Terrain.synthetic("rugged", size_m=8000.0, spacing=30.0, seed=5), device, 0.5)


def test_sliding_and_raycast_vanish_at_the_truth_real(device, thuringia):
    """The same on the real Thuringia SRTM3 tile."""
    _check_truth_minimum(thuringia, device, 1.0)


def _sliding_residual_reference(terrain, poses, quats, points):
    """Float64 NumPy version of eq. 14/16 for every (particle, point)."""
    out = np.empty((len(poses), len(points)))
    for i, (p, q) in enumerate(zip(poses, quats, strict=True)):
        mat = quat_to_mat(q)
        w = p + points @ mat.T
        h = terrain.height_at(w[:, 0], w[:, 1])
        w_hat = np.stack([w[:, 0], w[:, 1], -h], axis=1)
        c_hat = (w_hat - p) @ mat
        out[i] = points[:, 2] - c_hat[:, 2]
    return out


def _loglik_reference(res, lik, sigma=None):
    """Per-particle log-likelihoods of a residual matrix (NaN = invalid prediction), written out in NumPy;
    ``sigma`` (N, M) per-point σ (default ``lik.sigma_m``), each adding ``-log(σ_j / σ)``."""
    ok = np.isfinite(res)
    sigma = np.where(ok, lik.sigma_m if sigma is None else sigma, lik.sigma_m)
    r = np.where(ok, res, lik.outlier_sigmas * lik.sigma_m)
    z2 = (r / sigma) ** 2
    norm = np.log(sigma / lik.sigma_m)
    if lik.kind == "gaussian":
        return (-0.5 * z2 - norm).sum(axis=1)
    if lik.kind == "student_t":
        return (-0.5 * (lik.nu + 1) * np.log1p(z2 / lik.nu) - norm).sum(axis=1)
    err = np.nanmean(np.abs(res), axis=1)
    frac = ok.mean(axis=1)
    floor = -0.5 * lik.outlier_sigmas**2
    return np.where(ok.any(axis=1), frac * (-0.5 * err**2 / lik.r_err) + (1 - frac) * floor, floor)


def _nis_reference(res, lik, sigma=None):
    """Mean over the received points of min((r/σ_j)², k²), an unpredictable point counting k² (k = outlier_sigmas)."""
    k2 = lik.outlier_sigmas**2
    sigma = lik.sigma_m if sigma is None else sigma
    return np.where(np.isfinite(res), np.minimum((res / sigma) ** 2, k2), k2).mean(axis=1)


def _sliding_sigma_reference(terrain, poses, quats, points, sigma_range):
    """Float64 per-point σ of the sliding residuals: range noise along the ray ``u`` moves ``c_z - ĉ_z`` by
    ``g_z (∇F · u)`` times itself (∇F = (h_n, h_e, 1) of the bilinear map by central differences, g_z = R₂₂), with
    the kernel's floors |g_z| ≥ 0.2, |∇F · u| ≥ 0.25."""
    d = points / np.linalg.norm(points, axis=1, keepdims=True)
    out = np.empty((len(poses), len(points)))
    eps = 1e-3
    for i, (p, q) in enumerate(zip(poses, quats, strict=True)):
        mat = quat_to_mat(q)
        w = p + points @ mat.T
        h_n = (terrain.height_at(w[:, 0] + eps, w[:, 1]) - terrain.height_at(w[:, 0] - eps, w[:, 1])) / (2 * eps)
        h_e = (terrain.height_at(w[:, 0], w[:, 1] + eps) - terrain.height_at(w[:, 0], w[:, 1] - eps)) / (2 * eps)
        u = d @ mat.T
        slope_dot = u[:, 2] + h_n * u[:, 0] + h_e * u[:, 1]
        out[i] = max(abs(mat[2, 2]), 0.2) * sigma_range * np.maximum(np.abs(slope_dot), 0.25)
    return out


@pytest.mark.parametrize("kind", ["paper", "gaussian", "student_t"])
def test_sliding_loglik_matches_numpy(kind, device):
    """Sliding residuals and all three likelihoods equal a float64 NumPy computation of the same formulas,
    including particles partly off the map (their points score as outliers, no NaN)."""
    terrain = wt.Terrain.synthetic("rugged", size_m=4000.0, spacing=30.0, seed=6)
    pos, _, cloud = _truth_setup(terrain)
    rng = np.random.default_rng(2)
    n = 64
    poses = pos + rng.normal(0, [40, 40, 10], (n, 3))
    poses[:4, 0] += 1800.0  # near or over the northern edge: some points off the map
    quats = euler_to_quat(rng.normal(0, 0.01, n), rng.normal(0, 0.01, n), rng.normal(0, 0.01, n) + 0.3)
    # A point within float32 rounding of the map edge is on it or off it by chance: move such particles 7 m (the
    # float64 validity must not change under a 1 cm shift), so the validity of every point is decided.
    for _ in range(10):
        valid = [np.isfinite(_sliding_residual_reference(terrain, poses + d, quats, cloud.points_s))
                 for d in ([0, 0, 0], [0.01, 0.01, 0], [-0.01, -0.01, 0])]
        unsure = ((valid[0] != valid[1]) | (valid[0] != valid[2])).any(axis=1)
        if not unsure.any():
            break
        poses[unsure, 0] -= 7.0
    assert not unsure.any()
    lik = wt.Likelihood(kind, r_err=4.0, sigma_m=3.0, nu=5.0)
    out = wt.SlidingModel(terrain, lik).evaluate(*_poses(poses, quats, device), cloud)
    ref_res = _sliding_residual_reference(terrain, poses, quats, cloud.points_s)
    got_res = out.residual_m.numpy()
    assert np.isnan(ref_res).any() and np.isfinite(ref_res).any(axis=1).all()
    np.testing.assert_array_equal(np.isnan(got_res), np.isnan(ref_res))
    ok = np.isfinite(ref_res)
    np.testing.assert_allclose(got_res[ok], ref_res[ok], atol=2e-3)
    sigma = _sliding_sigma_reference(terrain, poses, quats, cloud.points_s, lik.sigma_m)
    np.testing.assert_allclose(out.loglik.numpy(), _loglik_reference(ref_res, lik, sigma), rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(out.nis.numpy(), _nis_reference(ref_res, lik, sigma), rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(out.n_valid.numpy(), np.isfinite(ref_res).sum(axis=1))
    assert np.isfinite(out.loglik.numpy()).all()


def test_sliding_sigma_is_the_range_noise_propagated(device, thuringia_crop):
    """At the true pose the sliding model's NIS is ≈ 1 when the range noise is the only error, also banked 60° at
    low altitude: each point's σ is the range σ propagated to its residual (``|g_z (∇F · u)| σ_range``), not the
    range σ itself (which made the NIS ≈ 0.1 in S6's geometry: bounds 3–4× too wide)."""
    thuringia = thuringia_crop
    pos, _, _ = _truth_setup(thuringia, seed=2)
    pos[2] = -(float(thuringia.height_at(pos[0], pos[1])) + 200.0)
    sensor = wt.PointCloudSensor(wt.ScanPattern.grid(10, 10, 30.0), range_sigma_m=0.5)
    rng = np.random.default_rng(7)
    for bank in (0.0, 60.0):
        q = euler_to_quat(np.radians(bank), 0.02, 0.7)
        model = wt.SlidingModel(thuringia, wt.Likelihood("gaussian", sensor_sigma_m=0.5), surface=True)
        nis = [model.evaluate(*_poses(pos[None], q[None], device), sensor.measure(thuringia, pos, q, rng=rng)).nis
               .numpy()[0] for _ in range(30)]
        assert 0.85 < np.mean(nis) < 1.15, (bank, np.mean(nis))


def test_paper_likelihood_never_rewards_unpredictable_points(device):
    """A particle that can predict only part of the scan (over the map edge) scores no better than the same fit
    with every point predicted: the paper form blends in the floor for the missing points."""
    terrain = wt.Terrain.synthetic("rugged", size_m=4000.0, spacing=30.0, seed=6)
    pos, q, cloud = _truth_setup(terrain)
    poses = np.stack([pos, pos + np.array([1800.0, 0.0, 0.0])])
    model = wt.SlidingModel(terrain, wt.Likelihood("paper", r_err=4.0))
    out = model.evaluate(*_poses(poses, np.tile(q, (2, 1)), device), cloud)
    n_valid = out.n_valid.numpy()
    assert n_valid[0] == cloud.valid.sum() and 0 < n_valid[1] < n_valid[0]
    assert out.loglik.numpy()[1] < out.loglik.numpy()[0]


def test_calibrated_sigma(thuringia):
    """sigma_m=None is sqrt(sensor² + map² + the model's surface mismatch); the mismatch is the RMS of the
    bilinear-minus-triangles difference (checked against dense sampling of both surfaces), 0 for ray casts."""
    t = thuringia
    lik = wt.Likelihood("gaussian", sensor_sigma_m=0.5, map_sigma_m=1.0)
    mism = t.bilinear_mismatch_sigma_m
    rng = np.random.default_rng(0)
    n0, n1, e0, e1 = t.bounds_ne
    north, east = rng.uniform(n0, n1, 400_000), rng.uniform(e0, e1, 400_000)
    diff = t.height_at(north, east) - t.surface_height_at(north, east)
    assert mism == pytest.approx(np.sqrt(np.nanmean(diff**2)), rel=0.02)
    assert wt.SlidingModel(t, lik).sigma_m == pytest.approx(np.sqrt(0.25 + 1.0 + mism**2))
    assert wt.RaycastModel(t, lik).sigma_m == pytest.approx(np.sqrt(1.25))
    assert wt.SlidingModel(t, wt.Likelihood("gaussian", sigma_m=2.0)).sigma_m == 2.0


def test_raycast_paper_error_matches_numpy(device):
    """The raycast model's error is eq. 15 on the range residuals: sqrt(sum_axis (mean_j |dr_j| |d_j,axis|)^2)."""
    terrain = wt.Terrain.synthetic("rugged", size_m=4000.0, spacing=30.0, seed=6)
    pos, q, cloud = _truth_setup(terrain)
    rng = np.random.default_rng(3)
    poses = pos + rng.normal(0, 30, (16, 3))
    quats = np.tile(q, (16, 1))
    out = wt.RaycastModel(terrain, wt.Likelihood("paper", r_err=2.0)).evaluate(*_poses(poses, quats, device), cloud)
    dirs_n = cloud.dirs_s @ quat_to_mat(q).T
    t = wt.raycast(terrain, np.repeat(poses, len(dirs_n), 0), np.tile(dirs_n, (16, 1)), backend="dda").reshape(16, -1)
    res = cloud.ranges_m - t
    ref_err = np.linalg.norm(np.nanmean(np.abs(res)[:, :, None] * np.abs(cloud.dirs_s)[None], axis=1), axis=1)
    np.testing.assert_allclose(out.error_m.numpy(), ref_err, rtol=1e-4, atol=2e-3)
    np.testing.assert_allclose(out.loglik.numpy(), -0.5 * ref_err**2 / 2.0, rtol=1e-3, atol=1e-3)


def test_all_points_invalid_gives_floor_and_flag(device):
    """A cloud whose every point is invalid (NaN samples) gives every particle the same score and the flag."""
    terrain = wt.Terrain.synthetic("rugged", size_m=3000.0, spacing=30.0, seed=1)
    cloud = wt.PointCloud.from_points(np.full((25, 3), np.nan))
    p_dev, q_dev = _poses(np.tile([0.0, 0.0, -2000.0], (10, 1)), np.tile([1.0, 0, 0, 0], (10, 1)), device)
    for model in (wt.SlidingModel(terrain), wt.RaycastModel(terrain)):
        out = model.evaluate(p_dev, q_dev, cloud)
        assert out.all_points_invalid
        ll = out.loglik.numpy()
        assert np.isfinite(ll).all() and np.ptp(ll) == 0.0


def test_nan_samples_are_excluded(device):
    """NaN samples in a received cloud are ignored: same score as the cloud without them."""
    terrain = wt.Terrain.synthetic("rugged", size_m=4000.0, spacing=30.0, seed=6)
    pos, q, cloud = _truth_setup(terrain)
    pts = cloud.points_s.copy()
    pts[::7] = np.nan
    holed = wt.PointCloud.from_points(pts)
    kept = wt.PointCloud.from_points(pts[np.isfinite(pts[:, 0])])
    p_dev, q_dev = _poses(pos + np.array([[0, 0, 0], [30.0, 10.0, 0]]), np.tile(q, (2, 1)), device)
    lik = wt.Likelihood("gaussian", sigma_m=2.0)
    a = wt.SlidingModel(terrain, lik).evaluate(p_dev, q_dev, holed).loglik.numpy()
    b = wt.SlidingModel(terrain, lik).evaluate(p_dev, q_dev, kept).loglik.numpy()
    np.testing.assert_allclose(a, b, rtol=1e-5)


def test_staged_cloud_rows_are_the_clouds(device):
    """The staged rows (the ranges uploaded, a kernel writing the rows) are each cloud's point ``r d`` (0 where
    invalid), direction, range and validity, and its meta row (received points, log-likelihood floor), as NumPy builds
    them: for a batch sharing one pattern, for clouds with their own directions (``PointCloud.from_points``), and again
    after the batch changes (one filter, with and without a lost point)."""
    from warptan.kernels import likelihood as klik

    rng = np.random.default_rng(3)
    terrain = wt.Terrain.synthetic("rugged", size_m=4000.0, spacing=30.0, seed=6)
    pattern = wt.ScanPattern.grid(4, 3, 25.0)
    shared = [wt.PointCloud(pattern.dirs_s, rng.uniform(500.0, 900.0, pattern.m)) for _ in range(3)]
    shared[1].ranges_m[[0, 5]] = np.nan
    below = np.array([0.0, 0.0, 700.0])
    own = [wt.PointCloud.from_points(rng.normal(0.0, 300.0, (pattern.m, 3)) + below) for _ in range(3)]
    own[2].ranges_m[4] = np.nan
    model = wt.SlidingModel(terrain, wt.Likelihood("gaussian", sigma_m=2.0))
    k_out = model.likelihood.outlier_sigmas
    for clouds in (shared, own, shared[:1], own[2:]):
        n = 2 * len(clouds)
        pos = wp.array(np.zeros((n, 3), np.float32), dtype=wp.vec3, device=device)
        quat = wp.array(np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)).astype(np.float32), dtype=wp.vec4, device=device)
        out = model.stage(clouds if len(clouds) > 1 else clouds[0], pos, quat)
        rows, meta = model._staged.numpy(), out.meta.numpy()
        for k, cloud in enumerate(clouds):
            r = cloud.ranges_m.astype(np.float32)
            ok = np.isfinite(r)
            d = cloud.dirs_s.astype(np.float32)
            np.testing.assert_allclose(rows[k, :, klik.CR_POINT:klik.CR_POINT + 3],
                                       np.where(ok[:, None], r[:, None] * d, 0.0), rtol=1e-6, atol=1e-4)
            np.testing.assert_array_equal(rows[k, :, klik.CR_DIR:klik.CR_DIR + 3], d)
            np.testing.assert_array_equal(rows[k, :, klik.CR_RANGE], r)
            np.testing.assert_array_equal(rows[k, :, klik.CR_VALID], ok.astype(np.float32))
            assert out.n_received[k] == ok.sum()
            np.testing.assert_array_equal(meta[k], np.array([ok.sum(), -0.5 * k_out * k_out * max(1, ok.sum())],
                                                            dtype=np.float32))


def test_stage_after_check_validates_what_it_stages(device):
    """``stage`` validates what it stages whatever ``check`` saw before (another measurement: a wrong type, a batch of
    unequal clouds, is refused); pose arrays are checked again whenever they are not the pair ``stage`` last accepted
    (a shape or dtype mismatch raises)."""
    rng = np.random.default_rng(8)
    terrain = wt.Terrain.synthetic("rugged", size_m=4000.0, spacing=30.0, seed=6)
    pattern = wt.ScanPattern.grid(4, 3, 25.0)
    cloud = wt.PointCloud(pattern.dirs_s, rng.uniform(500.0, 900.0, pattern.m))
    short = wt.PointCloud(pattern.dirs_s[:5], rng.uniform(500.0, 900.0, 5))
    model = wt.SlidingModel(terrain, wt.Likelihood("gaussian", sigma_m=2.0))
    pos, quat = _poses(np.zeros((4, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (4, 1)), device)
    model.check(cloud)
    with pytest.raises(wt.FilterError, match="needs a PointCloud"):
        model.stage(wt.AltimeterReading(700.0, 0.0), pos, quat)
    model.check([cloud, cloud])
    with pytest.raises(wt.FilterError, match="same number of points"):
        model.stage([cloud, short], pos, quat)
    model.check(cloud)
    assert model.stage(cloud, pos, quat).n_received.tolist() == [pattern.m]
    assert model.stage(cloud, pos, quat).n_received.tolist() == [pattern.m]  # (without a check before it)
    pos3, quat3 = _poses(np.zeros((3, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (4, 1)), device)
    with pytest.raises(wt.FilterError, match="shape"):
        model.stage(cloud, pos3, quat3)
    with pytest.raises(wt.FilterError, match="vec3 positions"):
        model.stage(cloud, quat, quat)


def test_held_staging_runs_when_released(device):
    """``hold_device_work``: a scan staged while the model holds leaves the staged rows as they were (its rows' launch,
    and on CUDA its copies, are handed back instead of queued); running what ``release_device_work`` returns, in
    order, stages it exactly as an unheld ``stage`` does. Not holding, nothing is held."""
    rng = np.random.default_rng(5)
    terrain = wt.Terrain.synthetic("rugged", size_m=4000.0, spacing=30.0, seed=6)
    pattern = wt.ScanPattern.grid(4, 3, 25.0)
    first, second = ([wt.PointCloud(pattern.dirs_s.copy(), rng.uniform(500.0, 900.0, pattern.m)) for _ in range(2)]
                     for _ in range(2))
    pos = wp.array(np.zeros((4, 3), np.float32), dtype=wp.vec3, device=device)
    quat = wp.array(np.tile([1.0, 0.0, 0.0, 0.0], (4, 1)).astype(np.float32), dtype=wp.vec4, device=device)
    model = wt.SlidingModel(terrain, wt.Likelihood("gaussian", sigma_m=2.0))
    reference = wt.SlidingModel(terrain, wt.Likelihood("gaussian", sigma_m=2.0))
    model.stage(first, pos, quat)
    before = model._staged.numpy().copy()
    assert model.release_device_work() == [] and not model._uploads.later(lambda: None)
    model.hold_device_work({})
    model.stage(second, pos, quat)
    held = model.release_device_work()
    assert held and all(callable(work) for work in held)
    np.testing.assert_array_equal(model._staged.numpy(), before)  # nothing ran yet
    for work in held:
        work()
    reference.stage(second, pos, quat)
    np.testing.assert_array_equal(model._staged.numpy(), reference._staged.numpy())
    assert not np.array_equal(model._staged.numpy(), before)


def test_altimeter_model(device):
    """Altimeter residual a - (h_baro - h(p_i)) matches NumPy, plus the barometer's altitude term; an off-map
    particle gets the floor (no NaN); without a barometer each particle's own altitude is used."""
    terrain = wt.Terrain.synthetic("rugged", size_m=3000.0, spacing=30.0, seed=2)
    poses = np.array([[0.0, 0.0, -1500.0], [200.0, -300.0, -1504.0], [1e5, 0.0, -1500.0]])
    quats = np.tile([1.0, 0, 0, 0], (3, 1))
    reading = wt.AltimeterReading(range_m=700.0, baro_alt_m=1490.0)
    lik = wt.Likelihood("paper", r_err=9.0)
    out = wt.AltimeterModel(terrain, lik, baro_sigma_m=2.0).evaluate(*_poses(poses, quats, device), reading)
    h = terrain.height_at(poses[:, 0], poses[:, 1])
    ref = 700.0 - (1490.0 - h)
    baro_term = -0.5 * ((1490.0 + poses[:, 2]) / 2.0) ** 2
    np.testing.assert_allclose(out.error_m.numpy()[:2], ref[:2], atol=1e-3)
    ll = out.loglik.numpy()
    np.testing.assert_allclose(ll[:2], -0.5 * ref[:2] ** 2 / 9.0 + baro_term[:2], rtol=1e-4)
    assert ll[2] == pytest.approx(-0.5 * lik.outlier_sigmas**2 + baro_term[2])
    no_baro = wt.AltimeterModel(terrain, lik, use_baro=False).evaluate(*_poses(poses, quats, device),
                                                                         wt.AltimeterReading(700.0))
    np.testing.assert_allclose(no_baro.error_m.numpy()[:2], (700.0 - (-poses[:, 2] - h))[:2], atol=1e-3)
    assert not no_baro.all_points_invalid


def test_bad_model_arguments():
    """Unknown model/likelihood names and wrong measurement types are clear ValueErrors."""
    terrain = wt.Terrain.synthetic("flat", size_m=1000.0, spacing=50.0)
    with pytest.raises(ValueError, match="unknown measurement model 'lidar'"):
        wt.make_model("lidar", terrain)
    with pytest.raises(ValueError, match="unknown likelihood 'cauchy'"):
        wt.Likelihood("cauchy")
    with pytest.raises(ValueError, match="r_err must be a positive"):
        wt.Likelihood(r_err=0.0)
    p, q = _poses([[0, 0, -500.0]], [[1.0, 0, 0, 0]], "cpu")
    with pytest.raises(ValueError, match="needs a PointCloud"):
        wt.SlidingModel(terrain).evaluate(p, q, wt.AltimeterReading(1.0, 2.0))
    with pytest.raises(ValueError, match="shape"):
        cloud = wt.PointCloud.from_points([[0, 0, 1.0]])
        wt.SlidingModel(terrain).evaluate(p, wp.zeros(2, dtype=wp.vec4, device="cpu"), cloud)


def test_attitude_marginal_matches_numpy(device):
    """The per-point Gaussian marginalised over the attitude uncertainty A equals a float64 NumPy computation:
    residuals r_j of the sliding model with their per-point σ_j (:func:`_sliding_sigma_reference`), Jacobians H_j
    w.r.t. dθ by central finite differences of the same model (q ⊗ Exp(dθ); the marginal is even in the sign of
    H), ``Σ (-0.5 r²/σ_j² - log(σ_j/σ)) + 0.5 bᵀ A (I + ΛA)⁻¹ b - 0.5 log det(I + AΛ)``; A = 0 (no attitude
    covariance bound) gives the plain sum. The NIS is the same marginal's Mahalanobis form, ``min(Σ min(z², k²), Σ z²
    − bᵀ A (I + ΛA)⁻¹ b) / n``: a particle whose attitude error lies within A is not judged lost for it."""
    from warptan.nav.frames import quat_exp, quat_mul

    terrain = wt.Terrain.synthetic("rugged", size_m=4000.0, spacing=30.0, seed=6)
    pos, q, cloud = _truth_setup(terrain)
    rng = np.random.default_rng(3)
    poses = pos + rng.normal(0, [6.0, 6.0, 2.0], (8, 3))
    quats = np.array([quat_mul(q, quat_exp(rng.normal(0, 0.002, 3))) for _ in poses])
    sigma = 0.7
    att = np.diag(np.radians([0.1, 0.1, 0.5]) ** 2)
    model = wt.SlidingModel(terrain, wt.Likelihood("gaussian", sigma_m=sigma))
    points = cloud.points_s[cloud.valid]

    def residuals(p, qq):
        mat = quat_to_mat(qq)
        w = p + points @ mat.T
        c_hat = (np.stack([w[:, 0], w[:, 1], -terrain.height_at(w[:, 0], w[:, 1])], axis=1) - p) @ mat
        return points[:, 2] - c_hat[:, 2]

    expected = {}
    k2 = model.likelihood.outlier_sigmas**2
    for label, a in (("zero", np.zeros((3, 3))), ("prior", att)):
        ll, nis = [], []
        for p, qq in zip(poses, quats, strict=True):
            r = residuals(p, qq)
            sig = _sliding_sigma_reference(terrain, [p], [qq], points, sigma)[0]
            h = np.stack([(residuals(p, quat_mul(qq, quat_exp(e))) - residuals(p, quat_mul(qq, quat_exp(-e)))) / 2e-5
                          for e in 1e-5 * np.eye(3)], axis=1)
            lam, b = h.T @ (h / sig[:, None] ** 2), h.T @ (r / sig**2)
            m = np.eye(3) + lam @ a
            ll.append(np.sum(-0.5 * (r / sig) ** 2 - np.log(sig / sigma)) + 0.5 * b @ a @ np.linalg.solve(m, b)
                      - 0.5 * np.log(np.linalg.det(m)))
            z2 = (r / sig) ** 2
            nis.append(min(np.minimum(z2, k2).sum(), max(z2.sum() - b @ a @ np.linalg.solve(m, b), 0.0)) / len(r))
        expected[label] = np.array(ll)
        cov = wp.array(a[None].astype(np.float32), dtype=wp.mat33, device=device)
        model.bind_attitude_cov(cov if label == "prior" else None)
        out = model.evaluate(*_poses(poses, quats, device), cloud)
        np.testing.assert_allclose(out.loglik.numpy(), expected[label], rtol=2e-3, atol=0.05)
        np.testing.assert_allclose(out.nis.numpy(), nis, rtol=5e-3, atol=5e-3)
        expected[label + " nis"] = np.array(nis)
    assert np.abs(expected["prior"] - expected["zero"]).min() > 1.0  # the attitude term is not negligible here
    # the attitude explains part of the misfit (particles whose misfit the clipped sum caps keep it)
    assert np.all(expected["prior nis"] <= expected["zero nis"]) and np.sum(
        expected["prior nis"] < expected["zero nis"] - 0.5) >= 4


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"map_correlation": 0.5}, "map_correlation must be a number ≥ 1"),
    ({"sensor_sigma_m": -1.0}, "sensor_sigma_m must be a number ≥ 0"),
    ({"map_sigma_m": float("nan")}, "map_sigma_m must be a number ≥ 0"),
    ({"sigma_m": 0.0}, "sigma_m must be a positive number"),
])
def test_bad_likelihood_parameters(kwargs, message):
    """Likelihood parameters out of range are one clear error naming the parameter."""
    with pytest.raises(ValueError, match=message):
        wt.Likelihood("gaussian", **kwargs)


def _fd_jacobians(model, poses, quats, cloud, eps_att=2e-4, eps_pos=0.05):
    """(residuals (N, M), H (N, M, 3) w.r.t. dθ, G (N, M, 3) w.r.t. the position): the prediction's Jacobians by
    central finite differences of the model's own residuals (``q ⊗ Exp(±ε e_k)``, ``p ± ε e_k``)."""
    from warptan.nav.frames import quat_exp, quat_mul

    def res(p, q):
        return model.evaluate(*_poses(p, q, "cpu"), cloud).residual_m.numpy().astype(np.float64)

    r0 = res(poses, quats)
    h = [-(res(poses, np.array([quat_mul(q, quat_exp(e)) for q in quats]))
           - res(poses, np.array([quat_mul(q, quat_exp(-e)) for q in quats]))) / (2 * eps_att)
         for e in eps_att * np.eye(3)]
    g = [-(res(poses + e, quats) - res(poses - e, quats)) / (2 * eps_pos) for e in eps_pos * np.eye(3)]
    return r0, np.stack(h, axis=2), np.stack(g, axis=2)


@pytest.mark.parametrize("model_name", ["sliding", "raycast"])
def test_attitude_information_matches_finite_differences(thuringia_crop, model_name):
    """Each particle's attitude information on a real DEM (the package's Thuringia 90 m crop) from the kernels'
    analytic Jacobians (sliding: terrain gradient and lever arm; ray casts: the range's derivative along the ray)
    equals a float64 NumPy computation with H (w.r.t. dθ) and G (w.r.t. the position) from central finite
    differences of the model's own residuals and the per-point σ_j (sliding: :func:`_sliding_sigma_reference`; ray
    casts: σ): unprojected (``project_position=False``) ``Λ = Σ HᵀH/σ_j²``, ``b = Σ Hᵀr/σ_j²``; projected (the
    default) the Schur complement ``Λ - Λ_θp (Λ_pp + πI)⁻¹ Λ_pθ``, ``b - Λ_θp (Λ_pp + πI)⁻¹ b_p`` (float32
    kernels: 3 % of the largest entry; 6 % for the projected Λ, a difference of large terms)."""
    from warptan.nav.frames import quat_exp, quat_mul
    from warptan.sensing.likelihood import POSITION_PRIOR_PRECISION

    thuringia = thuringia_crop
    pos, q, cloud = _truth_setup(thuringia, seed=4)
    rng = np.random.default_rng(5)
    poses = pos + rng.normal(0, [8.0, 8.0, 2.0], (4, 3))
    quats = np.array([quat_mul(q, quat_exp(rng.normal(0, 0.003, 3))) for _ in poses])
    sigma = 0.8
    got = {}
    for project in (False, True):
        model = wt.make_model(model_name, thuringia, wt.Likelihood("gaussian", sigma_m=sigma,
                                                                   project_position=project))
        out = model.evaluate(*_poses(poses, quats, "cpu"), cloud)
        got[project] = (out.lam.numpy().astype(np.float64), out.info.numpy().astype(np.float64))
    res, h, g = _fd_jacobians(model, poses, quats, cloud)
    sig = (_sliding_sigma_reference(thuringia, poses, quats, cloud.points_s, sigma) if model_name == "sliding"
           else np.full(res.shape, sigma))
    ok = np.isfinite(res) & np.isfinite(h).all(axis=2) & np.isfinite(g).all(axis=2)
    assert ok.sum(axis=1).min() > 50
    for i in range(len(poses)):
        hi, gi, ri, wi = h[i][ok[i]], g[i][ok[i]], res[i][ok[i]], 1.0 / sig[i][ok[i]] ** 2
        lam, b = hi.T @ (hi * wi[:, None]), hi.T @ (ri * wi)
        lam_tp, lam_pp, b_p = hi.T @ (gi * wi[:, None]), gi.T @ (gi * wi[:, None]), gi.T @ (ri * wi)
        k = lam_tp @ np.linalg.inv(lam_pp + POSITION_PRIOR_PRECISION * np.eye(3))
        lam_s, b_s = lam - k @ lam_tp.T, b - k @ b_p
        np.testing.assert_allclose(got[False][0][i], lam, atol=0.03 * np.abs(lam).max())
        np.testing.assert_allclose(got[False][1][i], b, atol=0.03 * np.abs(b).max() + 1.0)
        np.testing.assert_allclose(got[True][0][i], lam_s, atol=0.06 * np.abs(lam_s).max())
        np.testing.assert_allclose(got[True][1][i], b_s, atol=0.06 * np.abs(b_s).max() + 1.0)
        # what the projection removes is real: the position explains part of the attitude information
        assert np.trace(lam_s) < 0.95 * np.trace(lam)
    assert np.abs(got[False][0]).max() > 1e4  # a 650 m lever: the scan sees the attitude strongly (rad⁻²)


def test_attitude_information_follows_the_likelihood(device):
    """The paper likelihood gives no attitude information (its filter keeps C = 0); the footprint correlation
    scales the per-point Gaussian's Λ and b by ``(σ/σ_att)²``."""
    terrain = wt.Terrain.synthetic("rugged", size_m=4000.0, spacing=30.0, seed=6)
    pos, q, cloud = _truth_setup(terrain)
    poses = pos + np.array([[3.0, -2.0, 1.0]])
    got = {}
    for label, lk in (("paper", wt.Likelihood("paper", r_err=16.0)),
                      ("plain", wt.Likelihood("gaussian", sensor_sigma_m=0.5, map_sigma_m=0.3, map_correlation=4.0)),
                      ("footprint", wt.Likelihood("gaussian", sensor_sigma_m=0.5, map_sigma_m=0.3, map_correlation=4.0,
                                                  footprint_correlation=40.0))):
        model = wt.SlidingModel(terrain, lk)
        out = model.evaluate(*_poses(poses, q[None], device), cloud)
        got[label] = (out.lam.numpy()[0].copy(), out.info.numpy()[0].copy(), model)
    assert not got["paper"][0].any() and not got["paper"][1].any()
    model = got["footprint"][2]
    scale = (model.sigma_m / model.likelihood.sigma_att(model.surface_mismatch_m())) ** 2
    assert 0.05 < scale < 0.5
    np.testing.assert_allclose(got["footprint"][0], scale * got["plain"][0], rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(got["footprint"][1], scale * got["plain"][1], rtol=1e-4, atol=1e-3)


def test_altimeter_scores_a_particle_for_its_kernel(device):
    """Bound to a regularisation kernel K (the filter's ``h · chol(Σ̂)``), the altimeter scores each particle with
    the mean and variance of the map's height over K: on a plane h = c + g·p (bilinear exact) the mean is h(p) and
    the variance gᵀ K g, so the log-likelihood is ``-r²/2(σ² + gᵀKg) - log(sqrt(σ² + gᵀKg)/σ)`` plus the barometer's
    term, and the position information ``g gᵀ / (σ² + gᵀKg)`` (NumPy). The paper's scalar error ignores K; an
    unbound model scores the point particle."""
    n, e = np.meshgrid(np.arange(-40, 41) * 30.0, np.arange(-40, 41) * 30.0, indexing="ij")
    g = np.array([0.3, -0.2])
    plane = wt.Terrain(100.0 + g[0] * n + g[1] * e, -1200.0, -1200.0, 30.0, 30.0, name="plane")
    poses = np.array([[0.0, 0.0, -1500.0], [210.0, -330.0, -1503.0], [-400.0, 120.0, -1497.0]])
    quats = np.tile([1.0, 0, 0, 0], (3, 1))
    reading = wt.AltimeterReading(range_m=1400.0, baro_alt_m=1499.0)
    chol = np.array([[20.0, 0, 0], [5.0, 10.0, 0], [1.0, 2.0, 3.0]])
    kxy = (chol @ chol.T)[:2, :2]
    h = 100.0 + poses[:, :2] @ g
    res = 1400.0 - (1499.0 - h)
    baro_term = -0.5 * ((1499.0 + poses[:, 2]) / 2.0) ** 2
    model = wt.AltimeterModel(plane, wt.Likelihood("gaussian", sigma_m=1.5), baro_sigma_m=2.0)
    sigma = model.params().sigma
    plain = model.evaluate(*_poses(poses, quats, device), reading)
    np.testing.assert_allclose(plain.loglik.numpy(), -0.5 * res**2 / sigma**2 + baro_term, rtol=1e-4)
    model.bind_particle_kernel(wp.array(chol[None].astype(np.float32), dtype=wp.mat33, device=device))
    out = model.evaluate(*_poses(poses, quats, device), reading)
    var = sigma**2 + g @ kxy @ g
    np.testing.assert_allclose(out.error_m.numpy(), res, atol=2e-3)
    np.testing.assert_allclose(out.loglik.numpy(), -0.5 * res**2 / var - 0.5 * np.log(var / sigma**2) + baro_term,
                               rtol=1e-4)
    np.testing.assert_allclose(out.info_pos.numpy(), np.tile([g[0] ** 2, g[1] ** 2, g[0] * g[1]], (3, 1)) / var,
                               rtol=1e-4)
    paper = wt.AltimeterModel(plane, wt.Likelihood("paper", r_err=9.0), baro_sigma_m=2.0)
    paper.bind_particle_kernel(wp.array(chol[None].astype(np.float32), dtype=wp.mat33, device=device))
    np.testing.assert_allclose(paper.evaluate(*_poses(poses, quats, device), reading).loglik.numpy(),
                               -0.5 * res**2 / 9.0 + baro_term, rtol=1e-4)
