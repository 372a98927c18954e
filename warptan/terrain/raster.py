"""Reading real DEMs (DTED, SRTM .hgt, GeoTIFF) into a metric north/east height grid (design notes §2).

rasterio is imported inside the functions: ``import warptan`` needs only numpy and warp.

Choices made here (the paper leaves them open):

* A geographic raster (lat/lon), a projected raster whose unit is not the metre, or a rotated one, is
  reprojected with rasterio to a transverse Mercator (scale 1, WGS84) centred on the raster's centre;
  that centre is the NED origin, grid north is the projection's y axis (true north on the central
  meridian, within the meridian convergence, about 0.4° at 50° N and 0.5° of longitude, elsewhere).
* ``spacing=None`` keeps the native post spacing: for a geographic raster the N-S and E-W spacings in
  metres at the centre (e.g. SRTM3 at 50° N: 92.6 m north, 59.6 m east), so no resolution is lost.
* Heights are resampled bilinearly. Nodata stays a mask: an output post is nodata when any source post
  that contributes to it is nodata, or when it lies outside the source footprint.
* A projected metric raster without ``spacing`` is used as it is (no resampling); its NED origin is the
  centre of its posts. A south-up or east-to-west raster (positive y or negative x pixel size) is flipped to
  north-up first; a degenerate geotransform (zero or non-finite pixel size) is refused.
* Files are opened defensively: a path that reaches the network (``http://``, ``/vsicurl/``, ``/vsis3/`` ...),
  and a GDAL VRT that reads raw bytes (``VRTRawRasterBand``, which turns any file into "heights") or whose sources
  reach the network, are refused unless the caller allows them (``allow_network``, ``allow_raw_vrt``). A VRT mosaic
  of local DEM files is read as usual.
"""

from __future__ import annotations

import math
import os
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from warptan.checks import check_positive, host_memory_available
from warptan.terrain.units import height_unit_factor, metre_grid, raster_centre

MAX_POSTS = 60_000_000
"""Largest grid (posts) a load may produce; beyond it the requested spacing is almost surely a mistake."""
SAME_POSTS_REL = 0.01
"""Relative difference of post spacings within which a resampled raster takes another grid's posts
(:func:`read_raster`'s ``posts``): the same product cut elsewhere differs by the change of a degree's length across
the cut (4e-4 for 2 km of SRTM3 at 50° N); another product's posts (1″ against 3″) by far more."""
MAX_SOURCE_POSTS = 4 * MAX_POSTS
"""Largest raster (pixels) read into memory to be reprojected (float64: 1.9 GB); crop a larger file first. A raster
read at native resolution (metric, north-up, no spacing) becomes the grid: :data:`MAX_POSTS` applies."""
READ_BYTES_PER_POST = 32
"""Host memory a native read takes per post, about: the band (float32 and its mask), its float64 copy, the flipped
grid — a peak of 20 B/post in NumPy buffers measured with tracemalloc on the 30 m tile — plus GDAL's block cache."""


NETWORK_PREFIXES = ("/vsicurl", "/vsis3", "/vsigs", "/vsiaz", "/vsiadls", "/vsioss", "/vsiswift", "/vsihdfs",
                    "/vsiwebhdfs")
"""GDAL virtual file systems that read over the network."""
NETWORK_DRIVERS = frozenset({"WMS", "WMTS", "WCS", "HTTP", "EEDA", "EEDAI", "DAAS", "PLMOSAIC", "STACIT", "STACTA",
                             "OGCAPI", "NGW"})
"""GDAL drivers whose "files" are service descriptions fetched over the network (e.g. a ``<GDAL_WMS>`` XML)."""
MAX_VRT_BYTES = 64 << 20
"""Largest VRT file whose sources are checked (a mosaic of ~100 000 tiles)."""
_SERVICE_TAGS = (b"<GDAL_WMS", b"<GDAL_WMTS", b"<GDAL_WCS", b"<WCS_GDAL", b"<WMS_Capabilities", b"<Capabilities")


class TerrainError(ValueError):
    """A DEM or terrain argument that cannot be used; the message names the file or argument."""


def _is_network(name: str) -> bool:
    text = name.strip()
    return "://" in text or any(text.startswith(p) or f"{p}/" in text or f"{p}_streaming/" in text
                                for p in NETWORK_PREFIXES)


def check_references(path: str, allow_network: bool = False, allow_raw_vrt: bool = False, _depth: int = 0) -> None:
    """Refuse a DEM path that reaches the network, and a GDAL VRT (followed through nested VRTs) with a raw band
    (``VRTRawRasterBand`` reads any file's bytes as heights) or a network source, unless allowed.

    Raises:
        TerrainError: naming the file and the element that is refused.
    """
    if _is_network(path):
        if allow_network:
            return
        raise TerrainError(f"{path}: reading a DEM over the network is refused (pass allow_network=True to allow it)")
    if _depth > 8:
        raise TerrainError(f"{path}: VRT sources nested more than 8 deep")
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 20)
    except OSError:
        return  # not a plain file (e.g. /vsizip/...): GDAL decides
    start = head.lstrip()
    if start.startswith(_SERVICE_TAGS) and not allow_network:
        raise TerrainError(f"{path}: a web-service description (WMS/WMTS/WCS): reading a DEM over the network is "
                           "refused (pass allow_network=True to allow it)")
    if not start.startswith(b"<VRTDataset"):
        return
    if len(head) == 1 << 20:  # a large VRT (a mosaic of many tiles): read it whole
        with open(path, "rb") as f:
            head = f.read(MAX_VRT_BYTES + 1)
        if len(head) > MAX_VRT_BYTES:
            raise TerrainError(f"{path}: a VRT larger than {MAX_VRT_BYTES >> 20} MiB")
    try:
        root = ET.fromstring(head)
    except ET.ParseError as err:
        raise TerrainError(f"{path}: a VRT that is not valid XML ({err})") from None
    for band in root.iter("VRTRasterBand"):
        sub = band.get("subClass", "")
        if sub == "VRTRawRasterBand" and not allow_raw_vrt:
            raise TerrainError(f"{path}: VRT band {band.get('band', '?')} is a VRTRawRasterBand (reads any file's raw "
                               "bytes as heights); refused (pass allow_raw_vrt=True to allow it)")
    for source in root.iter("SourceFilename"):
        name = (source.text or "").strip()
        if source.get("relativeToVRT", "0") == "1" and not name.startswith("/"):
            name = os.path.join(os.path.dirname(os.path.abspath(path)), name)
        if _is_network(name) and not allow_network:
            raise TerrainError(f"{path}: VRT source {name} reads over the network; refused (pass allow_network=True "
                               "to allow it)")
        if os.path.isfile(name):
            check_references(name, allow_network, allow_raw_vrt, _depth + 1)


def _north_up(data: np.ndarray, transform, path: str):
    """An axis-aligned raster flipped to north-up, west-to-east (positive x and negative y pixel size)."""
    from rasterio.transform import Affine

    a, b, c, d, e, f = (transform.a, transform.b, transform.c, transform.d, transform.e, transform.f)
    det = a * e - b * d
    if not all(math.isfinite(v) for v in (a, b, c, d, e, f)) or det == 0.0:
        raise TerrainError(f"{path}: degenerate geotransform (pixel size {a:g} × {e:g}, rotation {b:g}, {d:g}); "
                           "the file's georeferencing is broken")
    if b != 0.0 or d != 0.0:
        return data, transform  # rotated: the reprojection handles it
    rows, cols = data.shape
    if a < 0.0:
        data, c, a = data[:, ::-1], c + a * cols, -a
    if e > 0.0:
        data, f, e = data[::-1], f + e * rows, -e
    return np.ascontiguousarray(data), Affine(a, 0.0, c, 0.0, e, f)


def _corner_bounds(transform, rows: int, cols: int) -> tuple[float, float, float, float]:
    xs, ys = zip(*(transform * (i, j) for i in (0, cols) for j in (0, rows)), strict=True)
    return min(xs), min(ys), max(xs), max(ys)


@dataclass
class RasterGrid:
    """A DEM laid out as a north/east grid (row 0 is the southernmost row)."""

    heights_m: np.ndarray
    """(rows, cols) float64 heights above MSL in m, NaN where nodata."""
    n0: float
    e0: float
    dn: float
    de: float
    crs_wkt: str
    """The metric CRS of the grid (WKT)."""
    origin_xy: tuple[float, float]
    """Projected (x=east, y=north) coordinates of the NED origin in ``crs_wkt``, m."""
    description: str
    """One line: source CRS and what was done to it."""


def check_spacing(spacing: float | None, name: str = "spacing") -> float | None:
    """Validate a post spacing in metres (None passes through)."""
    if spacing is None:
        return None
    return check_positive(spacing, name, TerrainError)


def tmerc_crs(lat_deg: float, lon_deg: float):
    """A transverse Mercator CRS (WGS84, scale 1, no false origin) centred at ``(lat, lon)``."""
    from rasterio.crs import CRS

    return CRS.from_proj4(
        f"+proj=tmerc +lat_0={lat_deg:.10f} +lon_0={lon_deg:.10f} +k=1 +x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs"
    )


def read_raster(path: str | os.PathLike, spacing: float | None = None,
                frame: tuple[str, tuple[float, float]] | None = None, *, band: int | None = None,
                posts: tuple[float, ...] | None = None, allow_network: bool = False,
                allow_raw_vrt: bool = False) -> RasterGrid:
    """Read a DEM file's heights (its one band, or ``band`` of several) into a :class:`RasterGrid`.

    Args:
        path: DTED (.dt0/.dt1/.dt2), SRTM (.hgt), GeoTIFF or any single-band raster GDAL reads.
        spacing: Output post spacing in m (both axes); None keeps the native spacing.
        frame: ``(crs_wkt, origin_xy)`` of another terrain: the raster is resampled (bilinear) into that metric
            CRS with that NED origin, so that two DEMs of the same ground share one frame (a map that is not the
            world); None: a projected north-up raster keeps its own grid, anything else is reprojected to a
            transverse Mercator centred on it.
        band: The band holding the heights (1-based); required for a raster of several bands (without it, an error
            naming them).
        posts: ``(n0, e0, dn, de, rows, cols)``, with ``frame``: another grid in that frame (its first post north
            and east of the origin and spacings, m; its size). A raster that is resampled anyway (not a projected
            metric north-up grid) and whose own spacing there is theirs within :data:`SAME_POSTS_REL` is resampled
            onto that grid, whole (GDAL's bilinear warp weighs a post by the output's extent: the same posts in
            another window differ by up to 1.6 m on the rugged tile), and cut to the rows and columns it covers:
            another cut of the same DEM gives the same heights at the same places, but at its edges. Otherwise (and
            for a raster that holds none of those posts) ``frame`` and ``posts`` are not used: the raster is read as
            without them.
        allow_network: Allow a path, or VRT sources, that read over the network.
        allow_raw_vrt: Allow a VRT with a ``VRTRawRasterBand`` (raw bytes of another file read as heights).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        TerrainError: not a raster, no CRS, all nodata, a degenerate geotransform, a refused reference, a bad
            spacing, a grid too large, or several bands and no (or no such) ``band``.
    """
    spacing = check_spacing(spacing)
    path = os.fspath(path)
    check_references(path, allow_network, allow_raw_vrt)
    if not _is_network(path):  # (an allowed network path has no local file to look for)
        if not os.path.exists(path):
            raise FileNotFoundError(f"DEM file not found: {path}")
        if os.path.isdir(path):
            raise TerrainError(f"{path}: is a directory, not a DEM file")
    if posts is not None and (frame is None or spacing is not None):
        raise ValueError("posts need a frame and no spacing")
    return _read(path, spacing, frame, allow_raw_vrt, allow_network, band, posts)


def _gdal_errors() -> tuple[type[Exception], ...]:
    from rasterio.errors import RasterioError

    try:
        from rasterio._err import CPLE_BaseError
    except ImportError:  # a rasterio without the private module: its public errors only
        return (RasterioError,)
    return (RasterioError, CPLE_BaseError)


def _read(path: str, spacing, frame, allow_raw_vrt: bool, allow_network: bool, band: int | None = None,
          posts=None) -> RasterGrid:
    import rasterio

    errors = _gdal_errors()
    env = {"GDAL_VRT_ENABLE_PYTHON": "NO", "GTIFF_REPORT_COMPD_CS": "YES"}  # (a vertical CRS states the heights' unit)
    if not allow_raw_vrt:
        env["GDAL_VRT_ENABLE_RAWRASTERBAND"] = "NO"
    def opener(name):  # without allow_network, a file GDAL reads through a web-service driver is refused
        with warnings.catch_warnings():  # no georeferencing is reported by the checks below, in one line
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            src = rasterio.open(name)
        if not allow_network and src.driver.upper() in NETWORK_DRIVERS:
            src.close()
            raise TerrainError(f"{name}: GDAL reads it with the {src.driver} driver (a web service): reading a DEM "
                               "over the network is refused (pass allow_network=True to allow it)")
        return src

    try:
        with rasterio.Env(**env):
            return _read_open(path, spacing, frame, opener, errors, band, posts)
    except errors as err:
        raise TerrainError(f"{path}: GDAL cannot use this raster ({err})") from None


def _read_open(path: str, spacing, frame, opener, errors, band: int | None = None, posts=None) -> RasterGrid:
    try:
        src = opener(path)
    except errors as err:
        if _is_tiff(path):  # (a GeoTIFF cut before its header, which a writer may put at the end)
            raise TerrainError(f"{path}: a TIFF file GDAL cannot open: truncated or damaged ({err})") from None
        raise TerrainError(f"{path}: not a raster that rasterio/GDAL can read ({err})") from None
    with src:
        if src.count < 1:
            raise TerrainError(f"{path}: raster has no bands")
        band = _band(src, band, path)
        truncated = _truncation(src, path)
        if truncated:
            raise TerrainError(truncated)
        if src.crs is None:
            raise TerrainError(f"{path}: raster has no CRS (no georeferencing), cannot place it on a metric grid")
        if src.width < 2 or src.height < 2:
            raise TerrainError(f"{path}: raster is {src.height}×{src.width} pixels; a DEM needs at least 2×2 posts")
        conformal = metre_grid(src.crs, src.transform, src.width, src.height)
        native = spacing is None and (frame is None or posts is not None) and conformal
        height_factor, wrong = height_unit_factor(src, band)
        if wrong:
            raise TerrainError(f"{path}: {wrong}")
        # read at native resolution, the grid is the raster; reprojected at native resolution, about as many posts
        at_native = native or (spacing is None and frame is None)
        limit = MAX_POSTS if at_native else MAX_SOURCE_POSTS
        if src.width * src.height > limit:
            raise TerrainError(f"{path}: raster is {src.height}×{src.width} = {src.width * src.height} posts (limit "
                               f"{limit}{' at native resolution' if at_native else ''}); crop it first "
                               "(gdal_translate -projwin)" + (" or give a coarser spacing" if at_native else ""))
        check_read_memory(path, src.height, src.width, "crop it first (gdal_translate -projwin)")
        try:
            heights = src.read(band, masked=True)
        except errors as err:
            raise TerrainError(f"{path}: cannot read band {band} ({err})") from None
        data = np.ma.filled(heights.astype(np.float64), np.nan) * height_factor
        data[~np.isfinite(data)] = np.nan
        if not np.isfinite(data).any():
            raise TerrainError(f"{path}: every post is nodata (nodata value {src.nodata})")
        crs, transform = src.crs, src.transform
    data, transform = _north_up(data, transform, path)
    bounds = _corner_bounds(transform, *data.shape)
    if crs.is_geographic:
        west, south, east, north = bounds
        if south < -90.0 or north > 90.0 or west < -540.0 or east > 540.0:
            raise TerrainError(f"{path}: geographic raster spans latitude {south:g}…{north:g}°, longitude "
                               f"{west:g}…{east:g}°: outside the Earth; its georeferencing is broken")

    metric = conformal
    north_up = transform.b == 0.0 and transform.d == 0.0 and transform.e < 0.0 and transform.a > 0.0
    if posts is not None and metric and north_up:  # used as it is: no resampling, no posts to share
        frame, posts = None, None
    if frame is None and metric and north_up and spacing is None:
        return _native_grid(data, crs, transform, path)
    return _reprojected_grid(data, crs, transform, bounds, spacing, path, frame, posts)


def check_read_memory(path, rows: int, cols: int, remedy: str) -> None:
    """Refuse (TerrainError) reading ``rows × cols`` posts whose :data:`READ_BYTES_PER_POST` exceed 90 % of the
    host memory available, before anything is read."""
    need = READ_BYTES_PER_POST * rows * cols
    have = host_memory_available()
    if need > 0.9 * have:
        raise TerrainError(f"{path}: reading its {rows}×{cols} posts needs about {need / 1e9:.2g} GB of memory but "
                           f"{have / 1e9:.2g} GB is available; {remedy}")


def _is_tiff(path: str) -> bool:
    """The file starts as a TIFF does (little- or big-endian, classic or BigTIFF)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError:
        return False
    return head in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


def _band(src, band: int | None, path: str) -> int:
    """The band to read: ``band`` (1-based, checked), else the only one; a raster of several bands without ``band``
    is an error naming them (a DEM is one band; an RGB rendering or a stack of products is not one to guess)."""
    names = ", ".join(f"{i} ({src.descriptions[i - 1] or src.colorinterp[i - 1].name})"
                      for i in range(1, src.count + 1))
    if band is None:
        if src.count > 1:
            raise TerrainError(f"{path}: raster has {src.count} bands ({names}); say which holds the heights: "
                               f"'{path}#band=N' as a terrain spec, Terrain.from_raster(path, band=N)")
        return 1
    if isinstance(band, bool) or not isinstance(band, (int, np.integer)) or not 1 <= band <= src.count:
        raise TerrainError(f"{path}: band {band!r} does not exist; the raster has {src.count} band(s) ({names})")
    return int(band)


def _truncation(src, path: str) -> str | None:
    """Why a GeoTIFF is truncated (its header places image data beyond the end of the file), or None. Checked
    before anything else: a cut file also loses the tags after its cut (its CRS), and "no CRS" would mislead."""
    if src.driver != "GTiff" or not os.path.isfile(path):
        return None
    size = os.path.getsize(path)
    bh, bw = src.block_shapes[0]
    ny, nx = -(-src.height // bh), -(-src.width // bw)
    if nx * ny <= 4096:
        blocks = [(x, y) for y in range(ny) for x in range(nx)]
    else:  # a large tiled file: its first and last rows of blocks
        blocks = [(x, y) for y in (0, ny - 1) for x in range(min(nx, 2048))]
    end = 0
    for x, y in blocks:
        offset = src.get_tag_item(f"BLOCK_OFFSET_{x}_{y}", "TIFF", bidx=1)
        length = src.get_tag_item(f"BLOCK_SIZE_{x}_{y}", "TIFF", bidx=1)
        if offset and length:
            end = max(end, int(offset) + int(length))
    if end > size:
        return (f"{path}: the file is truncated: it has {size} bytes but its header places image data up to byte "
                f"{end}; copy or download it again")
    return None


def _native_grid(data, crs, transform, path) -> RasterGrid:
    rows, cols = data.shape
    de, dn = float(transform.a), float(-transform.e)
    # Post (pixel-centre) coordinates of the first column and of the last (southernmost) row.
    x_first = transform.c + 0.5 * de
    y_south = transform.f - (rows - 0.5) * dn
    origin = (x_first + 0.5 * (cols - 1) * de, y_south + 0.5 * (rows - 1) * dn)
    return RasterGrid(
        heights_m=np.ascontiguousarray(data[::-1]),
        n0=y_south - origin[1],
        e0=x_first - origin[0],
        dn=dn,
        de=de,
        crs_wkt=crs.to_wkt(),
        origin_xy=origin,
        description=f"{_crs_name(crs)}, native posts",
    )


def _reprojected_grid(data, crs, transform, bounds, spacing, path, frame=None, posts=None) -> RasterGrid:
    from rasterio.enums import Resampling
    from rasterio.transform import from_origin
    from rasterio.warp import reproject, transform_bounds
    from rasterio.warp import transform as warp_transform

    rows, cols = data.shape
    # Centre of the raster, in geographic coordinates, is the projection centre and the NED origin.
    cx, cy = raster_centre(transform, cols, rows)
    lon_c, lat_c = (v[0] for v in warp_transform(crs, "EPSG:4326", [cx], [cy]))
    if frame is None:
        dst_crs, origin = tmerc_crs(lat_c, lon_c), (0.0, 0.0)
    else:
        from rasterio.crs import CRS

        dst_crs, origin = CRS.from_wkt(frame[0]), (float(frame[1][0]), float(frame[1][1]))
    if spacing is None:
        # Native spacing: the length in metres of one source pixel step along each axis at the centre.
        px = [cx, cx + transform.a, cx + transform.b]
        py = [cy, cy + transform.d, cy + transform.e]
        xs, ys = warp_transform(crs, dst_crs, px, py)
        de = math.hypot(xs[1] - xs[0], ys[1] - ys[0])
        dn = math.hypot(xs[2] - xs[0], ys[2] - ys[0])
        how = "native spacing"
        if posts is not None:
            if not (math.isclose(dn, posts[2], rel_tol=SAME_POSTS_REL)
                    and math.isclose(de, posts[3], rel_tol=SAME_POSTS_REL)):
                return _reprojected_grid(data, crs, transform, bounds, spacing, path)  # another product's posts
            dn, de = float(posts[2]), float(posts[3])
            how = f"onto the posts of another grid ({dn:.6g} m × {de:.6g} m)"
    else:
        dn = de = spacing
        how = f"resampled to {spacing:g} m"
    left, bottom, right, top = transform_bounds(crs, dst_crs, *bounds, densify_pts=51)
    if posts is not None:  # the other grid, whole (the warp's sampling depends on the output's extent)
        x_first, y_south = origin[0] + posts[1], origin[1] + posts[0]
        out_rows, out_cols = int(posts[4]), int(posts[5])
        left, top = x_first - 0.5 * de, y_south + (out_rows - 0.5) * dn
    else:  # as many posts as the footprint holds, the grid centred on it
        out_cols = math.floor((right - left) / de)
        out_rows = math.floor((top - bottom) / dn)
        left += 0.5 * ((right - left) - out_cols * de)
        top -= 0.5 * ((top - bottom) - out_rows * dn)
        x_first, y_south = left + 0.5 * de, top - (out_rows - 0.5) * dn
    if out_rows < 2 or out_cols < 2:
        raise TerrainError(f"{path}: spacing {spacing} m leaves fewer than 2×2 posts")
    if out_rows * out_cols > MAX_POSTS:
        at = "its native resolution" if spacing is None else f"spacing {spacing} m"  # (it said "spacing None m")
        raise TerrainError(f"{path}: reprojected at {at} it would make {out_rows}×{out_cols} posts (limit "
                           f"{MAX_POSTS}); give a larger spacing or crop it first")
    dst_transform = from_origin(left, top, de, dn)

    heights = np.full((out_rows, out_cols), np.nan, dtype=np.float32)
    reproject(
        source=data.astype(np.float32),
        destination=heights,
        src_transform=transform,
        src_crs=crs,
        src_nodata=np.nan,
        dst_transform=dst_transform,
        dst_crs=dst_crs,
        dst_nodata=np.nan,
        resampling=Resampling.bilinear,
    )
    # A second pass on the nodata indicator: any contribution from a nodata post (or from outside the
    # footprint, value 2) invalidates the output post instead of being averaged away.
    holes = np.where(np.isfinite(data), 0.0, 1.0).astype(np.float32)
    holes_out = np.full((out_rows, out_cols), 2.0, dtype=np.float32)
    reproject(
        source=holes,
        destination=holes_out,
        src_transform=transform,
        src_crs=crs,
        src_nodata=2.0,
        dst_transform=dst_transform,
        dst_crs=dst_crs,
        dst_nodata=2.0,
        resampling=Resampling.bilinear,
    )
    out = heights.astype(np.float64)
    out[(holes_out != 0.0) | ~np.isfinite(out)] = np.nan
    if posts is not None and not np.isfinite(out).any():  # another place: read on its own
        return _reprojected_grid(data, crs, transform, bounds, spacing, path)
    if not np.isfinite(out).any():
        raise TerrainError(f"{path}: no valid post after reprojection")
    if posts is not None:  # the other grid's posts this raster covers: its rows and columns with data
        rows_ok, cols_ok = np.flatnonzero(np.isfinite(out).any(axis=1)), np.flatnonzero(np.isfinite(out).any(axis=0))
        out = out[rows_ok[0]:rows_ok[-1] + 1, cols_ok[0]:cols_ok[-1] + 1]
        x_first += cols_ok[0] * de
        y_south += (out_rows - 1 - rows_ok[-1]) * dn  # row 0 is the northernmost here
    target = (f"transverse Mercator at {lat_c:.4f}°N {lon_c:.4f}°E" if frame is None
              else f"another terrain's frame ({_crs_name(dst_crs)})")
    return RasterGrid(
        heights_m=np.ascontiguousarray(out[::-1]),
        n0=y_south - origin[1],
        e0=x_first - origin[0],
        dn=dn,
        de=de,
        crs_wkt=dst_crs.to_wkt(),
        origin_xy=origin,
        description=f"{_crs_name(crs)} reprojected to {target}, {how}",
    )


def _crs_name(crs) -> str:
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else (crs.to_dict().get("proj", "custom") + " CRS")


def projected_to_latlon(crs_wkt: str, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Projected (x east, y north) in ``crs_wkt`` -> (lat, lon) in degrees, WGS84."""
    from rasterio.crs import CRS
    from rasterio.warp import transform as warp_transform

    lon, lat = warp_transform(CRS.from_wkt(crs_wkt), "EPSG:4326", np.ravel(x), np.ravel(y))
    return np.asarray(lat).reshape(np.shape(x)), np.asarray(lon).reshape(np.shape(x))


def latlon_to_projected(crs_wkt: str, lat: np.ndarray, lon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lat, lon) in degrees, WGS84 -> projected (x east, y north) in ``crs_wkt``."""
    from rasterio.crs import CRS
    from rasterio.warp import transform as warp_transform

    x, y = warp_transform("EPSG:4326", CRS.from_wkt(crs_wkt), np.ravel(lon), np.ravel(lat))
    return np.asarray(x).reshape(np.shape(lat)), np.asarray(y).reshape(np.shape(lat))
