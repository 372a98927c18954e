# Over 500 lines on purpose: Terrain is the one object users hold (heights, frame, CRS, device copies), and its
# loaders, height queries, map statistics and views are its methods; what is not (raster I/O, generated surfaces,
# mesh files, maps and worlds) lives in the sibling modules.
"""Terrain: a DEM as a regular north/east height grid, its samplers and its triangle mesh (design notes §2, §9).

Posts are at ``north = n0 + i*dn``, ``east = e0 + j*de`` (``i`` grows north); heights are metres above
MSL, positive up, and a point at NED position ``p`` is on the terrain when ``p_z = -h(p_x, p_y)``.
Nodata is kept as a mask (NaN heights); a cell is valid only when its four posts are valid, and every
sampler reports a position off the grid or in an invalid cell as invalid (NaN), never clamped.

The device-side copies (a :class:`warptan.kernels.terrain.HeightGrid` and the ``wp.Mesh`` of the
triangulated grid, built with the SAH BVH constructor) are built lazily, once per device, and cached.
"""

from __future__ import annotations

import functools
import math
import os
import warnings
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import warp as wp

from warptan.checks import LOCAL_FRAME_M
from warptan.device import resolve_device
from warptan.kernels import terrain as kterrain
from warptan.terrain.raster import (
    MAX_POSTS,
    TerrainError,
    check_read_memory,
    check_spacing,
    latlon_to_projected,
    projected_to_latlon,
    read_raster,
)

NAMED_TERRAINS = {
    "rugged": "thuringia_hilly_srtm3_crop44km.tif",
    "rugged30": "san_gabriel_rugged_srtm1_30m_utm11.tif",
    "flat": "ganges_plain_flat_srtm3_crop24km.tif",
}
"""Real terrains shipped with the package (``warptan/data/dem``, provenance in its README.md): ``rugged`` SRTM3
Thuringia (±22 km, ≈ 93 × 59 m posts), ``rugged30`` SRTM1 San Gabriel Mountains (19 × 36 km, 30 m UTM), ``flat``
SRTM3 Ganges plain (±12 km)."""
PLAUSIBLE_HEIGHTS_M = (-500.0, 9000.0)
"""Heights a land DEM can hold (the Dead Sea shore is at −430 m, Everest at 8 849 m): posts outside are nodata
(a fill value the file does not declare, a corrupt post), with a :class:`TerrainWarning`. Pass another
``valid_range_m`` for bathymetry."""
_SYNTHETIC_DEFAULTS = {"size_m": 20_000.0, "spacing": 30.0, "seed": 0}
"""A generated terrain's default options (:meth:`Terrain.synthetic`; its name lists the others)."""
DEM_DIR_ENV = "WARPTAN_DEM_DIR"
"""A folder that, when set, replaces the package's copies of the named terrains (same file names, or the
``.npz`` of :meth:`Terrain.save_npz` for machines without rasterio)."""


class TerrainWarning(UserWarning):
    """A DEM was loaded but changed: posts outside the plausible height range were made nodata."""


def named_terrain_file(name: str) -> Path:
    """The file of a named terrain: ``$WARPTAN_DEM_DIR/FILE`` (``.tif`` or ``.npz``) when that variable is set,
    else the package's copy.

    Raises:
        TerrainError: an unknown name, or ``WARPTAN_DEM_DIR`` set to a folder without the file.
    """
    if name not in NAMED_TERRAINS:
        raise TerrainError(f"unknown terrain name {name!r}; use one of {', '.join(NAMED_TERRAINS)}, "
                           "'synthetic:rugged', 'synthetic:flat' or a DEM file")
    file = NAMED_TERRAINS[name]
    folder = os.environ.get(DEM_DIR_ENV)
    if folder:
        for candidate in (Path(folder) / file, (Path(folder) / file).with_suffix(".npz")):
            if candidate.exists():
                return candidate
        raise TerrainError(f"{DEM_DIR_ENV}={folder} holds neither {file} nor its .npz (terrain {name!r}); "
                           f"unset {DEM_DIR_ENV} to use the package's copy")
    return Path(str(resources.files("warptan") / "data" / "dem" / file))


def _check_npz_size(path) -> None:
    """Refuse (TerrainError) a ``.npz`` whose heights exceed :data:`~warptan.terrain.raster.MAX_POSTS` posts or the
    memory available, from the array's header (before it is decompressed: a 945 kB file held 81 M posts, 5.4 GB)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive, archive.open("heights_m.npy") as f:
            version = np.lib.format.read_magic(f)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, _ = read(f)
    except (KeyError, ValueError, OSError, zipfile.BadZipFile) as err:
        raise TerrainError(f"{path}: not a terrain saved by Terrain.save_npz ({err})") from None
    posts = int(np.prod(shape)) if len(shape) else 1
    if len(shape) != 2 or posts > MAX_POSTS:
        raise TerrainError(f"{path}: heights of shape {shape} ({posts} posts; a DEM is 2-D, at most {MAX_POSTS} "
                           "posts); crop or coarsen it first")
    check_read_memory(path, shape[0], shape[1], "crop or coarsen it first")


def terrain_source_file(spec) -> Path | None:
    """The file a terrain spec of :meth:`Terrain.load` reads (a named terrain's file, a DEM path without its
    ``#band=N``), or None (a ``synthetic:`` spec, a name or path that is not a file): what an output must never
    replace or hold."""
    if not isinstance(spec, (str, os.PathLike)):
        return None
    text = os.fspath(spec)
    if text in NAMED_TERRAINS:
        try:
            return named_terrain_file(text)
        except TerrainError:
            return None
    if text.startswith("synthetic:"):
        return None
    head, sep, _ = text.rpartition("#band=")
    for candidate in ((text, head) if sep else (text,)):
        if os.path.exists(candidate):
            return Path(candidate)
    return None


@dataclass(eq=False)
class Terrain:
    """A height grid in the local NED frame, with optional geographic reference.

    Build one with :meth:`from_raster`, :meth:`synthetic`, :meth:`from_grid` or :meth:`load` rather than
    directly.
    """

    heights_m: np.ndarray
    """(rows, cols) float64 post heights above MSL in m, positive up; NaN = nodata. Row 0 is south."""
    n0: float
    """North coordinate of post row 0, m."""
    e0: float
    """East coordinate of post column 0, m."""
    dn: float
    """Post spacing north, m."""
    de: float
    """Post spacing east, m."""
    crs_wkt: str | None = None
    """Metric CRS of the grid (WKT), or None for a terrain without geographic reference."""
    origin_xy: tuple[float, float] = (0.0, 0.0)
    """Projected (x east, y north) coordinates of the NED origin in ``crs_wkt``, m."""
    name: str = "terrain"
    """Where it came from (file path or ``synthetic:kind``)."""
    description: str = ""
    """One line on the source and the processing."""
    valid_range_m: tuple[float, float] = PLAUSIBLE_HEIGHTS_M
    """Heights outside ``[low, high]`` m are nodata (with a :class:`TerrainWarning`); :data:`PLAUSIBLE_HEIGHTS_M`."""
    _device_cache: dict = field(default_factory=dict, repr=False, init=False)
    # not an __init__ field: dataclasses.replace(terrain, heights_m=...) must not share the old grid's device copies

    def __post_init__(self):
        try:
            h = np.asarray(self.heights_m, dtype=np.float64)
        except (TypeError, ValueError):
            raise TerrainError(f"{self.name}: heights must be a 2-D array of numbers, got "
                               f"{type(self.heights_m).__name__}") from None
        if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
            raise TerrainError(f"{self.name}: heights must be a 2-D grid of at least 2×2 posts, got {h.shape}")
        for key in ("dn", "de"):
            check_spacing(getattr(self, key), f"{self.name}: {key}")
        for key in ("n0", "e0"):
            value = getattr(self, key)
            if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and abs(value) < LOCAL_FRAME_M):
                raise TerrainError(f"{self.name}: {key} = {value!r} must be a finite number of metres (|{key}| < "
                                   f"{LOCAL_FRAME_M:g})")
        low, high = (float(v) for v in self.valid_range_m)
        if not low < high:
            raise TerrainError(f"{self.name}: valid_range_m = {self.valid_range_m!r} must be (low, high), low < high")
        self.valid_range_m = (low, high)
        h = h.copy()
        h[~np.isfinite(h)] = np.nan
        with np.errstate(invalid="ignore"):
            implausible = (h < low) | (h > high)
        if implausible.any():
            bad = h[implausible]
            warnings.warn(f"{self.name}: {bad.size} post(s) outside the plausible {low:g}…{high:g} m (from "
                          f"{bad.min():.6g} to {bad.max():.6g} m) treated as nodata", TerrainWarning, stacklevel=3)
            h[implausible] = np.nan
        if not np.isfinite(h).any():
            raise TerrainError(f"{self.name}: every post is nodata (or outside {low:g}…{high:g} m)")
        self.heights_m = h
        self.n0, self.e0, self.dn, self.de = float(self.n0), float(self.e0), float(self.dn), float(self.de)
        self.valid_posts = np.isfinite(h)
        """(rows, cols) bool: post has data."""
        corners = np.stack([h[:-1, :-1], h[1:, :-1], h[:-1, 1:], h[1:, 1:]])
        self.valid_cells = np.isfinite(corners).all(axis=0)
        """(rows-1, cols-1) bool: all four posts of the cell have data."""
        with np.errstate(invalid="ignore"):
            self.cell_max_m = np.where(self.valid_cells, corners.max(axis=0), np.inf)
        """(rows-1, cols-1) highest post of each cell in m (+inf for an invalid cell)."""
        self.h_min = float(np.nanmin(h))
        self.h_max = float(np.nanmax(h))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_raster(cls, path: str | os.PathLike, spacing: float | None = None, onto: Terrain | None = None, *,
                    valid_range_m: tuple[float, float] = PLAUSIBLE_HEIGHTS_M, allow_network: bool = False,
                    allow_raw_vrt: bool = False, band: int | None = None, posts=None) -> Terrain:
        """Load a DEM file (DTED, SRTM .hgt, GeoTIFF, a VRT of them; see :mod:`warptan.terrain.raster` for the
        projection).

        Args:
            path: The raster file.
            spacing: Post spacing in m for both axes; None keeps the native spacing.
            onto: Another (georeferenced) terrain whose NED frame this one shares: the raster is resampled into
                that terrain's CRS and origin (a map of the same ground from another source).
            valid_range_m: Plausible heights; posts outside are nodata (with a warning).
            allow_network, allow_raw_vrt: Allow a DEM (or VRT source) read over the network, a VRT raw band.
            band: The band holding the heights (1-based); required for a raster of several bands.
            posts: ``(crs_wkt, origin_xy, (n0, e0, dn, de, rows, cols))``: another grid's frame and posts, which a
                raster that is resampled anyway takes when its own spacing is theirs (:func:`warptan.terrain.raster.
                read_raster`); a flight log's DEM posts (:attr:`warptan.io.flightlog.FlightLog.dem_posts`) make another
                cut of its DEM the same map. Not with ``onto``.
        """
        frame = lattice = None
        if posts is not None:
            if onto is not None:
                raise TerrainError(f"{path}: give onto or posts, not both")
            frame, lattice = (posts[0], tuple(posts[1])), tuple(float(v) for v in posts[2])
        if onto is not None:
            if not onto.crs_wkt:
                raise TerrainError(f"{path}: cannot be placed onto {onto.name}, which has no geographic reference "
                                   "(a generated or array terrain)")
            frame = (onto.crs_wkt, onto.origin_xy)
        grid = read_raster(path, spacing, frame, band=band, posts=lattice, allow_network=allow_network,
                           allow_raw_vrt=allow_raw_vrt)
        return cls(
            grid.heights_m, grid.n0, grid.e0, grid.dn, grid.de, crs_wkt=grid.crs_wkt, origin_xy=grid.origin_xy,
            name=os.fspath(path), description=grid.description, valid_range_m=valid_range_m,
        )

    @classmethod
    def synthetic(cls, kind: str = "rugged", size_m: float = _SYNTHETIC_DEFAULTS["size_m"],
                  spacing: float = _SYNTHETIC_DEFAULTS["spacing"], seed: int = _SYNTHETIC_DEFAULTS["seed"]) -> Terrain:
        """A deterministic generated terrain centred on the NED origin.

        ``rugged``: a fractal (power-law spectrum, several octaves) surface with about 800 m of relief,
        hills of several kilometres down to ridges of a few posts; ``flat``: a gently undulating plain with
        a few metres of relief. Same ``(kind, size_m, spacing, seed)``, same heights.

        Args:
            kind: "rugged" or "flat".
            size_m: Side of the square area in m.
            spacing: Post spacing in m.
            seed: Random seed.
        """
        from warptan.terrain.synthetic import synthetic_heights

        given = {"size_m": size_m, "spacing": spacing, "seed": seed}
        heights, half, spacing, size_m = synthetic_heights(kind, size_m, spacing, seed)  # (checks the options)
        options = "".join(f",{k}={v:g}" for k, v in given.items() if v != _SYNTHETIC_DEFAULTS[k])
        return cls(  # (named by its spec, non-default options kept: another seed is another terrain)
            heights, -half, -half, spacing, spacing, name=f"synthetic:{kind}{options}",
            description=f"synthetic {kind} terrain, {size_m:g} m square, {spacing:g} m posts, seed {seed}",
        )

    @classmethod
    def from_grid(
        cls, heights_m: np.ndarray, spacing: float | tuple[float, float], origin: tuple[float, float] = (0.0, 0.0),
        name: str = "grid", valid_range_m: tuple[float, float] = PLAUSIBLE_HEIGHTS_M,
    ) -> Terrain:
        """A terrain from a (rows, cols) height array (row 0 south) with post 0,0 at ``origin`` = (n0, e0)."""
        dn, de = (spacing, spacing) if np.isscalar(spacing) else spacing
        return cls(heights_m, origin[0], origin[1], dn, de, name=name, description=f"grid from an array, {name}",
                   valid_range_m=valid_range_m)

    @classmethod
    def load(cls, spec: str | os.PathLike, spacing: float | None = None, **raster_options) -> Terrain:
        """Load from a name of :data:`NAMED_TERRAINS` (``rugged``, ``rugged30``, ``flat``: real DEMs shipped with the
        package), a file (raster or ``.npz`` saved by :meth:`save_npz`) or a ``synthetic:KIND[,key=value...]``
        spec (keys ``size_m``, ``spacing``, ``seed``), e.g. ``synthetic:rugged,size_m=10000,seed=3``; a raster of
        several bands as ``FILE#band=N``.
        ``raster_options`` (``valid_range_m``, ``allow_network``, ``allow_raw_vrt``, ``band``, ``posts``) go to
        :meth:`from_raster`."""
        if not isinstance(spec, (str, os.PathLike)):
            raise TerrainError(f"a terrain is a name ({', '.join(NAMED_TERRAINS)}), a DEM path or a 'synthetic:KIND' "
                               f"spec, got {type(spec).__name__} {spec!r}")
        text = os.fspath(spec)
        if text in NAMED_TERRAINS:
            file = named_terrain_file(text)
            terrain = cls.from_npz(file) if file.suffix == ".npz" else cls.from_raster(file, spacing=spacing,
                                                                                       **raster_options)
            terrain.name = f"{text}:{NAMED_TERRAINS[text]}"
            terrain.description = f"{terrain.description} (read from {file})"
            return terrain
        if text.startswith("synthetic:"):
            kind, *pairs = text[len("synthetic:"):].split(",")
            kwargs: dict = {}
            for pair in pairs:
                key, sep, value = pair.partition("=")
                if not sep or key not in ("size_m", "spacing", "seed"):
                    raise TerrainError(f"{text}: bad option {pair!r}; use size_m=, spacing=, seed=")
                if key in kwargs:  # (the last one was taken silently)
                    raise TerrainError(f"{text}: option {key} given twice")
                try:
                    kwargs[key] = int(value) if key == "seed" else float(value)
                except ValueError:
                    raise TerrainError(f"{text}: option {key} needs a number, got {value!r}") from None
                number = kwargs[key]
                if not (math.isfinite(number) and (number >= 0 if key == "seed" else number > 0)):
                    raise TerrainError(f"{text}: option {key} must be " + ("a whole number ≥ 0" if key == "seed" else
                                                                            "a positive number of metres") +
                                       f", got {value}")
            if spacing is not None:
                kwargs["spacing"] = spacing
            return cls.synthetic(kind, **kwargs)
        if text.endswith(".npz"):
            return cls.from_npz(text)
        head, sep, value = text.rpartition("#band=")
        if sep:
            try:
                raster_options["band"] = int(value)
            except ValueError:
                raise TerrainError(f"{text}: band needs a whole number, got {value!r}") from None
            text = head
        return cls.from_raster(text, spacing=spacing, **raster_options)

    # ------------------------------------------------------------------ persistence
    def save_npz(self, path: str | os.PathLike) -> None:
        """Save the grid and its reference to ``.npz`` (for machines without rasterio)."""
        np.savez_compressed(
            path, heights_m=self.heights_m, grid=np.array([self.n0, self.e0, self.dn, self.de]),
            origin_xy=np.array(self.origin_xy), crs_wkt=np.array(self.crs_wkt or ""), name=np.array(self.name),
            description=np.array(self.description),
        )

    @classmethod
    def from_npz(cls, path: str | os.PathLike) -> Terrain:
        """Load a terrain saved by :meth:`save_npz`."""
        if not os.path.exists(path):
            raise FileNotFoundError(f"terrain file not found: {path}")
        _check_npz_size(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                n0, e0, dn, de = (float(v) for v in z["grid"])
                return cls(
                    z["heights_m"], n0, e0, dn, de, crs_wkt=str(z["crs_wkt"]) or None,
                    origin_xy=tuple(float(v) for v in z["origin_xy"]), name=str(z["name"]),
                    description=str(z["description"]),
                )
        except (KeyError, ValueError, OSError) as err:
            raise TerrainError(f"{path}: not a terrain saved by Terrain.save_npz ({err})") from None

    # ------------------------------------------------------------------ geometry
    @property
    def shape(self) -> tuple[int, int]:
        """(rows north, cols east)."""
        return self.heights_m.shape

    @property
    def bounds_ne(self) -> tuple[float, float, float, float]:
        """(north_min, north_max, east_min, east_max) of the posts, m."""
        rows, cols = self.shape
        return self.n0, self.n0 + (rows - 1) * self.dn, self.e0, self.e0 + (cols - 1) * self.de

    @property
    def nodata_fraction(self) -> float:
        """Fraction of posts without data."""
        return float(1.0 - self.valid_posts.mean())

    def contains(self, north, east) -> np.ndarray:
        """True where ``(north, east)`` lies inside the post extent (validity of the data not checked)."""
        n_min, n_max, e_min, e_max = self.bounds_ne
        north, east = np.asarray(north, dtype=np.float64), np.asarray(east, dtype=np.float64)
        return (north >= n_min) & (north <= n_max) & (east >= e_min) & (east <= e_max)

    def _cells(self, north, east):
        north = np.asarray(north, dtype=np.float64)
        east = np.asarray(east, dtype=np.float64)
        rows, cols = self.shape
        u = (north - self.n0) / self.dn
        v = (east - self.e0) / self.de
        with np.errstate(invalid="ignore"):
            inside = (u >= 0) & (u <= rows - 1) & (v >= 0) & (v <= cols - 1)
        i = np.clip(np.floor(np.where(inside, u, 0)).astype(np.int64), 0, rows - 2)
        j = np.clip(np.floor(np.where(inside, v, 0)).astype(np.int64), 0, cols - 2)
        h = self.heights_m
        return inside, u - i, v - j, h[i, j], h[i + 1, j], h[i, j + 1], h[i + 1, j + 1]

    def height_at(self, north, east) -> np.ndarray:
        """Bilinear terrain height (m above MSL) at NED horizontal positions, float64, on the host.

        Args:
            north, east: Arrays (broadcastable) of positions in m.

        Returns:
            Heights in m; NaN off the grid or in a cell with a nodata post.
        """
        inside, fu, fv, h00, h10, h01, h11 = self._cells(north, east)
        h = (1 - fu) * ((1 - fv) * h00 + fv * h01) + fu * ((1 - fv) * h10 + fv * h11)
        return np.where(inside, h, np.nan)

    def surface_height_at(self, north, east) -> np.ndarray:
        """Height (m) of the triangulated surface (what the mesh and ray casts see); NaN where invalid."""
        inside, fu, fv, h00, h10, h01, h11 = self._cells(north, east)
        lower = h00 + fu * (h10 - h00) + fv * (h11 - h10)
        upper = h00 + fv * (h01 - h00) + fu * (h11 - h01)
        h = np.where(fu >= fv, lower, upper)
        h = np.where(np.isfinite(h00 + h10 + h01 + h11), h, np.nan)
        return np.where(inside, h, np.nan)

    def gradient_at(self, north, east, surface: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """``(∂h/∂north, ∂h/∂east)`` of the bilinear (default) or triangulated surface at NED horizontal positions,
        float64, on the host (the expressions of :func:`warptan.kernels.terrain.grid_gradient`); NaN where invalid."""
        inside, fu, fv, h00, h10, h01, h11 = self._cells(north, east)
        if surface:
            lower = fu >= fv
            gn = np.where(lower, h10 - h00, h11 - h01) / self.dn
            ge = np.where(lower, h11 - h10, h01 - h00) / self.de
        else:
            gn = ((1 - fv) * (h10 - h00) + fv * (h11 - h01)) / self.dn
            ge = ((1 - fu) * (h01 - h00) + fu * (h11 - h10)) / self.de
        ok = inside & np.isfinite(h00 + h10 + h01 + h11)
        return np.where(ok, gn, np.nan), np.where(ok, ge, np.nan)

    @functools.cached_property
    def bilinear_mismatch_sigma_m(self) -> float:
        """RMS difference (m) between the bilinear height and the triangulated surface over the valid cells.

        In a cell with corner heights ``h00, h10, h01, h11`` the two interpolants differ by ``c·u(1-v)`` (or
        ``c·v(1-u)`` in the other triangle) with the twist ``c = h00 - h10 - h01 + h11``; its mean square over a
        triangle is ``c²/90``. This is the map error a model that reads bilinear heights (sliding, altimeter)
        sees when the world is the triangulated grid (the surface the ray casts, and the simulated sensor, see).
        """
        h = self.heights_m
        twist = (h[:-1, :-1] - h[1:, :-1] - h[:-1, 1:] + h[1:, 1:])[self.valid_cells]
        return float(np.sqrt(np.mean(twist**2) / 90.0)) if twist.size else 0.0

    def holdout_rms_m(self, k: int, noise_m: float = 0.0) -> float | None:
        """RMS error (m) of predicting this grid's posts by bilinear interpolation of every ``k``-th post: the map
        error of this terrain resampled to ``k`` times its spacing, measured on itself. The share of a known white
        post noise ``noise_m`` (in the held-out post and in the four it is predicted from, ``1 + Σw²`` times its
        variance) is removed. None when the grid has fewer than 2×2 posts at ``k`` times its spacing."""
        h = self.heights_m
        big_r, big_c = (h.shape[0] - 1) // k, (h.shape[1] - 1) // k  # coarse cells
        if big_r < 1 or big_c < 1:
            return None
        coarse = h[: big_r * k + 1: k, : big_c * k + 1: k]
        block = h[: big_r * k, : big_c * k].reshape(big_r, k, big_c, k)
        fu = (np.arange(k) / k)[None, :, None, None]
        fv = (np.arange(k) / k)[None, None, None, :]
        pred = ((1 - fu) * (1 - fv) * coarse[:-1, None, :-1, None] + fu * (1 - fv) * coarse[1:, None, :-1, None]
                + (1 - fu) * fv * coarse[:-1, None, 1:, None] + fu * fv * coarse[1:, None, 1:, None])
        held_out = np.ones((1, k, 1, k), dtype=bool)
        held_out[0, 0, 0, 0] = False  # the coarse post itself
        err = np.broadcast_to(np.where(held_out, block - pred, np.nan), pred.shape)
        sum_w2 = np.broadcast_to(((1 - fu) ** 2 + fu**2) * ((1 - fv) ** 2 + fv**2), pred.shape)
        ok = np.isfinite(err)
        if not ok.any():
            return None
        mean_sq = float(np.mean(err[ok] ** 2)) - noise_m**2 * float(np.mean(1.0 + sum_w2[ok]))
        return math.sqrt(max(mean_sq, 0.0))

    def interpolation_sigma_m(self, noise_m: float = 0.0) -> float:
        """Estimated RMS error (m) of this grid's bilinear heights against the ground it samples, from the grid
        alone (its post spacing and roughness): ``e(d) = e(2d) / 2^α``, where ``e(kd)`` is
        :meth:`holdout_rms_m` (the grid predicting its own posts from every k-th one, the known post noise
        removed) and ``α = log2(e(4d) / e(2d))`` clipped to [0.5, 2] extrapolates the scaling of the error with
        the spacing one octave down (α = 2: smooth terrain, the error of a bilinear interpolant grows with the
        curvature × d²; α ≈ 0.5: rough, Brownian-like relief). The held-out posts lie mid-cell, where the error is
        largest, so the estimate errs high (on a quadratic surface by 20 %). This is the map error a model sees
        when the world is finer than its map (the likelihood's map σ,
        :func:`warptan.sim.scenarios.scenario_likelihood`). """
        e2, e4 = self.holdout_rms_m(2, noise_m), self.holdout_rms_m(4, noise_m)
        if not e2:
            return 0.0
        alpha = 2.0 if not e4 else min(max(math.log2(e4 / e2), 0.5), 2.0)
        return e2 / 2.0**alpha

    @functools.cached_property
    def slope_rms(self) -> float:
        """The RMS of the slope's magnitude ``|∇h|`` over the grid's posts (central differences, nodata left out):
        the typical slope that turns a vertical map error into a horizontal fix error
        (:meth:`warptan.sensing.likelihood.Likelihood.fix_sigma_m`). Measured: the 90 m rugged tile 0.14, the 30 m
        rugged tile 0.45, the 90 m flat tile 0.014."""
        gn, ge = np.gradient(np.asarray(self.heights_m, dtype=np.float64), self.dn, self.de)
        square = gn**2 + ge**2
        return float(np.sqrt(np.nanmean(square))) if np.isfinite(square).any() else 0.0

    @functools.cached_property
    def slope_correlation_m(self) -> float:
        """Correlation length (m) of the terrain's slope: the lag at which the autocorrelation of ``∂h/∂north``
        along north, and of ``∂h/∂east`` along east, first falls below 1/e (their mean; FFT of the whole grid,
        nodata as zero slope). It is the scale on which the pattern of gradients that turns a vertical map error into
        a position fix changes (:meth:`warptan.sensing.likelihood.Likelihood.fix_process`). Measured: the 90 m rugged
        tile 280/240 m, the 30 m rugged tile 180/150 m, the 90 m flat tile 90/80 m (one post: its slope is noise)."""
        gn, ge = np.gradient(np.asarray(self.heights_m, dtype=np.float64), self.dn, self.de)
        lags = []
        for g, spacing, axis in ((gn, self.dn, 0), (ge, self.de, 1)):
            g = np.nan_to_num(g - np.nanmean(g))
            n = g.shape[axis]
            spectrum = np.fft.rfft(g, n=2 * n, axis=axis)
            ac = np.fft.irfft(spectrum * np.conj(spectrum), axis=axis).mean(axis=1 - axis)[:n]
            if ac[0] > 0:  # an axis along which the ground does not slope says nothing
                below = np.flatnonzero(ac < ac[0] / math.e)
                lags.append((below[0] if below.size else n) * spacing)
        return float(max(np.mean(lags) if lags else 0.0, min(self.dn, self.de)))

    def coarsened(self, factor_n: int, factor_e: int | None = None) -> Terrain:
        """A coarser map of this terrain: the mean of each block of ``factor_n × factor_e`` posts (a DEM product
        resampled by averaging), its post at the block's centre; a block with a nodata post is nodata."""
        fn, fe = int(factor_n), int(factor_n if factor_e is None else factor_e)
        if fn < 1 or fe < 1:
            raise TerrainError(f"{self.name}: coarsening factors must be ≥ 1, got {fn}×{fe}")
        if fn == fe == 1:
            return self
        rows, cols = self.shape[0] // fn, self.shape[1] // fe
        if rows < 2 or cols < 2:
            raise TerrainError(f"{self.name}: coarsening by {fn}×{fe} leaves fewer than 2×2 posts")
        h = self.heights_m[: rows * fn, : cols * fe].reshape(rows, fn, cols, fe).mean(axis=(1, 3))
        return Terrain(h, self.n0 + 0.5 * (fn - 1) * self.dn, self.e0 + 0.5 * (fe - 1) * self.de, self.dn * fn,
                       self.de * fe, crs_wkt=self.crs_wkt, origin_xy=self.origin_xy, valid_range_m=self.valid_range_m,
                       name=f"{self.name} (block mean {fn}×{fe})",
                       description=f"{self.description}; block mean of {fn}×{fe} posts")

    # ------------------------------------------------------------------ geographic reference
    def _require_crs(self) -> str:
        if not self.crs_wkt:
            raise TerrainError(f"{self.name}: terrain has no geographic reference (synthetic or array terrain)")
        return self.crs_wkt

    def latlon_to_ne(self, lat, lon) -> tuple[np.ndarray, np.ndarray]:
        """Geographic (degrees, WGS84) -> this terrain's (north, east) in m."""
        x, y = latlon_to_projected(self._require_crs(), np.asarray(lat, float), np.asarray(lon, float))
        return y - self.origin_xy[1], x - self.origin_xy[0]

    def ne_to_latlon(self, north, east) -> tuple[np.ndarray, np.ndarray]:
        """This terrain's (north, east) in m -> geographic (lat, lon) in degrees, WGS84."""
        x = np.asarray(east, float) + self.origin_xy[0]
        y = np.asarray(north, float) + self.origin_xy[1]
        return projected_to_latlon(self._require_crs(), x, y)

    # ------------------------------------------------------------------ device side
    def _device_entry(self, device) -> dict:
        device = resolve_device(device)
        entry = self._device_cache.get(device.alias)
        if entry is None:
            entry = {"device": device}
            self._device_cache[device.alias] = entry
        return entry

    def grid(self, device=None) -> kterrain.HeightGrid:
        """The :class:`~warptan.kernels.terrain.HeightGrid` on ``device`` (cached)."""
        entry = self._device_entry(device)
        if "grid" not in entry:
            g = kterrain.HeightGrid()
            g.heights = wp.array(self.heights_m.astype(np.float32), dtype=wp.float32, device=entry["device"])
            g.cell_max = wp.array(self.cell_max_m.astype(np.float32), dtype=wp.float32, device=entry["device"])
            g.n0, g.e0, g.dn, g.de = self.n0, self.e0, self.dn, self.de
            g.h_min, g.h_max = self.h_min, self.h_max
            g.inv_dn, g.inv_de = 1.0 / self.dn, 1.0 / self.de
            g.block_top = wp.array(self.block_top_m().astype(np.float32), dtype=wp.float32, device=entry["device"])
            entry["grid"] = g
        return entry["grid"]

    def block_top_m(self, block: int = kterrain.BLOCK_CELLS) -> np.ndarray:
        """Per block of ``block`` × ``block`` cells (the last row and column of blocks may be smaller), the highest
        post in m of the block and its eight neighbours (+inf where one of their cells is invalid): an upper bound
        of the surface within ``block`` cells of any point of the block (:func:`warptan.kernels.raycast.
        local_band_entry`)."""
        cm = self.cell_max_m
        nb_i, nb_j = -(-cm.shape[0] // block), -(-cm.shape[1] // block)
        padded = np.full((nb_i * block, nb_j * block), -np.inf)
        padded[:cm.shape[0], :cm.shape[1]] = cm
        tops = padded.reshape(nb_i, block, nb_j, block).max(axis=(1, 3))
        ring = np.pad(tops, 1, constant_values=-np.inf)
        return np.max([ring[a:a + nb_i, b:b + nb_j] for a in range(3) for b in range(3)], axis=0)

    def mesh_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (rows*cols, 3) NED in m (z = -height; 0 at nodata posts, which no face uses) and faces
        (F, 3) int32, two per valid cell, diagonal (i,j)-(i+1,j+1), wound with normals pointing up."""
        rows, cols = self.shape
        north = self.n0 + self.dn * np.arange(rows)
        east = self.e0 + self.de * np.arange(cols)
        nn, ee = np.meshgrid(north, east, indexing="ij")
        verts = np.stack([nn, ee, -np.nan_to_num(self.heights_m, nan=0.0)], axis=-1).reshape(-1, 3)
        ci, cj = np.nonzero(self.valid_cells)
        v00 = ci * cols + cj
        v10, v01, v11 = v00 + cols, v00 + 1, v00 + cols + 1
        faces = np.concatenate([np.stack([v00, v11, v10], 1), np.stack([v00, v01, v11], 1)]).astype(np.int32)
        return verts, faces

    def mesh(self, device=None) -> wp.Mesh:
        """The triangulated grid as a ``wp.Mesh`` on ``device`` (SAH BVH; built once per device, cached)."""
        entry = self._device_entry(device)
        if "mesh" not in entry:
            verts, faces = self.mesh_arrays()
            d = entry["device"]
            points = wp.array(verts.astype(np.float32), dtype=wp.vec3, device=d)
            indices = wp.array(faces.ravel(), dtype=wp.int32, device=d)
            entry["mesh"] = wp.Mesh(points=points, indices=indices, bvh_constructor="sah")
        return entry["mesh"]

    def sample(self, north_m: wp.array, east_m: wp.array, surface: bool = False, out: wp.array | None = None):
        """Batch-sample heights on the device of the input arrays (float32; NaN = invalid).

        Args:
            north_m, east_m: (K,) float32 Warp arrays on the same device.
            surface: False for bilinear heights, True for the triangulated surface.
            out: Optional (K,) float32 output array.
        """
        if north_m.device != east_m.device or north_m.shape != east_m.shape:
            raise ValueError(
                f"north_m and east_m must share device and shape, got {north_m.device}/{north_m.shape} "
                f"and {east_m.device}/{east_m.shape}"
            )
        device = north_m.device
        if out is None:
            out = wp.empty(north_m.shape, dtype=wp.float32, device=device)
        elif out.device != device or out.shape != north_m.shape:
            raise ValueError(f"out must be on {device} with shape {north_m.shape}")
        wp.launch(kterrain.sample_heights_kernel, dim=north_m.shape[0],
                  inputs=[self.grid(device), int(bool(surface)), north_m, east_m], outputs=[out], device=device)
        return out

    def information_map(self, dirs_body, altitude_agl_m: float, sigma_m: float, **options):
        """The Fisher information of a scan about the horizontal position at every post, and its 1σ bound
        (:func:`warptan.terrain.information.information_map`, which takes the ``options``)."""
        from warptan.terrain.information import information_map

        return information_map(self, dirs_body, altitude_agl_m, sigma_m, **options)

    # ------------------------------------------------------------------ export (warptan.terrain.meshfile)
    def to_trimesh(self, frame: str = "ned"):
        """The triangulated grid as a ``trimesh.Trimesh`` in NED (default) or ENU (x east, y north, z up)."""
        from warptan.terrain.meshfile import to_trimesh

        return to_trimesh(self, frame)

    def export(self, path: str | os.PathLike, frame: str = "enu", overwrite: bool = False) -> None:
        """Write the mesh for viewing (.ply, .glb, .obj, .stl; ENU with z up by default). An existing file is
        replaced only with ``overwrite=True`` (whole or not at all); a failed write names the file and leaves
        it as it was (:func:`warptan.terrain.meshfile.export_mesh`)."""
        from warptan.terrain.meshfile import export_mesh

        export_mesh(self, path, frame, overwrite)

    def info(self) -> dict:
        """A summary for people: source, CRS, bounds, spacing, shape, height range, nodata fraction."""
        n_min, n_max, e_min, e_max = self.bounds_ne
        out = {
            "name": self.name,
            "description": self.description,
            "crs": _crs_summary(self.crs_wkt),
            "shape": list(self.shape),
            "spacing_m": [self.dn, self.de],
            "bounds_ne_m": [n_min, n_max, e_min, e_max],
            "height_range_m": [self.h_min, self.h_max],
            "nodata_fraction": self.nodata_fraction,
        }
        if self.crs_wkt:
            lat, lon = self.ne_to_latlon(np.array([n_min, n_max]), np.array([e_min, e_max]))
            out["bounds_latlon_deg"] = [float(lat[0]), float(lat[1]), float(lon[0]), float(lon[1])]
        return out


def _crs_summary(crs_wkt: str | None) -> str:
    if not crs_wkt:
        return "none (local NED grid)"
    from rasterio.crs import CRS

    crs = CRS.from_wkt(crs_wkt)
    epsg = crs.to_epsg()
    if epsg:
        return f"EPSG:{epsg}"
    params = crs.to_dict()
    if params.get("proj") == "tmerc":
        return f"transverse Mercator, lat_0={params.get('lat_0', 0):.4f}, lon_0={params.get('lon_0', 0):.4f}, WGS84"
    return crs.to_string()
