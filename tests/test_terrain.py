"""Terrain: loading real DEMs, bad input, synthetic terrains, samplers and mesh (design notes §2)."""

import numpy as np
import pytest
import warp as wp
from conftest import BOSPHORUS, GANGES, THURINGIA, dem_path

from warptan import Terrain, TerrainError


def _write_tif(path, data, crs="EPSG:32632", transform=None, nodata=None):
    import rasterio
    from rasterio.transform import from_origin

    transform = transform or from_origin(600_000.0, 5_600_000.0, 30.0, 30.0)
    with rasterio.open(path, "w", driver="GTiff", height=data.shape[0], width=data.shape[1], count=1,
                       dtype=data.dtype, crs=crs, transform=transform, nodata=nodata) as dst:
        dst.write(data, 1)
    return str(path)


def _bilinear_reference(h, n0, e0, dn, de, north, east):
    """Float64 bilinear interpolation written independently of the package (loop over points)."""
    rows, cols = h.shape
    out = np.full(len(north), np.nan)
    for k, (n, e) in enumerate(zip(north, east, strict=True)):
        u, v = (n - n0) / dn, (e - e0) / de
        if not (0 <= u <= rows - 1 and 0 <= v <= cols - 1):
            continue
        i, j = min(int(u), rows - 2), min(int(v), cols - 2)
        a, b = u - i, v - j
        cell = h[i:i + 2, j:j + 2]
        if np.isnan(cell).any():
            continue
        out[k] = (cell[0, 0] * (1 - a) * (1 - b) + cell[1, 0] * a * (1 - b)
                  + cell[0, 1] * (1 - a) * b + cell[1, 1] * a * b)
    return out


def _holey_terrain():
    t = Terrain.synthetic("rugged", size_m=3000.0, spacing=30.0, seed=4)
    h = t.heights_m.copy()
    h[40:44, 50:53] = np.nan
    h[10, 10] = np.nan
    return Terrain.from_grid(h, spacing=(30.0, 25.0), origin=(-1500.0, -1250.0), name="holey")


# ---------------------------------------------------------------- real DEMs
def test_thuringia_highest_post_is_grosser_beerberg(thuringia):
    """height_at(latlon_to_ne(Großer Beerberg)) is within a few metres of its 983 m."""
    north, east = thuringia.latlon_to_ne(50.658, 10.744)
    assert abs(float(thuringia.height_at(north, east)) - 983.0) < 5.0
    assert abs(thuringia.h_max - 983.0) < 5.0


def test_thuringia_nodata_posts_are_masked(thuringia):
    """The tile's void posts (nodata -32768) read as NaN, never as -32768 or 0 m."""
    import rasterio

    with rasterio.open(dem_path(THURINGIA)) as src:
        band = src.read(1, masked=True)
        rows, cols = np.nonzero(np.ma.getmaskarray(band))
        xs, ys = rasterio.transform.xy(src.transform, rows, cols)
    assert len(rows) == 28
    north, east = thuringia.latlon_to_ne(np.asarray(ys), np.asarray(xs))
    assert np.isnan(thuringia.height_at(north, east)).all()
    valid = thuringia.heights_m[thuringia.valid_posts]
    assert valid.min() > 150.0  # no -32768 and no 0 m leaked into the data


def test_latlon_round_trip_below_one_millimetre(thuringia):
    """latlon_to_ne and ne_to_latlon invert each other to < 1 mm over the tile."""
    rng = np.random.default_rng(0)
    lat, lon = rng.uniform(50.0, 51.0, 200), rng.uniform(10.0, 11.0, 200)
    north, east = thuringia.latlon_to_ne(lat, lon)
    lat2, lon2 = thuringia.ne_to_latlon(north, east)
    north2, east2 = thuringia.latlon_to_ne(lat2, lon2)
    assert np.max(np.hypot(north2 - north, east2 - east)) < 1e-3
    assert np.max(np.abs(lat2 - lat)) < 1e-8 and np.max(np.abs(lon2 - lon)) < 1e-8


def test_real_tiles_load():
    """The Bosphorus DTED0 crop and the flat Ganges tile load with plausible shapes and heights."""
    bos = Terrain.from_raster(dem_path(BOSPHORUS))
    assert 60 <= bos.shape[0] <= 80 and 100 <= bos.shape[1] <= 130
    assert bos.h_min == pytest.approx(0.0, abs=1.0) and 400.0 < bos.h_max < 470.0
    ganges = Terrain.from_raster(dem_path(GANGES))
    assert 150.0 < ganges.h_min and ganges.h_max < 240.0


def test_srtm_hgt_and_dted_files_load(tmp_path):
    """The same data as SRTM .hgt (the Ganges tile converted) and as DTED level 0 (a generated tile) load
    through rasterio's drivers and give the heights of the GeoTIFF."""
    import rasterio
    import rasterio.shutil
    from rasterio.transform import from_origin

    with rasterio.open(dem_path(GANGES)) as src:
        profile = {k: v for k, v in src.profile.items() if k not in ("compress", "tiled", "blockxsize",
                                                                      "blockysize", "interleave")}
        data = src.read(1)
    hgt = tmp_path / "N28E078.hgt"
    with rasterio.open(hgt, "w", **{**profile, "driver": "SRTMHGT"}) as dst:
        dst.write(data, 1)
    a, b = Terrain.from_raster(dem_path(GANGES)), Terrain.from_raster(hgt)
    np.testing.assert_array_equal(np.isnan(a.heights_m), np.isnan(b.heights_m))
    np.testing.assert_allclose(a.heights_m[a.valid_posts], b.heights_m[b.valid_posts])

    tile = (100 + np.add.outer(np.arange(121)[::-1], np.arange(121))).astype(np.int16)  # a plane: 1 m a post
    tif = _write_tif(tmp_path / "tile.tif", tile, crs="EPSG:4326",
                     transform=from_origin(29.0 - 0.5 / 120, 42.0 + 0.5 / 120, 1 / 120, 1 / 120), nodata=-32767)
    rasterio.shutil.copy(tif, tmp_path / "n41.dt0", driver="DTED")
    dted = Terrain.from_raster(tmp_path / "n41.dt0")
    assert dted.dn == pytest.approx(926.6, abs=2.0) and 100 <= dted.h_min and dted.h_max <= 340
    n, e = dted.latlon_to_ne(41.5, 29.5)
    assert float(dted.height_at(n, e)) == pytest.approx(tile[60, 60], abs=0.5)


def test_resampling_spacing(thuringia):
    """spacing= resamples to square posts and keeps heights (coarser grid, same region)."""
    coarse = Terrain.from_raster(dem_path(THURINGIA), spacing=500.0)
    assert coarse.dn == coarse.de == 500.0
    n_min, n_max, _e_min, _e_max = coarse.bounds_ne
    assert n_max - n_min == pytest.approx(111_000.0, rel=0.02)
    # Compare on a set of interior points: bilinear of a 500 m grid vs the native one, rugged terrain.
    rng = np.random.default_rng(1)
    north, east = rng.uniform(-40_000, 40_000, 500), rng.uniform(-25_000, 25_000, 500)
    diff = coarse.height_at(north, east) - thuringia.height_at(north, east)
    assert np.nanmedian(np.abs(diff)) < 20.0


def test_projected_metric_raster_keeps_native_posts(tmp_path):
    """A UTM GeoTIFF is used as it is: same posts (rows flipped to grow north), origin at its centre."""
    data = np.arange(20 * 30, dtype=np.float32).reshape(20, 30)
    data[3, 4] = -9999.0
    t = Terrain.from_raster(_write_tif(tmp_path / "utm.tif", data, nodata=-9999.0))
    assert t.shape == (20, 30) and t.dn == t.de == 30.0
    assert np.isnan(t.heights_m[20 - 1 - 3, 4])
    np.testing.assert_array_equal(t.heights_m[t.valid_posts], data[::-1][t.valid_posts])
    n_min, n_max, e_min, e_max = t.bounds_ne
    assert n_min == pytest.approx(-n_max) and e_min == pytest.approx(-e_max)
    # The NE post (row 0 of the file, last column) is at UTM x = 600000 + 29.5*30, y = 5600000 - 15.
    lat, lon = t.ne_to_latlon(n_max, e_max)
    from warptan.terrain.raster import latlon_to_projected

    x, y = latlon_to_projected(t.crs_wkt, lat, lon)
    assert float(x) == pytest.approx(600_000.0 + 29.5 * 30.0, abs=1e-3)
    assert float(y) == pytest.approx(5_600_000.0 - 15.0, abs=1e-3)


def test_dem_with_holes_loads_masked(tmp_path):
    """A geographic DEM with a nodata hole loads; the hole is masked after reprojection, not filled."""
    from rasterio.transform import from_origin

    rng = np.random.default_rng(2)
    data = (300.0 + 10.0 * rng.standard_normal((120, 120))).astype(np.int16)
    data[50:55, 60:70] = -32768
    path = _write_tif(tmp_path / "holes.tif", data, crs="EPSG:4326",
                      transform=from_origin(10.0, 51.0, 1 / 1200, 1 / 1200), nodata=-32768)
    t = Terrain.from_raster(path)
    lat = 51.0 - (52.5 / 1200)
    lon = 10.0 + (65.0 / 1200)
    assert np.isnan(t.height_at(*t.latlon_to_ne(lat, lon)))
    assert 0.0 < t.nodata_fraction < 0.2
    assert np.nanmin(t.heights_m) > 200.0


# ---------------------------------------------------------------- bad input
def test_missing_file_is_named():
    """A missing file raises FileNotFoundError naming it."""
    with pytest.raises(FileNotFoundError, match=r"no_such_dem\.tif"):
        Terrain.from_raster("/nonexistent/no_such_dem.tif")


def test_not_a_raster(tmp_path):
    """A text file is rejected as 'not a raster', naming the file."""
    path = tmp_path / "notes.tif"
    path.write_text("this is not a DEM")
    with pytest.raises(TerrainError, match=r"notes\.tif.*not a raster"):
        Terrain.from_raster(path)


def test_raster_without_crs(tmp_path):
    """A raster with no CRS cannot be placed on the metric grid."""
    path = _write_tif(tmp_path / "nocrs.tif", np.ones((10, 10), np.float32), crs=None)
    with pytest.raises(TerrainError, match=r"nocrs\.tif.*no CRS"):
        Terrain.from_raster(path)


def test_all_nodata_raster(tmp_path):
    """A raster whose every post is nodata is rejected."""
    path = _write_tif(tmp_path / "empty.tif", np.full((10, 10), -1.0, np.float32), nodata=-1.0)
    with pytest.raises(TerrainError, match=r"empty\.tif.*nodata"):
        Terrain.from_raster(path)


@pytest.mark.parametrize("spacing", [0.0, -30.0, float("nan"), "abc"])
def test_non_positive_spacing(spacing, tmp_path):
    """Non-positive or non-numeric spacing is rejected for rasters and synthetic terrains."""
    path = _write_tif(tmp_path / "ok.tif", np.ones((10, 10), np.float32))
    with pytest.raises(TerrainError, match="spacing"):
        Terrain.from_raster(path, spacing=spacing)
    with pytest.raises(TerrainError, match="spacing"):
        Terrain.synthetic("rugged", spacing=spacing)


def test_unknown_synthetic_kind():
    """An unknown synthetic kind names itself and the valid kinds."""
    with pytest.raises(TerrainError, match=r"'bumpy'.*rugged, flat"):
        Terrain.synthetic("bumpy")


# ---------------------------------------------------------------- synthetic
def test_synthetic_is_deterministic_with_the_promised_relief():
    """Same seed, same heights; rugged has hundreds of metres of relief, flat a few metres."""
    a = Terrain.synthetic("rugged", size_m=8000.0, spacing=40.0, seed=3)
    b = Terrain.synthetic("rugged", size_m=8000.0, spacing=40.0, seed=3)
    c = Terrain.synthetic("rugged", size_m=8000.0, spacing=40.0, seed=4)
    np.testing.assert_array_equal(a.heights_m, b.heights_m)
    assert not np.array_equal(a.heights_m, c.heights_m)
    assert 300.0 < np.ptp(a.heights_m) < 1500.0
    # Several scales: relief inside 1 km windows is still tens of metres.
    win = a.heights_m[:25, :25]
    assert np.ptp(win) > 10.0
    flat = Terrain.synthetic("flat", size_m=8000.0, spacing=40.0, seed=3)
    assert 1.0 < np.ptp(flat.heights_m) < 10.0


def test_npz_round_trip(tmp_path):
    """save_npz / load keep heights, mask and geographic reference."""
    t = _holey_terrain()
    t.save_npz(tmp_path / "t.npz")
    u = Terrain.load(str(tmp_path / "t.npz"))
    np.testing.assert_array_equal(np.isnan(t.heights_m), np.isnan(u.heights_m))
    np.testing.assert_array_equal(t.heights_m[t.valid_posts], u.heights_m[u.valid_posts])
    assert (u.n0, u.e0, u.dn, u.de) == (t.n0, t.e0, t.dn, t.de)


# ---------------------------------------------------------------- samplers
def _query_points(t, count, seed):
    rng = np.random.default_rng(seed)
    n_min, n_max, e_min, e_max = t.bounds_ne
    north = rng.uniform(n_min - 100.0, n_max + 100.0, count)
    east = rng.uniform(e_min - 100.0, e_max + 100.0, count)
    north[:3], east[:3] = n_min, e_min  # exact corner posts
    north[3], east[3] = n_max, e_max
    north[4] = np.nan
    return north, east


def test_host_bilinear_matches_reference():
    """height_at (host, float64) equals an independent bilinear reference, NaN off-grid and in holes."""
    t = _holey_terrain()
    north, east = _query_points(t, 3000, 0)
    ref = _bilinear_reference(t.heights_m, t.n0, t.e0, t.dn, t.de, north, east)
    got = t.height_at(north, east)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
    assert np.isnan(ref).sum() > 100 and (~np.isnan(ref)).sum() > 2000


def test_device_bilinear_matches_reference(device):
    """The bilinear kernel matches the float64 reference to float32 precision on every device."""
    t = _holey_terrain()
    north, east = _query_points(t, 5000, 1)
    ref = _bilinear_reference(t.heights_m, t.n0, t.e0, t.dn, t.de, north, east)
    n32 = wp.array(north.astype(np.float32), dtype=wp.float32, device=device)
    e32 = wp.array(east.astype(np.float32), dtype=wp.float32, device=device)
    got = t.sample(n32, e32).numpy()
    # Compare with the reference evaluated at the float32-rounded coordinates (what the kernel sees).
    ref32 = _bilinear_reference(t.heights_m, t.n0, t.e0, t.dn, t.de, north.astype(np.float32).astype(float),
                                east.astype(np.float32).astype(float))
    # Points within float32 rounding of the border may flip validity; everything else must agree.
    both = ~np.isnan(ref32) & ~np.isnan(got)
    assert (np.isnan(got) != np.isnan(ref32)).sum() == 0
    np.testing.assert_allclose(got[both], ref32[both], rtol=0, atol=1e-3)  # float32 at ~1000 m: 6e-5 m ulp
    assert np.isnan(ref).sum() > 100


def test_device_surface_matches_host(device):
    """The triangulated-surface kernel matches Terrain.surface_height_at (float64) on every device."""
    t = _holey_terrain()
    north, east = _query_points(t, 5000, 2)
    north, east = north.astype(np.float32).astype(float), east.astype(np.float32).astype(float)
    got = t.sample(wp.array(north, dtype=wp.float32, device=device), wp.array(east, dtype=wp.float32, device=device),
                   surface=True).numpy()
    ref = t.surface_height_at(north, east)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    ok = ~np.isnan(ref)
    np.testing.assert_allclose(got[ok], ref[ok], rtol=0, atol=1e-3)
    # bilinear and surface agree on posts
    rows, cols = t.shape
    pn = t.n0 + t.dn * np.arange(rows)[:, None] + 0 * np.arange(cols)[None, :]
    pe = t.e0 + t.de * np.arange(cols)[None, :] + 0 * np.arange(rows)[:, None]
    np.testing.assert_allclose(t.surface_height_at(pn, pe), t.height_at(pn, pe), atol=1e-9)


def test_sample_rejects_mismatched_arrays():
    """Inputs of different shapes are a clear ValueError."""
    t = _holey_terrain()
    a = wp.zeros(5, dtype=wp.float32, device="cpu")
    b = wp.zeros(6, dtype=wp.float32, device="cpu")
    with pytest.raises(ValueError, match="share device and shape"):
        t.sample(a, b)


# ---------------------------------------------------------------- mesh
@wp.kernel
def _vertical_rays_kernel(mesh: wp.uint64, north: wp.array(dtype=float), east: wp.array(dtype=float),
                          start_z: float, t_out: wp.array(dtype=float)):
    k = wp.tid()
    q = wp.mesh_query_ray(mesh, wp.vec3(north[k], east[k], start_z), wp.vec3(0.0, 0.0, 1.0), 1.0e7)
    t_out[k] = wp.where(q.result, q.t, wp.nan)


def test_mesh_vertices_and_vertical_rays(device):
    """Mesh vertices are the grid posts (z = -h); vertical rays hit the triangulated surface, which is
    height_at on posts and cell edges; rays over holes or off the grid miss."""
    t = _holey_terrain()
    mesh = t.mesh(device)
    assert t.mesh(device) is mesh  # cached per device
    verts = mesh.points.numpy()
    rows, cols = t.shape
    valid = t.valid_posts.ravel()
    np.testing.assert_allclose(-verts[valid, 2], t.heights_m.ravel()[valid], atol=1e-4)
    np.testing.assert_allclose(verts[:, 0].reshape(rows, cols)[:, 0], t.n0 + t.dn * np.arange(rows), atol=1e-3)

    north, east = _query_points(t, 4000, 3)
    north[4] = 0.0  # the NaN query point of _query_points is no ray
    # Add posts and points on cell edges, where the mesh surface equals the bilinear height (away from the
    # holes, where an edge shared by a valid and an invalid cell is legitimately both hit and invalid).
    ii, jj = np.meshgrid(np.arange(12, 38), np.arange(12, 48), indexing="ij")
    edge_n = np.concatenate([t.n0 + t.dn * ii.ravel(), t.n0 + t.dn * (ii.ravel() + 0.37)])
    edge_e = np.concatenate([t.e0 + t.de * (jj.ravel() + 0.61), t.e0 + t.de * jj.ravel()])
    north, east = np.concatenate([north, edge_n]), np.concatenate([east, edge_e])
    start = -(t.h_max + 100.0)
    out = wp.empty(len(north), dtype=float, device=device)
    wp.launch(_vertical_rays_kernel, dim=len(north), inputs=[mesh.id, wp.array(north, dtype=float, device=device),
              wp.array(east, dtype=float, device=device), start], outputs=[out], device=device)
    hit_height = -(start + out.numpy())
    surface = t.surface_height_at(north, east)
    np.testing.assert_array_equal(np.isnan(hit_height), np.isnan(surface))
    ok = ~np.isnan(surface)
    np.testing.assert_allclose(hit_height[ok], surface[ok], atol=2e-3)
    on_edges = slice(4000, None)
    assert not np.isnan(hit_height[on_edges]).any()
    np.testing.assert_allclose(hit_height[on_edges], t.height_at(north, east)[on_edges], atol=2e-3)


def test_trimesh_export(tmp_path):
    """to_trimesh has two faces per valid cell; export writes a PLY that trimesh reads back."""
    import trimesh

    t = _holey_terrain()
    tm = t.to_trimesh()
    assert len(tm.faces) == 2 * t.valid_cells.sum()
    t.export(tmp_path / "t.ply")
    back = trimesh.load(tmp_path / "t.ply")
    assert len(back.faces) == len(tm.faces)
    enu = t.to_trimesh("enu")
    assert (enu.face_normals[:, 2] > 0).all()  # faces point up
    with pytest.raises(ValueError, match="unsupported mesh format"):
        t.export(tmp_path / "t.xyz")


# ---------------------------------------------------------------------- package terrains, maps (issue 13)
@pytest.mark.parametrize("name, rows, cols, h_range", [
    ("rugged", (470, 490), (740, 760), (200.0, 990.0)),
    ("flat", (255, 270), (290, 305), (170.0, 225.0)),
    ("rugged30", (643, 643), (1197, 1197), (310.0, 2300.0)),
])
def test_named_terrains_ship_with_the_package(monkeypatch, name, rows, cols, h_range):
    """rugged / flat / rugged30 load from the package (no file outside the package, no environment variable), keep their
    georeference and name themselves the same on every machine."""
    from warptan.terrain.grid import NAMED_TERRAINS, named_terrain_file

    monkeypatch.delenv("WARPTAN_DEM_DIR", raising=False)
    path = named_terrain_file(name)
    assert path.exists() and path.parent.name == "dem" and path.parent.parent.name == "data"
    t = Terrain.load(name)
    assert t.name == f"{name}:{NAMED_TERRAINS[name]}"
    assert rows[0] <= t.shape[0] <= rows[1] and cols[0] <= t.shape[1] <= cols[1]
    assert h_range[0] <= t.h_min and t.h_max <= h_range[1] and t.nodata_fraction < 0.01  # reprojected edges
    assert t.crs_wkt


def test_package_crops_are_the_source_posts():
    """The package's Thuringia crop holds exactly the source tile's posts in its window (no resampling)."""
    import rasterio

    from warptan.terrain.grid import named_terrain_file

    with rasterio.open(dem_path(THURINGIA)) as src, rasterio.open(named_terrain_file("rugged")) as crop:
        r0, c0 = (src.height - crop.height) // 2, (src.width - crop.width) // 2
        window = src.read(1, window=rasterio.windows.Window(c0, r0, crop.width, crop.height))
        np.testing.assert_array_equal(crop.read(1), window)
        assert crop.transform.almost_equals(src.window_transform(rasterio.windows.Window(c0, r0, 1, 1)))


def test_dem_dir_override_and_missing_file(monkeypatch, tmp_path):
    """WARPTAN_DEM_DIR replaces the package copies (an .npz is enough); a folder without the file is a clear
    error, never a silent fallback to a generated terrain."""
    from warptan.terrain.grid import NAMED_TERRAINS

    monkeypatch.setenv("WARPTAN_DEM_DIR", str(tmp_path))
    with pytest.raises(TerrainError, match="holds neither"):
        Terrain.load("flat")
    Terrain.synthetic("flat", size_m=3000.0, spacing=100.0).save_npz(
        tmp_path / NAMED_TERRAINS["flat"].replace(".tif", ".npz"))
    t = Terrain.load("flat")
    assert t.name == f"flat:{NAMED_TERRAINS['flat']}" and t.shape == (31, 31)
    with pytest.raises(TerrainError, match="unknown terrain name"):
        from warptan.terrain.grid import named_terrain_file
        named_terrain_file("bumpy")


def test_coarsened_is_block_means_at_block_centres():
    h = np.arange(6 * 9, dtype=float).reshape(6, 9)
    t = Terrain.from_grid(h, 10.0, origin=(100.0, -50.0))
    c = t.coarsened(3)
    assert c.shape == (2, 3) and c.dn == c.de == 30.0
    assert c.heights_m[0, 0] == pytest.approx(h[:3, :3].mean()) and c.heights_m[1, 2] == pytest.approx(h[3:, 6:].mean())
    assert (c.n0, c.e0) == (110.0, -40.0)
    assert t.coarsened(1) is t


def test_interpolation_sigma_against_the_truth():
    """The map's interpolation error estimated from the map alone: a plane has none; on a quadratic surface it
    errs high by ≤ 25 % (analytic RMS c d² / √30 over a cell); on the 30 m tile, coarsened 2/3/6×, it is within
    30 % of the error measured against the 30 m triangles; known white post noise is removed from it."""
    x = np.arange(201) * 10.0
    plane = Terrain.from_grid(np.add.outer(0.3 * x, 0.1 * x), 10.0)
    assert plane.interpolation_sigma_m() == pytest.approx(0.0, abs=1e-9)
    c = 1e-3
    quad = Terrain.from_grid(np.tile(c * x[:, None] ** 2, (1, 201)), 10.0)
    truth = c * 10.0**2 / np.sqrt(30.0)
    assert truth <= quad.interpolation_sigma_m() <= 1.25 * truth
    world = Terrain.load("rugged30")
    rng = np.random.default_rng(0)
    n_min, n_max, e_min, e_max = world.bounds_ne
    north, east = rng.uniform(n_min + 600, n_max - 600, 50_000), rng.uniform(e_min + 600, e_max - 600, 50_000)
    for factor in (2, 3, 6):
        the_map = world.coarsened(factor)
        measured = np.sqrt(np.nanmean((the_map.height_at(north, east) - world.surface_height_at(north, east)) ** 2))
        assert 0.7 * measured <= the_map.interpolation_sigma_m() <= 1.3 * measured, factor
        noisy = Terrain(the_map.heights_m + rng.normal(0.0, 3.0, the_map.shape), the_map.n0, the_map.e0,
                        the_map.dn, the_map.de)
        assert noisy.interpolation_sigma_m(3.0) == pytest.approx(the_map.interpolation_sigma_m(), rel=0.1)


def test_raster_onto_another_terrains_frame(tmp_path):
    """A DEM read onto another terrain's frame lands where that terrain has the same ground: the same file
    read onto itself gives the same heights at the same NED positions."""
    world = Terrain.load("rugged30")
    from warptan.terrain.grid import named_terrain_file

    again = Terrain.from_raster(named_terrain_file("rugged30"), onto=world)
    assert again.origin_xy == world.origin_xy and again.dn == pytest.approx(30.0)
    rng = np.random.default_rng(2)
    n, e = rng.uniform(-8000, 8000, 2000), rng.uniform(-16000, 16000, 2000)
    np.testing.assert_allclose(again.height_at(n, e), world.height_at(n, e), atol=0.01)
    with pytest.raises(TerrainError, match="no geographic reference"):
        Terrain.from_raster(named_terrain_file("rugged30"), onto=Terrain.synthetic("flat", size_m=2000.0))


def test_a_replaced_terrain_samples_its_own_heights_not_the_cached_grid_of_the_original():
    """``dataclasses.replace(terrain, heights_m=...)`` is a new map: its device samples are its heights, not the grid
    the original had already uploaded (the cache was an init field and was copied with the rest)."""
    import dataclasses

    flat = Terrain.from_grid(np.zeros((20, 20)), 30.0)
    north, east = wp.array([150.0], dtype=wp.float32), wp.array([150.0], dtype=wp.float32)
    assert flat.sample(north, east).numpy()[0] == 0.0  # uploads the grid
    raised = dataclasses.replace(flat, heights_m=np.full((20, 20), 40.0))
    assert raised.sample(north, east).numpy()[0] == pytest.approx(40.0)
    assert flat.sample(north, east).numpy()[0] == 0.0


def test_the_slope_correlation_length_of_sinusoidal_ridges():
    """Ridges ``h = 50 sin(2π north / λ)``: the slope's autocorrelation is ``cos(2π lag / λ)``, below 1/e from
    ``lag = λ acos(1/e) / 2π`` (λ = 2 km: 381 m, to a post); the east axis, without slope, says nothing."""
    north = np.arange(400) * 30.0
    ridges = Terrain.from_grid(np.tile(50.0 * np.sin(2 * np.pi * north / 2000.0)[:, None], (1, 300)), 30.0)
    assert ridges.slope_correlation_m == pytest.approx(2000.0 * np.arccos(1 / np.e) / (2 * np.pi), abs=31.0)


def test_block_top_bounds_the_cells_within_reach():
    """``block_top_m``: per block, the highest post of the block and its neighbours (brute force), +inf next to a
    nodata post, on a grid whose cells do not fill the last blocks."""
    rng = np.random.default_rng(2)
    heights = rng.uniform(0.0, 500.0, (43, 30))
    heights[5, 27] = np.nan
    terrain = Terrain.from_grid(heights, spacing=10.0)
    top = terrain.block_top_m(block=4)
    cm = terrain.cell_max_m
    assert top.shape == (11, 8)
    for bi in range(11):
        for bj in range(8):
            want = cm[max(0, 4 * bi - 4):4 * bi + 8, max(0, 4 * bj - 4):4 * bj + 8].max()
            assert top[bi, bj] == want
    assert np.isinf(top[0, 5:]).all() and np.isfinite(top[3:, :5]).all()


def test_the_rms_slope_of_sinusoidal_ridges():
    """Ridges ``h = 50 sin(2π north / λ)``: ``|∇h| = 50 (2π / λ) |cos|``, RMS ``50 (2π / λ) / √2`` (0.111 for λ = 2 km;
    central differences on 30 m posts read the slope within 0.2 %)."""
    north = np.arange(400) * 30.0
    ridges = Terrain.from_grid(np.tile(50.0 * np.sin(2 * np.pi * north / 2000.0)[:, None], (1, 300)), 30.0)
    assert ridges.slope_rms == pytest.approx(50.0 * 2 * np.pi / 2000.0 / np.sqrt(2.0), rel=3e-3)
