"""What a DEM's CRS says about its units: whether its posts are a metric grid as they are (a projected CRS in metres
whose scale is 1 where the DEM lies), and the unit of its heights (a compound CRS's vertical part, or the band's tag).
:mod:`warptan.terrain.raster` reads DEMs with them."""

from __future__ import annotations

import math
import re

import numpy as np

SCALE_TOLERANCE = 0.002
"""How far from 1 a projected raster's scale (its units per metre on the ground, east and north at its centre) may
be for its posts to be used as a metric grid (UTM within its zone: at most 0.1 %): Web Mercator (EPSG:3857) at 50°N
is 1.56, and its grid taken as metres made a replay 1 km wrong. Beyond it the raster is reprojected to a transverse
Mercator at its centre, as a geographic one is."""


def raster_centre(transform, cols: int, rows: int) -> tuple[float, float]:
    """The raster's centre in its CRS (``transform`` an affine geotransform)."""
    return (transform.c + transform.a * cols / 2.0 + transform.b * rows / 2.0,
            transform.f + transform.d * cols / 2.0 + transform.e * rows / 2.0)


def metre_grid(crs, transform, cols: int, rows: int) -> bool:
    """True when the raster's posts are a metric grid as they are: a projected CRS in metres whose scale at the
    raster's centre is within :data:`SCALE_TOLERANCE` of 1."""
    if crs is None or not crs.is_projected or not math.isclose(crs.linear_units_factor[1], 1.0):
        return False
    from rasterio.warp import transform as warp_transform

    cx, cy = raster_centre(transform, cols, rows)
    step = 100.0
    lon, lat = warp_transform(crs, "EPSG:4326", [cx, cx + step, cx], [cy, cy, cy + step])
    if not np.all(np.isfinite(lon + lat)):
        return False
    # metres on the ground per degree at the centre's latitude (WGS84 meridian and prime-vertical radii)
    a, e2 = 6378137.0, 6.69437999014e-3
    phi = math.radians(lat[0])
    w = math.sqrt(1.0 - e2 * math.sin(phi) ** 2)
    m_lat, m_lon = math.radians(a * (1.0 - e2) / w**3), math.radians(a / w * math.cos(phi))
    scales = [step / math.hypot((lat[k] - lat[0]) * m_lat, (lon[k] - lon[0]) * m_lon) for k in (1, 2)]
    return all(abs(k - 1.0) <= SCALE_TOLERANCE for k in scales)


_HEIGHT_UNITS = {**dict.fromkeys(("m", "metre", "meter", "metres", "meters"), 1.0),
                 **dict.fromkeys(("ft", "foot", "feet", "international foot"), 0.3048),
                 **dict.fromkeys(("us survey foot", "us-ft", "ftus", "us foot", "foot us"), 1200.0 / 3937.0)}
"""Metres per height unit, by the names GDAL and PROJ write (lower case, underscores as spaces)."""


def height_unit_factor(src, band: int) -> tuple[float, str | None]:
    """(metres per unit of the raster's heights, None) — the unit its vertical CRS states (a compound CRS), else its
    band's unit tag; 1 (metres) when neither says and its horizontal unit is the metre or the degree — or (nan, what
    is wrong): a unit other than metres or feet, or a raster in feet that does not say its heights' unit (they may be
    feet or metres: US DEMs have both)."""
    stated, whence = None, None
    vertical = _vertical_unit(src.crs)
    if vertical is not None:
        stated, whence = vertical, "its vertical CRS"
    else:
        tag = (src.units[band - 1] if src.units else None) or ""
        if tag.strip():
            stated, whence = tag.strip(), f"band {band}'s unit tag"
    if stated is not None:
        factor = _HEIGHT_UNITS.get(stated.lower().replace("_", " ").strip())
        if factor is not None:
            return factor, None
        return math.nan, (f"heights in {stated!r} ({whence}); warptan reads heights in metres or feet: convert them "
                          "first (gdal_calc.py)")
    if src.crs is not None and not src.crs.is_geographic and not math.isclose(src.crs.linear_units_factor[1], 1.0):
        return math.nan, (f"its CRS is in {src.crs.linear_units_factor[0]} and its heights' unit is not stated "
                          "(heights in feet or in metres?); tag the band's unit first (gdal_edit.py -units ft|m, rio "
                          "edit-info --units) or give a compound CRS with its vertical unit")
    return 1.0, None


def _vertical_unit(crs) -> str | None:
    """The unit name of a compound CRS's vertical part, from its WKT; None without one."""
    if crs is None:
        return None
    wkt = crs.to_wkt()
    start = max(wkt.find("VERT_CS["), wkt.find("VERTCRS["), wkt.find("VERTICALCRS["))
    if start < 0:
        return None
    match = re.search(r'(?:LENGTHUNIT|UNIT)\["([^"]+)"', wkt[start:])
    return match.group(1) if match else None
