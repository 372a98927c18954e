"""Ray casting: every backend against trimesh and a float64 brute-force reference, on every device."""

import numpy as np
import pytest
import warp as wp

import warptan as wt
from warptan.terrain.raycast import raycast_pattern


def _small_terrain():
    return wt.Terrain.synthetic("rugged", size_m=1800.0, spacing=30.0, seed=7)


def _reference_f64(terrain, origins, dirs):
    """First front-face hit of each ray on all mesh triangles, float64 Möller–Trumbore, brute force;
    NaN for an origin off the grid or below the surface (the library's stated rule)."""
    verts, faces = terrain.mesh_arrays()
    v0, v1, v2 = (verts[faces[:, k]] for k in range(3))
    e1, e2 = v1 - v0, v2 - v0
    normal = np.cross(e1, e2)  # points up (-z) for every face
    out = np.full(len(origins), np.nan)
    for k, (o, d) in enumerate(zip(origins, dirs / np.linalg.norm(dirs, axis=1, keepdims=True), strict=True)):
        s = terrain.surface_height_at(o[0], o[1])
        if not terrain.contains(o[0], o[1]) or (np.isfinite(s) and o[2] > -s):
            continue
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            tv = o - v0
            u = np.einsum("ij,ij->i", tv, p) * inv
            qv = np.cross(tv, e1)
            v = (qv @ d) * inv
            t = np.einsum("ij,ij->i", e2, qv) * inv
        hit = (np.abs(det) > 1e-12) & (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9) & (t >= 0)
        if hit.any():
            kbest = np.flatnonzero(hit)[np.argmin(t[hit])]
            if normal[kbest] @ d < 0:  # hits the top side
                out[k] = t[kbest]
    return out


def _trimesh_reference(terrain, origins, dirs):
    tm = terrain.to_trimesh()
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    loc, idx_ray, idx_tri = tm.ray.intersects_location(origins, d, multiple_hits=False)
    out = np.full(len(origins), np.nan)
    front = (tm.face_normals[idx_tri] * d[idx_ray]).sum(axis=1) < 0
    out[idx_ray[front]] = np.linalg.norm(loc[front] - origins[idx_ray[front]], axis=1)
    blocked = ~terrain.contains(origins[:, 0], origins[:, 1])
    s = terrain.surface_height_at(origins[:, 0], origins[:, 1])
    blocked |= np.isfinite(s) & (origins[:, 2] > -s)
    out[blocked] = np.nan
    return out


def _ray_set(terrain, count, seed):
    """Down-looking rays from above, upward rays (sky), rays leaving the grid, rays starting underground."""
    rng = np.random.default_rng(seed)
    n_min, n_max, e_min, e_max = terrain.bounds_ne
    o = np.stack([rng.uniform(n_min + 10, n_max - 10, count), rng.uniform(e_min + 10, e_max - 10, count),
                  -rng.uniform(terrain.h_max + 10, terrain.h_max + 600, count)], axis=1)
    d = np.stack([rng.uniform(-0.6, 0.6, count), rng.uniform(-0.6, 0.6, count), rng.uniform(0.4, 1.5, count)], axis=1)
    q = count // 10
    d[:q, 2] *= -1.0  # up into the sky: miss
    o[q:2 * q, :2] = [n_max - 5.0, e_max - 5.0]  # at the north-east corner, many leave the grid
    d[q:2 * q, :2] = np.abs(d[q:2 * q, :2]) * 4.0
    ground = terrain.height_at(o[2 * q:3 * q, 0], o[2 * q:3 * q, 1])
    o[2 * q:3 * q, 2] = -(ground - 5.0)  # 5 m underground
    return o, d


@pytest.mark.parametrize("backend", ["dda", "mesh", "bisection"])
def test_backends_match_trimesh(backend, device):
    """Each backend agrees with trimesh's ray–triangle intersector: same hits/misses, ranges within 1 cm
    (bisection: within its resolution, 2 cm)."""
    terrain = _small_terrain()
    o, d = _ray_set(terrain, 3000, 0)
    ref = _trimesh_reference(terrain, o, d)
    got = wt.raycast(terrain, o, d, backend=backend, device=device)
    assert np.isnan(ref).sum() > 500 and np.isfinite(ref).sum() > 1200
    assert (np.isnan(got) != np.isnan(ref)).sum() == 0
    ok = np.isfinite(ref)
    np.testing.assert_allclose(got[ok], ref[ok], rtol=0, atol=0.02 if backend == "bisection" else 0.01)


def test_dda_and_mesh_match_float64_reference(device):
    """dda and mesh match a float64 brute-force reference (every triangle tested) to 1 cm, no flips."""
    terrain = wt.Terrain.synthetic("rugged", size_m=900.0, spacing=30.0, seed=8)
    o, d = _ray_set(terrain, 300, 1)
    ref = _reference_f64(terrain, o, d)
    for backend in ("dda", "mesh"):
        got = wt.raycast(terrain, o, d, backend=backend, device=device)
        assert (np.isnan(got) != np.isnan(ref)).sum() == 0, backend
        ok = np.isfinite(ref)
        np.testing.assert_allclose(got[ok], ref[ok], atol=0.01, err_msg=backend)


def test_grazing_rays_over_a_ridge(device):
    """Near-horizontal rays skimming a ridge: dda and mesh hit below the crest and miss above it, flipping
    against the float64 reference only where the ray clears the crest by < 1 cm. Bisection may jump a
    ridge thinner than its step (here: crossings less than ~50 m below the crest), then it misses
    (NaN): it never returns a range that is not on the surface."""
    n = 40
    heights = np.full((n, n), 100.0)
    heights[:, 20] = 300.0  # a ridge running north, one post wide
    terrain = wt.Terrain.from_grid(heights, spacing=25.0, origin=(0.0, 0.0), name="ridge")
    k = 200
    clear = np.linspace(-20.0, 20.0, k)  # height of the ray above the crest where it crosses it, m
    slope = 0.02
    e_cross = 20 * 25.0
    o = np.stack([np.full(k, 500.0), np.full(k, e_cross - 300.0), -(300.0 + clear + slope * 300.0)], axis=1)
    d = np.tile([0.0, 1.0, slope], (k, 1))
    ref = _reference_f64(terrain, o, d)
    got = wt.raycast(terrain, o, d, backend="bisection", device=device)
    ok = np.isfinite(got)
    np.testing.assert_allclose(got[ok], ref[ok], atol=0.02)
    for backend in ("dda", "mesh"):
        got = wt.raycast(terrain, o, d, backend=backend, device=device)
        flips = np.isnan(got) != np.isnan(ref)
        assert np.all(np.abs(clear[flips]) < 0.01), (backend, clear[flips])
        assert np.isfinite(got[clear < -0.5]).all() and np.isnan(got[clear > 0.5]).all(), backend
        ok = np.isfinite(ref) & np.isfinite(got)
        np.testing.assert_allclose(got[ok], ref[ok], atol=0.02, err_msg=backend)


def test_bisection_finds_the_first_surface_behind_a_thin_ridge(device):
    """A ray crossing a one-post-wide wall at mid-height stops at the wall with the default step (half a post),
    not at the ground behind it; a march step of 4 posts jumps over the wall (why the default is small)."""
    n = 60
    heights = np.full((n, n), 0.0)
    heights[:, 30] = 200.0
    terrain = wt.Terrain.from_grid(heights, spacing=30.0, name="wall")
    o = np.array([[900.0, 30 * 30.0 - 400.0, -300.0]])
    d = np.array([[0.0, 400.0, 200.0]])  # crosses the wall line at 100 m height
    exact = wt.raycast(terrain, o, d, backend="dda", device=device)[0]
    p = o[0] + exact * d[0] / np.linalg.norm(d[0])
    assert p[1] < 30 * 30.0 and -p[2] > 50.0  # the hit is on the wall's face
    fine = wt.raycast(terrain, o, d, backend="bisection", device=device)[0]
    assert fine == pytest.approx(exact, abs=0.02)
    coarse = wt.raycast(terrain, o, d, backend="bisection", device=device, step_m=120.0)[0]
    assert coarse > exact + 50.0


def test_pattern_form_matches_single_rays(device):
    """raycast_pattern (N poses × M directions) equals wt.raycast on the same rays."""
    terrain = _small_terrain()
    rng = np.random.default_rng(3)
    n_pose = 7
    pos = np.stack([rng.uniform(-500, 500, n_pose), rng.uniform(-500, 500, n_pose),
                    np.full(n_pose, -(terrain.h_max + 200))], axis=1)
    quat = wt.frames.euler_to_quat(rng.uniform(-0.3, 0.3, n_pose), rng.uniform(-0.3, 0.3, n_pose),
                                   rng.uniform(-3, 3, n_pose))
    pattern = wt.ScanPattern.grid(4, 5)
    got = raycast_pattern(terrain, wp.array(pos.astype(np.float32), dtype=wp.vec3, device=device),
                          wp.array(quat.astype(np.float32), dtype=wp.vec4, device=device),
                          pattern.device_dirs(device), wt.RayCaster("dda")).numpy()
    dirs_n = np.einsum("nij,mj->nmi", wt.frames.quat_to_mat(quat), pattern.dirs_s).reshape(-1, 3)
    ref = wt.raycast(terrain, np.repeat(pos, pattern.m, axis=0), dirs_n, backend="dda", device=device)
    np.testing.assert_allclose(got.ravel(), ref, atol=0.01)


def test_nodata_hole_gives_nan(device):
    """Rays that come down into a nodata hole return NaN on every backend, not a range beyond it."""
    heights = np.full((30, 30), 50.0)
    heights[10:20, 10:20] = np.nan
    terrain = wt.Terrain.from_grid(heights, spacing=10.0)
    o = np.array([[150.0, 150.0, -200.0], [150.0, 20.0, -200.0]])
    d = np.array([[0.0, 0.1, 1.0], [0.0, 0.0, 1.0]])
    for backend in ("dda", "mesh", "bisection"):
        r = wt.raycast(terrain, o, d, backend=backend, device=device)
        assert np.isnan(r[0]) and r[1] == pytest.approx(150.0, abs=1e-3), backend


@pytest.mark.parametrize(("origins", "dirs", "message"), [
    ([[0, 0, -500]], [[0, 0, 0]], "zero-length or not finite"),
    ([[0, 0, -500]], [[0, np.inf, 1]], "zero-length or not finite"),
    ([[np.nan, 0, -500]], [[0, 0, 1]], "origins are not finite"),
    ([[0, 0, -500], [0, 0, -500]], [[0, 0, 1]], "same number of rays"),
    ([[0, 0]], [[0, 0, 1]], r"shape \(K, 3\)"),
])
def test_bad_rays_are_value_errors(origins, dirs, message):
    """Bad rays raise a ValueError that names the problem."""
    with pytest.raises(ValueError, match=message):
        wt.raycast(_small_terrain(), np.array(origins, float), np.array(dirs, float), device="cpu")


def test_unknown_backend():
    """An unknown backend name lists the valid ones."""
    with pytest.raises(ValueError, match=r"unknown ray-cast backend 'optix'.*mesh, dda, bisection"):
        wt.raycast(_small_terrain(), np.zeros((1, 3)), np.array([[0.0, 0, 1]]), backend="optix")


def test_mismatched_devices():
    """Warp inputs on two devices are rejected (needs a GPU)."""
    if not wp.get_cuda_device_count():
        pytest.skip("needs a CUDA device to have two devices")
    o = wp.zeros(1, dtype=wp.vec3, device="cpu")
    d = wp.array([wp.vec3(0.0, 0.0, 1.0)], dtype=wp.vec3, device="cuda:0")
    with pytest.raises(ValueError, match="origins_n is on cpu but dirs_n on cuda:0"):
        wt.raycast(_small_terrain(), o, d)


def test_residual_forms_agree_bit_for_bit(device):
    """The per-particle form of the ray residuals (the CPU's: one thread loops over a particle's rays) writes the same
    bits as the per-ray form on the CPU (the same values elsewhere; a normal may differ only at a hit on a triangle's
    edge, where the two forms may take either triangle's), with invalid points, an origin under the ground,
    rays within a block's reach (the DDA starts at the local band: :func:`warptan.kernels.raycast.local_band_entry`)
    and rays beyond it; and those ranges match the float64 reference."""
    import warptan.kernels.raycast as kray
    from warptan.kernels.likelihood import CLOUD_ROW_LEN, cloud_row

    terrain = wt.Terrain.synthetic("rugged", size_m=3000.0, spacing=30.0, seed=9)
    rng = np.random.default_rng(4)
    n, m = 12, 40
    pos = np.stack([rng.uniform(-600, 600, n), rng.uniform(-600, 600, n), np.full(n, -(terrain.h_max + 20))], 1)
    pos[3, 2] = -(terrain.height_at(pos[3, 0], pos[3, 1]) - 5.0)  # underground: every ray NaN
    pos[5, 2] = -(terrain.h_max + 2500.0)  # high: the reach exceeds a block's, the whole band is marched
    quat = wt.frames.euler_to_quat(rng.uniform(-0.2, 0.2, n), rng.uniform(-0.2, 0.2, n), rng.uniform(-3, 3, n))
    dirs = np.stack([rng.uniform(-0.4, 0.4, m), rng.uniform(-0.4, 0.4, m), np.ones(m)], 1)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    cloud = np.zeros((1, m, CLOUD_ROW_LEN), np.float32)
    cloud[0, :, 3:6], cloud[0, :, 6], cloud[0, :, 7] = dirs, 800.0, 1.0
    cloud[0, ::7, 7] = 0.0  # invalid points
    cloud[0, :, :3] = dirs * 800.0
    grid = terrain.grid(device)
    args = [grid, wp.uint64(0), kray.BACKEND_DDA, 15.0, 12, 0, n, wp.array(pos.astype(np.float32), dtype=wp.vec3,
            device=device), wp.array(quat.astype(np.float32), dtype=wp.vec4, device=device),
            wp.array(cloud, dtype=cloud_row, device=device)]
    outs = []
    for kernel, dim in ((kray.raycast_residual_kernel, (n, m)), (kray.raycast_residual_rows_kernel, n)):
        res = wp.zeros((n, m), dtype=wp.float32, device=device)
        nrm = wp.zeros((n, m), dtype=wp.vec3, device=device)
        vert = wp.zeros((n, m), dtype=wp.float32, device=device)
        wp.launch(kernel, dim=dim, inputs=args, outputs=[res, nrm, 1, vert], device=device)
        outs.append([a.numpy() for a in (res, nrm, vert)])
    dirs_n = np.einsum("nij,mj->nmi", wt.frames.quat_to_mat(quat), dirs)
    # the per-particle form's normal is its hit triangle's (cell_hit), the per-ray form's the map read at the hit
    # point: they may differ only where the hit lies on a triangle's edge (within EDGE_EPS), where the read can
    # place it in the neighbour
    differ = ~np.isclose(outs[0][1], outs[1][1], rtol=1e-4, atol=1e-3).all(axis=-1) & np.isfinite(outs[0][0])
    assert differ.mean() < 0.02
    hit_pts = pos[:, None, :] + (800.0 - outs[0][0])[..., None] * dirs_n
    u = (hit_pts[..., 0] - terrain.n0) / terrain.dn
    v = (hit_pts[..., 1] - terrain.e0) / terrain.de
    fu, fv = u - np.floor(u), v - np.floor(v)
    edge = np.min([fu, 1.0 - fu, fv, 1.0 - fv, np.abs(fu - fv)], axis=0) < 1e-3
    assert edge[differ].all()
    outs[1][1][differ] = outs[0][1][differ]
    for a, b in zip(*outs, strict=True):  # the CPU runs the per-particle form; CUDA's compiler may contract otherwise
        if wt.resolve_device(device).is_cpu:
            np.testing.assert_array_equal(a, b)
        else:
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-3)
    res = outs[0][0]
    assert np.isnan(res[3]).all() and np.isnan(res[:, ::7]).all()
    ok = np.ones((n, m), bool)
    ok[3], ok[:, ::7] = False, False
    ref = _reference_f64(terrain, np.repeat(pos, m, axis=0), dirs_n.reshape(-1, 3)).reshape(n, m)
    assert (np.isnan(res[ok]) == np.isnan(ref[ok])).all() and np.isfinite(res[ok]).mean() > 0.9
    hit = ok & np.isfinite(ref)
    np.testing.assert_allclose((800.0 - res)[hit], ref[hit], atol=0.01)
    reach = np.hypot(dirs_n[..., 0], dirs_n[..., 1]) * (-pos[:, 2:3] - terrain.h_min) / dirs_n[..., 2]
    block_reach = kray.BLOCK_CELLS * min(terrain.dn, terrain.de)
    assert (reach[5] > block_reach).mean() > 0.8 and (reach[ok] < block_reach).mean() > 0.3
