"""The information map (issue 34): the Fisher information of a scan about the position at every post, against closed
forms on a plane and a float64 NumPy oracle on rugged ground; its bounds, the leg, bad input, the command line."""

import math
import subprocess
import sys

import numpy as np
import pytest

import warptan as wt
from warptan.terrain.information import drms_bound, information_map, scan_footprint
from warptan.terrain.raster import TerrainError

SLOPE = (0.05, -0.02)  # ∂h/∂north, ∂h/∂east of the plane


@pytest.fixture(scope="module")
def plane():
    n, e = np.arange(80) * 30.0, np.arange(80) * 30.0
    return wt.Terrain(500.0 + SLOPE[0] * n[:, None] + SLOPE[1] * e[None, :], 0.0, 0.0, 30.0, 30.0, name="plane")


@pytest.fixture(scope="module")
def hills():
    return wt.Terrain.synthetic("rugged", size_m=6000.0, spacing=30.0, seed=3)


def _dirs(side=5, half=20.0):
    return wt.ScanPattern.grid(side, side, half).dirs_s


def _correlated(offsets, rms, corr):
    d = offsets[:, None, :] - offsets[None, :, :]
    return rms * rms * np.exp(-(d ** 2).sum(-1) / (corr * corr))


def test_plane_information_is_the_closed_form(device, plane):
    """On a plane every point's residual moves as ``v = (a, b, 1)``: one scan of M points gives ``J = (M/σ²) v vᵀ``
    and N scans N times that (within 1 %; float32 gradients); the map error's modes give ``(1ᵀ R⁻¹ 1) v vᵀ`` (R the
    white plus correlated covariance over the footprint, inverted in float64); the horizontal position is not fixed
    (a plane moved sideways is the plane moved up): the bound is infinite. An altimeter with a barometer reads
    ``(a, b)`` once a reading: rank one, no fix either."""
    v = np.array([SLOPE[0], SLOPE[1], 1.0])
    m = information_map(plane, _dirs(), 300.0, 0.5, n_scans=3, device=device)
    c = 40
    np.testing.assert_allclose(m.info_scan[c, c], 25 / 0.25 * np.outer(v, v), rtol=0.01, atol=1e-3)
    np.testing.assert_allclose(m.info_leg[c, c], 75 / 0.25 * np.outer(v, v), rtol=0.01, atol=3e-3)
    assert np.isinf(m.bound_scan_m[c, c]) and np.isinf(m.bound_leg_m[c, c])
    off = scan_footprint(_dirs(), 300.0)
    told = information_map(plane, _dirs(), 300.0, 0.5, map_error_rms_m=3.0, map_error_corr_m=500.0, n_scans=1,
                           device=device)
    r = 0.25 * np.eye(len(off)) + _correlated(off, 3.0, 500.0)
    ones = np.ones(len(off))
    np.testing.assert_allclose(told.info_scan[c, c], (ones @ np.linalg.solve(r, ones)) * np.outer(v, v), rtol=0.01,
                               atol=1e-4)
    alt = information_map(plane, [[0.0, 0.0, 1.0]], 300.0, 2.0, vertical_known=True, n_scans=1, device=device)
    g = np.array([SLOPE[0], SLOPE[1], 0.0])
    np.testing.assert_allclose(alt.info_scan[c, c], np.outer(g, g) / 4.0, rtol=0.01, atol=1e-7)
    assert np.isinf(alt.bound_scan_m[c, c])


def _oracle(terrain, offsets, centre, sigma, rms=0.0, corr=1.0):
    """float64 NumPy: J = Gᵀ R⁻¹ G with G the bilinear gradients (central differences inside the cell) and a unit
    vertical, R = σ² I + the correlated error, inverted whole."""
    pts = centre + offsets
    eps = 1e-3
    gn = (terrain.height_at(pts[:, 0] + eps, pts[:, 1]) - terrain.height_at(pts[:, 0] - eps, pts[:, 1])) / (2 * eps)
    ge = (terrain.height_at(pts[:, 0], pts[:, 1] + eps) - terrain.height_at(pts[:, 0], pts[:, 1] - eps)) / (2 * eps)
    g = np.stack([gn, ge, np.ones(len(pts))], axis=1)
    r = sigma * sigma * np.eye(len(pts)) + (_correlated(offsets, rms, corr) if rms else 0.0)
    return g.T @ np.linalg.solve(r, g)


def test_rugged_information_matches_a_float64_oracle(device, hills):
    """Over generated hills, at several posts: the kernel's information (with a stated map error of 3 m over 400 m)
    against a float64 NumPy oracle with the whole covariance inverted (within 1 %), and the DRMS bound of the
    horizontal block with the vertical marginalised (the Schur complement) against the oracle's inverse."""
    dirs, agl, sigma = _dirs(6, 25.0), 400.0, 0.5
    m = information_map(hills, dirs, agl, sigma, map_error_rms_m=3.0, map_error_corr_m=400.0, n_scans=1,
                        device=device)
    off = scan_footprint(dirs, agl)
    for i, j in ((60, 60), (80, 120), (130, 70), (100, 100)):
        centre = np.array([hills.n0 + i * hills.dn, hills.e0 + j * hills.de])
        want = _oracle(hills, off, centre, sigma, 3.0, 400.0)
        np.testing.assert_allclose(m.info_scan[i, j], want, rtol=0.01, atol=1e-3 * np.abs(want).max())
        cov = np.linalg.inv(want)
        assert m.bound_scan_m[i, j] == pytest.approx(math.sqrt(cov[0, 0] + cov[1, 1]), rel=0.01)


def test_leg_adds_its_scans(device, hills):
    """Without a map error the leg's information is the sum over its scans (the altitude error common): with the
    scans one post apart along north it equals the one-scan field summed over the posts of the leg, and its bound
    is below one scan's."""
    m = information_map(hills, _dirs(), 300.0, 0.5, n_scans=5, scan_step_m=hills.dn, device=device)
    i, j = 100, 90
    want = sum(m.info_scan[i + k, j] for k in range(-2, 3))
    np.testing.assert_allclose(m.info_leg[i, j], want, rtol=1e-5)
    inner = np.isfinite(m.bound_leg_m) & np.isfinite(m.bound_scan_m)
    assert inner.mean() > 0.5 and (m.bound_leg_m[inner] < m.bound_scan_m[inner]).all()


def test_drms_bound_of_known_matrices():
    """sqrt(tr J⁻¹): diag(4, 1) → sqrt(1/4 + 1); singular → inf; NaN → NaN."""
    info = np.array([[[4.0, 0.0], [0.0, 1.0]], [[1.0, 1.0], [1.0, 1.0]], [[np.nan, 0.0], [0.0, 1.0]]])
    got = drms_bound(info)
    assert got[0] == pytest.approx(math.sqrt(1.25)) and np.isinf(got[1]) and np.isnan(got[2])


@pytest.mark.parametrize(("call", "message"), [
    (lambda t: information_map(t, _dirs(), 0.0, 0.5), "must fly above the terrain"),
    (lambda t: information_map(t, _dirs(), -50.0, 0.5), "must fly above the terrain"),
    (lambda t: information_map(t, [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], 300.0, 0.5), "empty footprint"),
    (lambda t: information_map(t, _dirs(), 300.0, 0.0), "sigma_m"),
    (lambda t: information_map(t, _dirs(), 300.0, 0.5, map_error_rms_m=3.0), "map_error_corr_m > 0"),
    (lambda t: information_map(t, _dirs(), 300.0, 0.5).save_geotiff("/tmp/warptan_no_crs.tif"), "needs the DEM's CRS"),
])
def test_bad_input_is_refused_before_work(plane, call, message):
    """An altitude at or below the terrain, a scan none of whose rays meets the ground, a bad σ or map error, and a
    GeoTIFF of a DEM without CRS: clear errors."""
    with pytest.raises(TerrainError, match=message):
        call(plane)


def test_command_line_writes_the_map(tmp_path):
    """``warptan terrain info DEM --information --sensor S8 --out map.png --out map.tif``: a PNG with units and a
    two-band GeoTIFF in the DEM's CRS; a GeoTIFF of a DEM without CRS is refused before work (exit 2, one line)."""
    pytest.importorskip("matplotlib")
    rasterio = pytest.importorskip("rasterio")
    png, tif = tmp_path / "map.png", tmp_path / "map.tif"
    cmd = [sys.executable, "-c", "import sys; sys.path.pop(0); from warptan.cli import main; sys.exit(main())"]
    done = subprocess.run([*cmd, "terrain", "info", "rugged", "--spacing", "500", "--information", "--sensor", "S8",
                           "--stride", "2", "--out", str(png), "--out", str(tif)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "1σ horizontal bound" in done.stdout and png.stat().st_size > 10_000
    with rasterio.open(tif) as src:
        assert src.count == 2 and src.crs is not None and "one scan" in src.descriptions[0]
        bands = src.read()
    assert np.isfinite(bands).any() and (bands[np.isfinite(bands)] > 0).all()
    bad = subprocess.run([*cmd, "terrain", "info", "synthetic:rugged,size_m=3000", "--information",
                          "--out", str(tmp_path / "x.tif")], capture_output=True, text=True)
    assert bad.returncode == 2 and "needs the DEM's CRS" in bad.stderr and not (tmp_path / "x.tif").exists()


# ---------------------------------------------------------------------- the bound along a flight
def test_bound_of_one_update_is_the_closed_form(plane):
    """One altimeter reading with a barometer over the plane, no time before it: the bound's position covariance is
    ``(P0⁻¹ + J)⁻¹`` with ``J = [g gᵀ/(σ_a² + σ_b²), 0; 0, 1/σ_b²]`` (g the slope), within 1 %; the other states
    keep their prior."""
    from warptan.filter.bound import pcrb
    from warptan.nav.imu import imu_grade
    from warptan.nav.trajectory import Straight, Trajectory

    flight = Trajectory.build([Straight(1.0)], 100.0, [1200.0, 1200.0, -1000.0])
    p0 = np.diag(np.r_[[40.0, 30.0, 10.0], np.full(12, 0.01)] ** 2)
    sigmas = pcrb(flight, plane, [0], imu_grade("navigation"), p0, dirs_body=None, sigma_m=2.0, baro_sigma_m=1.0)
    g = np.array(SLOPE)
    info = np.zeros((3, 3))
    info[:2, :2] = np.outer(g, g) / 5.0
    info[2, 2] = 1.0
    want = np.linalg.inv(np.linalg.inv(p0[:3, :3]) + info)
    np.testing.assert_allclose(sigmas[1, :3], np.sqrt(np.diag(want)), rtol=0.01)
    np.testing.assert_allclose(sigmas[1, 3:], np.sqrt(np.diag(p0))[3:], rtol=1e-9)
    assert sigmas[0] == pytest.approx(np.sqrt(np.diag(p0)))


@pytest.mark.statistical
def test_filter_is_never_better_than_its_bound():
    """S8 and S1 (banked), 20 seeds each (200 particles, 35–45 s): the filter's horizontal mean squared error after
    convergence is not below the flight's posterior Cramér–Rao bound by more than twice its own Monte-Carlo
    standard error; every run's summary carries the bound per epoch and its converged value, and the results table
    shows it beside the RMSE."""
    from warptan.sim.report import aggregate, markdown_table

    for sid, duration in (("S8", 35.0), ("S1", 45.0)):
        runs = wt.run_scenario_batch(sid, list(range(20)), "cpu", duration_s=duration, particles=200)
        first = runs[0]
        sel = first.run.t_s >= first.config.filter.converged_after_s
        mse = np.array([(r.run.error[sel, :2] ** 2).sum(axis=1).mean() for r in runs])
        bound2 = float(np.mean(first.pcrb_m[sel] ** 2))
        assert mse.mean() >= bound2 - 2.0 * mse.std(ddof=1) / math.sqrt(len(mse)), (sid, mse.mean(), bound2)
        assert 0.0 < bound2 < mse.mean() and np.isfinite(first.pcrb_m).all()
        s = first.summary()
        assert len(s["pcrb_m"]) == len(first.run.t_s) and s["pcrb_converged_m"] == pytest.approx(math.sqrt(bound2))
        assert "horizontal RMSE / bound" in markdown_table(aggregate(runs))


@pytest.mark.parametrize("surface", [False, True], ids=["bilinear", "triangles"])
def test_host_gradient_is_the_surface_slope(hills, surface):
    """``Terrain.gradient_at`` (the bound's gradients) against central differences of the surface's own heights, at
    points inside cells (1e-6 relative); NaN off the map."""
    rng = np.random.default_rng(5)
    i, j = rng.integers(5, 190, 200), rng.integers(5, 190, 200)
    fu, fv = rng.uniform(0.1, 0.9, 200), rng.uniform(0.1, 0.9, 200)
    fv = np.where(np.abs(fu - fv) < 0.05, 0.5 * fu, fv)  # off a triangle's diagonal
    n, e = hills.n0 + (i + fu) * hills.dn, hills.e0 + (j + fv) * hills.de
    height = hills.surface_height_at if surface else hills.height_at
    eps = 1e-4
    want_n = (height(n + eps, e) - height(n - eps, e)) / (2 * eps)
    want_e = (height(n, e + eps) - height(n, e - eps)) / (2 * eps)
    gn, ge = hills.gradient_at(n, e, surface)
    np.testing.assert_allclose(gn, want_n, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(ge, want_e, rtol=1e-6, atol=1e-7)
    assert np.isnan(hills.gradient_at(np.array([1e7]), np.array([0.0]), surface)[0]).all()


def test_the_png_paints_no_fix_grey_as_its_colour_bar_says(tmp_path):
    """Cells where the terrain fixes nothing (a flat half: bound inf) are grey in the PNG, as the colour bar's label
    says; before, an inf was masked as bad and painted white, the colour of no footprint."""
    pytest.importorskip("matplotlib")
    import matplotlib.image as mpimg

    from warptan.sim.scenario_config import load_config
    from warptan.sim.scenarios import scenario_scan

    rng = np.random.default_rng(0)
    h = 300.0 + np.cumsum(np.cumsum(rng.normal(0.0, 1.0, (60, 60)), axis=0), axis=1) * 0.5
    h[:, :30] = 300.0  # no relief: no fix
    t = wt.Terrain.from_grid(h, 90.0, name="half flat")
    scan = scenario_scan(load_config("S8"))
    m = t.information_map(scan["dirs_body"], 600.0, scan["sigma_m"], n_scans=5, scan_step_m=scan["step_m"], stride=2)
    assert np.isinf(m.bound_scan_m).any() and np.isfinite(m.bound_scan_m).any()
    rgb = mpimg.imread(m.save_png(tmp_path / "map.png"))[..., :3]
    grey = np.all(np.abs(rgb - 0.6) < 0.02, axis=2)
    assert grey.mean() > 0.03  # (the colour bar's over-triangle alone is far less)


def test_the_png_gives_each_panels_number(tmp_path, monkeypatch):
    """Each panel's title gives its median bound and the share of the map that fixes, and the colour bar reads in
    plain metres (it read 4×10⁰)."""
    pytest.importorskip("matplotlib")
    import matplotlib.figure

    from warptan.sim.scenario_config import load_config
    from warptan.sim.scenarios import scenario_scan

    seen = []
    save = matplotlib.figure.Figure.savefig
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: (
        seen.append([(ax.get_title(), [t.get_text() for t in ax.get_yticklabels()]) for ax in fig.axes]),
        save(fig, *a, **k))[1])
    t = wt.Terrain.synthetic("rugged", size_m=6000.0, spacing=90.0, seed=0)
    scan = scenario_scan(load_config("S8"))
    m = t.information_map(scan["dirs_body"], 600.0, scan["sigma_m"], n_scans=5, scan_step_m=scan["step_m"], stride=2)
    m.save_png(tmp_path / "map.png")
    (one, _), (leg, _), (_, bar) = seen[0][:3]
    median = np.median(m.bound_scan_m[np.isfinite(m.bound_scan_m)])
    assert one.startswith(f"one scan: median {median:.2g} m, ") and "% of the map fixes" in one
    assert leg.startswith("5 scans along the leg: median") and bar and all("×" not in b for b in bar)
