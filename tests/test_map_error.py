"""The stated map error in the likelihood (issue 31, part 2): map-error modes marginalised per scan, against NumPy
float64 oracles (the covariance they represent, the Woodbury form the kernels sum, the along-track sharing of a
footprint much smaller than the correlation length), and the default path unchanged."""

import math

import numpy as np
import pytest
import warp as wp

import warptan as wt
from warptan.world import WorldModel

STATED = {"map_error_sigma_m": 5.0, "map_error_corr_m": 1000.0, "track_step_m": 10.0}


def _grid_xy(n=10, half_deg=30.0, agl=650.0):
    t = np.tan(np.radians(np.linspace(-half_deg, half_deg, n)))
    gx, gy = np.meshgrid(t, t)
    return np.c_[gx.ravel(), gy.ravel()] * agl


def test_the_modes_hold_the_stated_covariance_and_its_sharing():
    """U diag(k) Uᵀ reproduces κ-weighted (σ_e²/σ²) R on the scan to its dropped remainder; a tiny footprint's
    offset mode is shared by Σ_k exp(−(k s / L)²) ≈ √π L / s scans."""
    lk = wt.Likelihood("gaussian", **STATED)
    xy = _grid_xy()
    table, info = lk.error_modes(xy, np.ones(len(xy)), 0.5)
    q = info["n_modes"]
    assert 12 <= q <= 16 and info["remainder"] < 1e-3 and not table[:, q:].any() and table.shape == (101, 16)
    c = np.array(info["c"])
    assert np.all((c > 0) & (c <= 1)) and info["sharing"][0] > info["sharing"][-1] >= 1.0
    u = table[:-1, :q].astype(np.float64)
    lam = np.array(info["eigenvalues"])
    k = np.array(info["sharing"]) * 25.0 * lam / 0.25  # κ_i σ_e² λ_i / σ²
    np.testing.assert_allclose(table[-1, :q], k / (1.0 + k), rtol=1e-6)  # the weights c_i
    np.testing.assert_allclose(u.T @ u, np.eye(q), atol=1e-4)  # orthonormal modes
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    r = np.exp(-(d / 1000.0) ** 2)
    np.testing.assert_allclose(u.T @ r @ u, np.diag(lam), atol=1e-3 * lam[0])
    tiny = lk.error_modes(xy * 1e-3, np.ones(len(xy)), 0.5)[1]
    expected = sum(math.exp(-((k * 10.0 / 1000.0) ** 2)) for k in range(-1000, 1001))
    assert tiny["sharing"][0] == pytest.approx(expected, rel=1e-3)
    assert expected == pytest.approx(math.sqrt(math.pi) * 100.0, rel=1e-3)
    assert wt.Likelihood("gaussian").error_modes(xy, np.ones(len(xy)), 0.5)[1]["n_modes"] == 0
    assert wt.Likelihood("paper", **STATED).error_modes(xy, np.ones(len(xy)), 0.5)[1]["n_modes"] == 0


def test_the_woodbury_form_equals_the_inverse_of_the_covariance():
    """zᵀ(I + U K Uᵀ)⁻¹z = zᵀz − Σ c_i (u_iᵀ z)², c_i = k_i / (1 + k_i) from the table: what the kernels sum for a
    particle that predicts every point, against a dense float64 solve."""
    lk = wt.Likelihood("gaussian", **STATED)
    xy = _grid_xy(agl=900.0)
    table, info = lk.error_modes(xy, 1.0 / np.cos(np.radians(np.linspace(-30, 30, len(xy)))), 0.8)
    q = info["n_modes"]
    u, c = table[:-1, :q].astype(np.float64), table[-1, :q].astype(np.float64)
    k = np.array(info["sharing"]) * 25.0 * np.array(info["eigenvalues"]) / 0.64
    cov = np.eye(len(xy)) + u @ np.diag(k) @ u.T
    z = np.random.default_rng(0).normal(size=(5, len(xy))) * 3.0
    direct = np.einsum("ij,ij->i", z, np.linalg.solve(cov, z.T).T)
    woodbury = np.einsum("ij,ij->i", z, z) - ((z @ u) ** 2 * c).sum(axis=1)
    np.testing.assert_allclose(woodbury, direct, rtol=1e-4)


@pytest.fixture(scope="module")
def scan():
    dem = wt.Terrain.load("rugged")
    world = WorldModel(error_rms_m=5.0, error_corr_m=1000.0, seed=1).build(dem)
    sensor = wt.PointCloudSensor(wt.ScanPattern.grid(10, 10, 30.0), range_sigma_m=0.5)
    p_true = np.array([0.0, 0.0, -(dem.height_at(0.0, 0.0) + 700.0)])
    q = np.array([1.0, 0.0, 0.0, 0.0])
    cloud = sensor.measure_many(world, p_true, q, [np.random.default_rng(0)])[0]
    rng = np.random.default_rng(1)
    pos = p_true + np.c_[rng.normal(0, 30, 64), rng.normal(0, 30, 64), rng.normal(0, 5, 64)]
    return dem, cloud, pos, q


@pytest.mark.parametrize("name", ["raycast", "sliding"])
def test_the_kernels_add_the_modes_share_and_nothing_without_a_statement(scan, name, device):
    """The kernel's log-likelihood with modes minus without is 0.5 Σ_i c_i (u_iᵀ z)² of its own residuals, c_i =
    k_i / (1 + k_i), and never more than 0.5 zᵀz over the points a particle predicts (ray casts: one σ for every
    point); the attitude information stays positive semi-definite; without a stated error n_modes = 0."""
    dem, cloud, pos, q = scan
    poses = (wp.array(pos, dtype=wp.vec3, device=device), wp.array(np.tile(q, (len(pos), 1)), dtype=wp.vec4,
                                                                     device=device))
    plain = wt.make_model(name, dem, wt.Likelihood("gaussian", sensor_sigma_m=0.5), surface=True) \
        if name == "sliding" else wt.make_model(name, dem, wt.Likelihood("gaussian", sensor_sigma_m=0.5))
    stated = type(plain)(dem, wt.Likelihood("gaussian", sensor_sigma_m=0.5, **STATED),
                         **({"surface": True} if name == "sliding" else {}))
    a, b = plain.evaluate(*poses, cloud), stated.evaluate(*poses, cloud)
    assert plain.modes_info["n_modes"] == 0 and stated.modes_info["n_modes"] >= 12
    ev = np.linalg.eigvalsh(b.lam.numpy().astype(np.float64))
    assert ev.min() > -1e-4 * ev.max()
    if name == "raycast":
        res = b.residual_m.numpy().astype(np.float64)
        ok = np.isfinite(res)
        z = np.where(ok, res, 0.0) / stated.sigma_m
        table = stated._modes.numpy().astype(np.float64)
        u_tab, c = table[:-1], table[-1]
        p = z @ u_tab
        expected = 0.5 * (c * p**2).sum(axis=1)
        assert np.all(expected <= 0.5 * (z**2).sum(axis=1) * (1 + 1e-5))
        got = b.loglik.numpy().astype(np.float64) - a.loglik.numpy().astype(np.float64)
        np.testing.assert_allclose(got, expected, rtol=2e-3, atol=2e-3 * np.abs(expected).max())
    else:
        assert np.all(b.loglik.numpy() >= a.loglik.numpy() - 1e-3)  # the modes explain, never penalise
        assert not np.array_equal(b.loglik.numpy(), a.loglik.numpy())


def test_a_stated_error_keeps_s8_honest_over_a_world_with_that_error():
    """S8 over a world whose map error is 5 m RMS correlated over 1 km (4 seeds, 90 s): without the statement the
    per-point likelihood's 3σ covers under half of its error on some axis (12–65 %); told the DEM's accuracy,
    over 85 % on each axis and the horizontal RMSE under half. (20 seeds per scenario: scripts/world_study.py.)"""
    from warptan.scenarios import run_scenario_batch

    world = {"world_error_rms_m": 5.0, "world_error_corr_m": 1000.0, "world_seed": 1000, "duration_s": 90.0}
    runs = {told: run_scenario_batch("S8", [0, 1, 2, 3], map_error_rms_m=5.0 if told else 0.0,
                                     map_error_corr_m=1000.0 if told else 0.0, **world) for told in (False, True)}
    cov = {k: np.mean([r.summary()["coverage_3sigma"] for r in v], axis=0) for k, v in runs.items()}
    horiz = {k: np.hypot(*np.sqrt(np.mean([r.rmse_converged ** 2 for r in v], axis=0))[:2]) for k, v in runs.items()}
    assert cov[False].min() < 0.5 and cov[True].min() > 0.85, cov
    assert horiz[True] < 0.5 * horiz[False], horiz


def test_the_command_line_states_the_accuracy(capsys, tmp_path):
    """`--map-error-m` needs `--map-error-corr-m`; with both a run over a world with that error writes its runs."""
    from warptan import cli

    assert cli.main(["run", "S8", "--map-error-m", "5", "--check"]) == 2
    assert "needs likelihood.map_error_corr_m > 0" in capsys.readouterr().err
    out = tmp_path / "o"
    assert cli.main(["run", "S8", "--map-error-m", "5", "--map-error-corr-m", "1000", "--world-error-m", "5",
                     "--world-error-corr-m", "1000", "--duration-s", "1", "--particles", "32", "--out", str(out),
                     "--quiet", "--no-plots"]) == 0
    import json

    run = json.loads((out / "results.json").read_text())["runs"][0]
    assert run["world"]["model"]["error_rms_m"] == 5.0 and "error 5 m / 1000 m" in run["terrain"]
