"""The CPU's kernels with the points as SIMD lanes (kernels/simd.py, kernels/simd_ray.py) against the Warp kernels they
stand in for (kernels/sliding.py, kernels/likelihood.py, kernels/raycast.py: one thread per particle, point by point):
the same residuals (and ray casts) bit for bit, the same counts, the sums within float32 reassociation, on every branch
of the per-point path."""

import numpy as np
import pytest
import warp as wp

import warptan as wt
from warptan.kernels import likelihood as klik
from warptan.kernels import raycast as kray
from warptan.kernels import simd as ksimd
from warptan.kernels import simd_ray as ksimd_ray
from warptan.kernels import sliding as kslide
from warptan.nav.frames import euler_to_quat, quat_to_mat

DEVICE = "cpu"


def _terrain():
    """Rugged 30 m map with a nodata hole (the points that land in it, or off the map, are not predictable)."""
    t = wt.Terrain.synthetic("rugged", size_m=3000.0, spacing=30.0, seed=4)
    heights = t.heights_m.copy()
    heights[40:46, 50:58] = np.nan
    return wt.Terrain.from_grid(heights, spacing=30.0, origin=(t.bounds_ne[0], t.bounds_ne[2]))


def _cloud(terrain, truth, quat, m: int, rng):
    """Scans of ``m`` random rays measured at each ``truth`` pose (0.5 m range noise), as the staged rows ``[c, d,
    range, valid]``; a ray off the map and one in seven more are not received (zero point, NaN range)."""
    dirs = np.column_stack([rng.uniform(-0.7, 0.7, m), rng.uniform(-0.7, 0.7, m), np.ones(m)])
    sensor = wt.PointCloudSensor(wt.ScanPattern(dirs), range_sigma_m=0.5)
    rows = np.zeros((len(truth), m, 8), np.float32)
    for f, (p, q) in enumerate(zip(truth, quat, strict=True)):
        c = sensor.measure(terrain, p, q, rng=rng)
        valid = c.valid & (rng.random(m) > 1.0 / 7.0)
        rows[f, :, :3] = np.where(valid[:, None], c.points_s, 0.0)
        rows[f, :, 3:6] = sensor.pattern.dirs_s
        rows[f, :, 6] = np.where(valid, c.ranges_m, np.nan)
        rows[f, :, 7] = valid
    return wp.array(rows, dtype=klik.cloud_row, device=DEVICE)


def _params(lik: int, sigma: float, sigma_range: float, sigma_map: float, sigma_err: float):
    p = klik.LikParams()
    p.err_kind, p.lik, p.r_err, p.sigma, p.nu, p.k_out = klik.ERR_MEAN_ABS, lik, 4.0, sigma, 5.0, 3.0
    p.att_scale, p.pos_precision = 1.0, 1.0e-4
    p.sigma_range, p.sigma_map, p.n_modes, p.sigma_err = sigma_range, sigma_map, 0, sigma_err
    return p


def _outputs(n: int):
    """error, loglik, nis, points used, Λ, b, mode posteriors."""
    return [wp.zeros(n, dtype=t, device=DEVICE) for t in (wp.float32, wp.float32, wp.float32, wp.int32, wp.mat33,
                                                          wp.vec3, klik.modes_vec)]


def _modes(n: int, simd: bool = False):
    """The mode arrays of a launch without modes (and the SIMD kernels' unused scratch row)."""
    z = wp.zeros(1, dtype=klik.modes_vec, device=DEVICE)
    scratch = [wp.zeros(1, dtype=klik.modes_sums_vec, device=DEVICE)] if simd else []
    return [z, wp.zeros(n, dtype=klik.modes_vec, device=DEVICE), z, *scratch]


def _run(kernel, terrain, surface, params, pos, quat, cloud, att, simd=False):
    n, m, b = pos.shape[0], cloud.shape[1], cloud.shape[0]
    outs = [wp.full((n, m), 7.0, dtype=wp.float32, device=DEVICE), *_outputs(n)]
    wp.launch(kernel, dim=n, inputs=[0, n // b, terrain.grid(DEVICE), surface, pos, quat, cloud, att, params,
                                     *_modes(n, simd)], outputs=outs, device=DEVICE)
    return [o.numpy() for o in outs[:7]]


def _assert_sums_equal(got, ref, lik):
    """Counts exactly; error, log-likelihood, NIS, Λ and b to float32 reassociation (NaN where NaN)."""
    np.testing.assert_array_equal(got[3], ref[3])  # points used
    for name, k in (("error", 0), ("loglik", 1), ("nis", 2), ("lam", 4), ("info", 5)):
        scale = np.nanmax(np.abs(ref[k]))
        np.testing.assert_allclose(got[k], ref[k], rtol=1e-4, atol=1e-5 * scale, err_msg=name)
        assert np.isfinite(got[k]).all() or name == "error", name  # the error of a particle with no point: NaN
    if lik == klik.LIK_PAPER:
        assert not got[4].any() and not got[5].any()
    else:
        assert np.abs(got[4]).max() > 0.0


CASES = [
    (klik.LIK_GAUSS, 1.0, 0.5, 0.8, 0.0),  # the map is not the world: gross misses scored apart
    (klik.LIK_GAUSS, 0.05, 4.0, 0.0, 0.0),  # every point's σ far from the likelihood's: -log(σ_j/σ) folded often
    (klik.LIK_GAUSS, 2.0, 0.0, 0.0, 0.0),  # a noiseless sensor: the likelihood's own σ
    (klik.LIK_STUDENT, 1.0, 0.5, 0.3, 2.0),  # a stated map error (without its modes)
    (klik.LIK_PAPER, 1.0, 0.5, 0.8, 0.0),  # no information sums
]


@pytest.mark.parametrize("surface", [0, 1])
@pytest.mark.parametrize(("lik", "sigma", "sigma_range", "sigma_map", "sigma_err"), CASES)
def test_simd_sliding_equals_the_warp_kernel(surface, lik, sigma, sigma_range, sigma_map, sigma_err):
    """Two filters of 24 particles, 37 points a scan (the last group of lanes part-filled), particles scattered
    30 m about each filter's truth and two of them over the map's edge; residuals identical, sums to float32
    rounding."""
    rng = np.random.default_rng(surface + 10 * lik)
    terrain = _terrain()
    n0, n1, e0, e1 = terrain.bounds_ne
    b, n_per, m = 2, 24, 37
    ground = float(np.nanmax(terrain.heights_m))
    truth = np.column_stack([rng.uniform(n0 + 700, n1 - 700, b), rng.uniform(e0 + 700, e1 - 700, b),
                             np.full(b, -(ground + 400.0))])
    truth_q = euler_to_quat(rng.normal(0, 0.1, b), rng.normal(0, 0.1, b), rng.uniform(-3, 3, b))
    pos = np.repeat(truth, n_per, axis=0) + rng.normal(0.0, [30.0, 30.0, 3.0], (b * n_per, 3))
    pos[3, 0] = n1 - 20.0  # over the map's edge: most of its points off the map
    pos[30, 1] = e0 + 10.0
    quat = np.repeat(truth_q, n_per, axis=0)
    att = wp.array(np.tile(np.diag([1e-4, 1e-4, 4e-4]).astype(np.float32), (b, 1, 1)), dtype=wp.mat33, device=DEVICE)
    args = (terrain, surface, _params(lik, sigma, sigma_range, sigma_map, sigma_err),
            wp.array(pos.astype(np.float32), dtype=wp.vec3, device=DEVICE),
            wp.array(quat.astype(np.float32), dtype=wp.vec4, device=DEVICE), _cloud(terrain, truth, truth_q, m, rng),
            att)
    ref = _run(kslide.sliding_loglik_kernels[False, False], *args)
    got = _run(ksimd.sliding_loglik_simd_kernels[False], *args, simd=True)
    np.testing.assert_array_equal(got[0].view(np.uint32), ref[0].view(np.uint32))  # residuals, NaN where NaN
    assert np.isnan(ref[0]).any() and np.isfinite(ref[0]).any()
    _assert_sums_equal(got[1:], ref[1:], lik)


def _ray_casts(rng, roll: float = 0.1):
    """Real DDA casts (residuals, scaled normals, heights above the map) of 48 particles 30 m about the truth, two
    over the map's edge, 37 random rays a scan, one in seven not received, the aircraft rolled by ``roll`` (rad):
    (model, casts, attitudes, attitude covariance)."""
    terrain = _terrain()
    n0, n1, e0, e1 = terrain.bounds_ne
    m, n = 37, 48
    ground = float(np.nanmax(terrain.heights_m))
    truth = np.array([0.5 * (n0 + n1), 0.5 * (e0 + e1), -(ground + 400.0)])
    truth_q = euler_to_quat(roll, -0.05, 0.7)
    pos = truth + rng.normal(0.0, [30.0, 30.0, 3.0], (n, 3))
    pos[3, 0] = n1 - 20.0
    pos[30, 1] = e0 + 10.0
    dirs = np.column_stack([rng.uniform(-0.7, 0.7, m), rng.uniform(-0.7, 0.7, m), np.ones(m)])
    sensor = wt.PointCloudSensor(wt.ScanPattern(dirs), range_sigma_m=0.5)
    cloud = sensor.measure(terrain, truth, truth_q, rng=rng)
    cloud.ranges_m[rng.random(m) < 1.0 / 7.0] = np.nan
    model = wt.RaycastModel(terrain, wt.Likelihood("gaussian", sensor_sigma_m=0.5, map_sigma_m=0.8),
                            caster=wt.RayCaster("dda"))  # gross misses gated: the casts write the heights above
    quat = wp.array(np.tile(truth_q, (n, 1)).astype(np.float32), dtype=wp.vec4, device=DEVICE)
    cast = model.evaluate(wp.array(pos.astype(np.float32), dtype=wp.vec3, device=DEVICE), quat, cloud)
    assert np.isnan(cast.residual_m.numpy()).any() and np.isfinite(cast.vertical_m.numpy()).any()
    att = wp.array(np.diag([1e-4, 1e-4, 4e-4]).astype(np.float32)[None], dtype=wp.mat33, device=DEVICE)
    return model, cast, quat, att


def _reduce(kernel, model, cast, quat, att, params, mode_args):
    n = quat.shape[0]
    outs = _outputs(n)
    wp.launch(kernel, dim=n, inputs=[0, n, cast.residual_m, quat, cast.normal, cast.vertical_m, model._staged, att,
                                     params, *mode_args], outputs=outs, device=DEVICE)
    return [o.numpy() for o in outs]


@pytest.mark.parametrize(("lik", "sigma", "sigma_range", "sigma_map", "sigma_err"), CASES)
def test_simd_ray_reduction_equals_the_warp_kernel(lik, sigma, sigma_range, sigma_map, sigma_err):
    """The ray-casting model's reduction over real DDA casts (:func:`_ray_casts`): the SIMD kernel's sums equal the
    Warp kernel's."""
    model, cast, quat, att = _ray_casts(np.random.default_rng(100 + 10 * lik))
    params = _params(lik, sigma, sigma_range, sigma_map, sigma_err)
    params.err_kind = klik.ERR_AXES
    n = quat.shape[0]
    ref = _reduce(klik.reduce_loglik_kernels[False, False], model, cast, quat, att, params, _modes(n))
    got = _reduce(ksimd.reduce_loglik_simd_kernels[False], model, cast, quat, att, params, _modes(n, simd=True))
    _assert_sums_equal(got[:6], ref[:6], lik)


@pytest.mark.parametrize(("m", "want_vertical"), [(37, 1), (100, 0), (ksimd_ray.MAX_ORDERED + 3, 1)])
def test_simd_ray_casts_equal_the_warp_kernel(m, want_vertical):
    """The DDA casts in lanes against the per-particle Warp kernel: two filters of 24 particles 30 m about their
    truths (a scan part-filling its last group of lanes; one beyond the rays it orders), two particles over the map's
    edge, one below the ground; rays into the nodata hole, off the map, level and upward, one in seven not received:
    ranges, normals and heights above the map bit for bit."""
    rng = np.random.default_rng(m)
    terrain = _terrain()
    n0, n1, e0, e1 = terrain.bounds_ne
    b, n_per = 2, 24
    ground = float(np.nanmax(terrain.heights_m))
    truth = np.column_stack([rng.uniform(n0 + 900, n1 - 900, b), rng.uniform(e0 + 900, e1 - 900, b),
                             np.full(b, -(ground + 300.0))])
    truth_q = euler_to_quat(rng.normal(0, 0.3, b), rng.normal(0, 0.3, b), rng.uniform(-3, 3, b))
    pos = np.repeat(truth, n_per, axis=0) + rng.normal(0.0, [30.0, 30.0, 3.0], (b * n_per, 3))
    pos[3, 0] = n1 - 20.0  # over the map's edge
    pos[30, 1] = e0 + 10.0
    pos[7, 2] = 50.0  # below the ground: its origin is blocked
    quat = np.repeat(truth_q, n_per, axis=0)
    cloud = _cloud(terrain, truth, truth_q, m, rng).numpy()
    cloud[:, :3, 3:6] = [[0.6, 0.0, 0.8], [0.0, 1.0, 0.0], [0.0, 0.6, -0.8]]  # steep, level, upward
    grid = terrain.grid(DEVICE)
    ins = [grid, wp.uint64(0), kray.BACKEND_DDA, 0.0, 0, 0, n_per, wp.array(pos.astype(np.float32), dtype=wp.vec3,
           device=DEVICE), wp.array(quat.astype(np.float32), dtype=wp.vec4, device=DEVICE),
           wp.array(cloud, dtype=klik.cloud_row, device=DEVICE)]
    got = []
    for kernel in (kray.raycast_residual_rows_kernel, ksimd_ray.raycast_residual_rows_simd_kernel):
        outs = [wp.full((b * n_per, m), 7.0, dtype=wp.float32, device=DEVICE),
                wp.full((b * n_per, m), wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3, device=DEVICE), want_vertical,
                wp.full((b * n_per, m), 7.0, dtype=wp.float32, device=DEVICE)]
        wp.launch(kernel, dim=b * n_per, inputs=ins, outputs=outs, device=DEVICE)
        got.append([outs[0].numpy(), outs[1].numpy(), outs[3].numpy()])
    (r_ref, n_ref, v_ref), (r_got, n_got, v_got) = got
    for ref, new in ((r_ref, r_got), (n_ref, n_got), (v_ref, v_got)):
        np.testing.assert_array_equal(new.view(np.uint32), ref.view(np.uint32))
    hit = np.isfinite(r_ref)
    assert hit.mean() > 0.5 and (~hit).any() and np.isnan(r_ref[7]).all() and (n_ref[hit] != 0.0).any()
    assert (v_ref == 7.0).all() if not want_vertical else np.isfinite(v_ref).any()


def test_the_cpu_models_run_the_simd_kernels(monkeypatch):
    """The CPU's sliding model launches the SIMD kernel, with map-error modes its form with the modes' sums (the
    ray-casting model's reduction likewise); its DDA casts run in lanes, the other backends' per particle."""
    launched = []
    import warptan.sensing.measurement as meas

    real = meas.launch_rows
    monkeypatch.setattr(meas, "launch_rows", lambda kernel, *a, **k: launched.append(kernel.key) or real(kernel, *a,
                                                                                                          **k))
    terrain = wt.Terrain.synthetic("rugged", size_m=3000.0, spacing=30.0, seed=4)
    pos = np.array([[0.5 * (terrain.bounds_ne[0] + terrain.bounds_ne[1]),
                     0.5 * (terrain.bounds_ne[2] + terrain.bounds_ne[3]), -(np.nanmax(terrain.heights_m) + 400.0)]])
    q = euler_to_quat(0.0, 0.0, 0.4)[None]
    cloud = wt.PointCloudSensor(wt.ScanPattern.grid(5, 5, 20.0), range_sigma_m=0.0).measure(terrain, pos[0], q[0])
    poses = (wp.array(pos.astype(np.float32), dtype=wp.vec3, device=DEVICE),
             wp.array(q.astype(np.float32), dtype=wp.vec4, device=DEVICE))
    wt.SlidingModel(terrain, wt.Likelihood("gaussian"), surface=True).evaluate(*poses, cloud)
    assert launched[-1] == ksimd.sliding_loglik_simd_kernels[False].key
    stated = wt.Likelihood("gaussian", map_error_sigma_m=3.0, map_error_corr_m=300.0, track_step_m=50.0)
    out = wt.SlidingModel(terrain, stated, surface=True).evaluate(*poses, cloud)
    assert launched[-1] == ksimd.sliding_loglik_simd_kernels[True].key
    assert np.isfinite(out.loglik.numpy()).all()
    wt.RaycastModel(terrain, wt.Likelihood("gaussian")).evaluate(*poses, cloud)
    assert launched[-2:] == [ksimd_ray.raycast_residual_rows_simd_kernel.key,
                             ksimd.reduce_loglik_simd_kernels[False].key]
    wt.RaycastModel(terrain, wt.Likelihood("gaussian"), caster=wt.RayCaster("bisection")).evaluate(*poses, cloud)
    assert launched[-2] == kray.raycast_residual_rows_kernel.key
    wt.RaycastModel(terrain, stated).evaluate(*poses, cloud)
    assert launched[-1] == ksimd.reduce_loglik_simd_kernels[True].key


def _mode_state(params, m: int, n: int, b: int, rng):
    """A stated map error's mode table for ``m`` scattered ground points (:meth:`warptan.Likelihood.error_modes`),
    each particle's prior amplitudes and each filter's variances: (table, mean, var) on the CPU; ``params`` takes
    the modes."""
    lik = wt.Likelihood("gaussian", map_error_sigma_m=4.0, map_error_corr_m=300.0, track_step_m=20.0)
    table, info = lik.error_modes(rng.uniform(-250.0, 250.0, (m, 2)), 1.0 + rng.uniform(0.0, 0.3, m), 0.7,
                                  (1.0, 0.0), absorb_offset=True)
    assert info["n_modes"] == klik.MAX_MODES
    params.n_modes = klik.MAX_MODES
    mean = rng.normal(0.0, 1.0, (n, klik.MAX_MODES)).astype(np.float32)
    var = np.abs(rng.normal(1.0, 0.5, (b, klik.MAX_MODES))).astype(np.float32)
    return (wp.array(table, dtype=klik.modes_vec, device=DEVICE), wp.array(mean, dtype=klik.modes_vec, device=DEVICE),
            wp.array(var, dtype=klik.modes_vec, device=DEVICE))


def _assert_modes_equal(got, ref, lik):
    """The sums as :func:`_assert_sums_equal`, the modes' posteriors to float32 reassociation."""
    _assert_sums_equal(got[:6], ref[:6], lik)
    np.testing.assert_allclose(got[6], ref[6], rtol=1e-4, atol=1e-4 * np.abs(ref[6]).max(), err_msg="mode_post")
    assert np.abs(ref[6]).max() > 0.0


@pytest.mark.parametrize("lik", [klik.LIK_GAUSS, klik.LIK_STUDENT])
def test_simd_sliding_with_modes_equals_the_warp_kernel(lik):
    """A stated map error (16 modes): the SIMD kernel with the modes' sums gives the Warp kernel's residuals bit for
    bit, its sums, information and mode posteriors to float32 rounding (2 filters of 24 particles, 37 points, two
    particles over the map's edge)."""
    rng = np.random.default_rng(7 + lik)
    terrain = _terrain()
    n0, n1, e0, e1 = terrain.bounds_ne
    b, n_per, m = 2, 24, 37
    n = b * n_per
    ground = float(np.nanmax(terrain.heights_m))
    truth = np.column_stack([rng.uniform(n0 + 700, n1 - 700, b), rng.uniform(e0 + 700, e1 - 700, b),
                             np.full(b, -(ground + 400.0))])
    truth_q = euler_to_quat(rng.normal(0, 0.1, b), rng.normal(0, 0.1, b), rng.uniform(-3, 3, b))
    pos = np.repeat(truth, n_per, axis=0) + rng.normal(0.0, [30.0, 30.0, 3.0], (n, 3))
    pos[3, 0] = n1 - 20.0
    pos[30, 1] = e0 + 10.0
    params = _params(lik, 1.0, 0.5, 0.3, 4.0)
    table, mean, var = _mode_state(params, m, n, b, rng)
    att = wp.array(np.tile(np.diag([1e-4, 1e-4, 4e-4]).astype(np.float32), (b, 1, 1)), dtype=wp.mat33, device=DEVICE)
    cloud = _cloud(terrain, truth, truth_q, m, rng)
    head = [terrain.grid(DEVICE), 1, wp.array(pos.astype(np.float32), dtype=wp.vec3, device=DEVICE),
            wp.array(np.repeat(truth_q, n_per, axis=0).astype(np.float32), dtype=wp.vec4, device=DEVICE), cloud, att,
            params, table, mean, var]
    runs = []
    for kernel, extra in ((kslide.sliding_loglik_kernels[False, True], []),
                          (ksimd.sliding_loglik_simd_kernels[True], [wp.empty(n, dtype=klik.modes_sums_vec)])):
        outs = [wp.full((n, m), 7.0, dtype=wp.float32, device=DEVICE), *_outputs(n)]
        wp.launch(kernel, dim=n, inputs=[0, n_per, *head, *extra], outputs=outs, device=DEVICE)
        runs.append([o.numpy() for o in outs])
    ref, got = runs
    np.testing.assert_array_equal(got[0].view(np.uint32), ref[0].view(np.uint32))
    _assert_modes_equal(got[1:], ref[1:], lik)


@pytest.mark.parametrize("roll", [0.1, 0.9])
def test_simd_ray_reduction_with_modes_equals_the_warp_kernel(roll):
    """The ray-casting model's reduction with 16 map-error modes over real DDA casts (:func:`_ray_casts`): the SIMD
    kernel's sums, information and mode posteriors equal the Warp kernel's to float32 rounding; rolled by 0.9 rad,
    with rays more than 60° from the vertical (a large flat-ground sensitivity 1/u_z)."""
    rng = np.random.default_rng(11)
    model, cast, quat, att = _ray_casts(rng, roll)
    u_down = (model._staged.numpy()[0, :, 3:6].astype(np.float64) @ quat_to_mat(quat.numpy()[0]).T)[:, 2]
    assert (u_down < 0.5).any() == (roll > 0.5)
    params = _params(klik.LIK_GAUSS, 1.0, 0.5, 0.3, 4.0)
    params.err_kind = klik.ERR_AXES
    n = quat.shape[0]
    table, mean, var = _mode_state(params, cast.residual_m.shape[1], n, 1, rng)
    ref = _reduce(klik.reduce_loglik_kernels[False, True], model, cast, quat, att, params, [table, mean, var])
    got = _reduce(ksimd.reduce_loglik_simd_kernels[True], model, cast, quat, att, params,
                  [table, mean, var, wp.empty(n, dtype=klik.modes_sums_vec)])
    _assert_modes_equal(got, ref, klik.LIK_GAUSS)
