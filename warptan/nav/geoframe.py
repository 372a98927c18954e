"""A flight's frame tied to the Earth, and the change from it into a DEM's frame.

A flight log (format version 2, :mod:`warptan.io.flightlog`) states where its NED frame is on the Earth with a
:class:`GeoFrame`: the WGS84 latitude and longitude of the origin, the height of the origin above a named vertical
datum, and the datum. Its horizontal axes are those of a transverse Mercator projection (WGS84, scale 1, no false
origin) centred on the origin: north is the projection's y (true north at the origin), east its x, in metres;
down is ``origin_height_m − h`` with ``h`` the height above the datum. The same three numbers reproduce the frame in
any GIS (``+proj=tmerc +lat_0=… +lon_0=… +k=1 +x_0=0 +y_0=0 +datum=WGS84``).

A DEM's frame (:class:`~warptan.terrain.grid.Terrain`) is its own projected CRS (a native UTM grid, or the transverse
Mercator warptan builds for a geographic raster) with its own origin. :func:`frame_change` maps positions from a
log's frame into a DEM's point by point through latitude/longitude (PROJ, exact to the projections' float
precision), and turns velocities and attitudes by the angle between the two frames' north axes at each point (the
difference of their meridian convergences, e.g. up to 1–2° between a UTM grid and a tangent frame 100 km apart).
Neglected: the frames' scale difference (a UTM grid is 0.9996–1.0004 of true length; the factor is reported as
``scale_ppm``) applied to velocities and to the IMU's integrated distances — at most 0.4 m per km flown in UTM, 0 in
the tangent frames warptan builds itself (scale 1 at their origin, 1.2 ppm at 10 km) — and the vertical difference
between tangent planes (flat-earth frames, as the filter's INS: design notes §1). Heights are not converted between
vertical datums (no geoid grid ships with warptan): a log's heights must be above the DEM's datum, which the log names.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from warptan.nav.frames import quat_exp, quat_mul

IDENTITY_TOL_M = 1e-6
"""A change whose positions move by less than this (m) over the flight is the identity (the DEM's frame is the log's:
the same flight gives the same bits)."""


@dataclass(frozen=True)
class GeoFrame:
    """Where a NED frame is on the Earth (module docstring for the convention)."""

    origin_lat_deg: float
    origin_lon_deg: float
    origin_height_m: float = 0.0
    vertical_datum: str = ""
    """Name of the datum heights are above ("EGM96", "EGM2008", "WGS84 ellipsoid", …; "" = not stated)."""

    def problems(self) -> list[str]:
        """What makes the frame unusable (empty: usable)."""
        p = []
        lat, lon, h = self.origin_lat_deg, self.origin_lon_deg, self.origin_height_m
        if not (_number(lat) and abs(lat) < 90.0):
            p.append(f"frame.origin_lat_deg must be a finite latitude strictly between -90 and 90°, got {lat!r}")
        if not (_number(lon) and -360.0 <= lon <= 360.0):
            p.append(f"frame.origin_lon_deg must be a finite longitude in [-360, 360]°, got {lon!r}")
        if not (_number(h) and abs(h) < 1e5):
            p.append(f"frame.origin_height_m must be a finite height (|h| < 100 km), got {h!r}")
        if not isinstance(self.vertical_datum, str):
            p.append(f"frame.vertical_datum must be text, got {self.vertical_datum!r}")
        return p

    @property
    def crs_wkt(self) -> str:
        """The frame's horizontal CRS (transverse Mercator centred on the origin) as WKT."""
        from warptan.terrain.raster import tmerc_crs

        return tmerc_crs(self.origin_lat_deg, self.origin_lon_deg).to_wkt()

    def ne_to_latlon(self, north, east) -> tuple[np.ndarray, np.ndarray]:
        from warptan.terrain.raster import projected_to_latlon

        return projected_to_latlon(self.crs_wkt, np.asarray(east, float), np.asarray(north, float))

    def latlon_to_ne(self, lat, lon) -> tuple[np.ndarray, np.ndarray]:
        from warptan.terrain.raster import latlon_to_projected

        x, y = latlon_to_projected(self.crs_wkt, np.asarray(lat, float), np.asarray(lon, float))
        return y, x

    @classmethod
    def of_terrain(cls, terrain, vertical_datum: str = "") -> GeoFrame | None:
        """The frame whose origin is ``terrain``'s NED origin (None for a terrain without a CRS)."""
        if not getattr(terrain, "crs_wkt", None):
            return None
        lat, lon = terrain.ne_to_latlon(np.array([0.0]), np.array([0.0]))
        return cls(float(lat[0]), float(lon[0]), 0.0, vertical_datum)


def _number(v) -> bool:
    return isinstance(v, (int, float, np.number)) and not isinstance(v, bool) and math.isfinite(v)


@dataclass
class FrameChange:
    """Positions, vectors and attitudes from one frame (``source``: anything with ``ne_to_latlon``) into another
    (``target``: with ``latlon_to_ne``); ``dz`` is added to down (the source origin's height above the target's)."""

    source: object
    target: object
    dz: float = 0.0
    identity: bool = False

    def _map(self, north, east):
        lat, lon = self.source.ne_to_latlon(north, east)
        return self.target.latlon_to_ne(lat, lon)

    def positions(self, pos: np.ndarray) -> np.ndarray:
        pos = np.asarray(pos, dtype=np.float64)
        if self.identity:
            return pos.copy()
        flat = pos.reshape(-1, 3)
        n, e = self._map(flat[:, 0], flat[:, 1])
        return np.column_stack([n, e, flat[:, 2] - self.dz]).reshape(pos.shape)

    def angles(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K,) angle (rad, about down) from the source's north to the target's at each position, and the scale
        factor of target metres per source metre there."""
        flat = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        if self.identity:
            return np.zeros(len(flat)), np.ones(len(flat))
        n0, e0 = self._map(flat[:, 0], flat[:, 1])
        n1, e1 = self._map(flat[:, 0] + 1.0, flat[:, 1])
        return np.arctan2(e1 - e0, n1 - n0), np.hypot(n1 - n0, e1 - e0)

    def vectors(self, pos: np.ndarray, vec: np.ndarray) -> np.ndarray:
        """NED vectors (velocities) at ``pos`` turned into the target frame."""
        vec = np.asarray(vec, dtype=np.float64)
        if self.identity:
            return vec.copy()
        return turn_vectors(self.angles(pos)[0], vec)

    def attitudes(self, pos: np.ndarray, quat_nb: np.ndarray) -> np.ndarray:
        """Body-to-NED quaternions at ``pos`` as body-to-target-NED: ``q_z(angle) ⊗ q_nb``."""
        quat_nb = np.asarray(quat_nb, dtype=np.float64)
        if self.identity:
            return quat_nb.copy()
        a, _ = self.angles(pos)
        q = quat_mul(quat_exp(np.outer(a, (0.0, 0.0, 1.0))), quat_nb.reshape(-1, 4))
        return (q / np.linalg.norm(q, axis=1, keepdims=True)).reshape(quat_nb.shape)

    def scale_ppm(self, pos: np.ndarray) -> float:
        """The largest ``|scale − 1|`` over ``pos``, parts per million (what the change neglects)."""
        _, k = self.angles(pos)
        return float(np.max(np.abs(k - 1.0)) * 1e6) if len(k) else 0.0


def turn_vectors(angle, vec) -> np.ndarray:
    """NED vectors (K, 3) turned by ``angle`` (rad, scalar or (K,)) about down: north (1, 0, 0) becomes
    (cos a, sin a, 0)."""
    vec = np.asarray(vec, dtype=np.float64)
    v = vec.reshape(-1, 3)
    c, s = np.cos(angle), np.sin(angle)
    return np.column_stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]]).reshape(vec.shape)


def frame_change(source, target, probe: np.ndarray, dz: float = 0.0) -> FrameChange:
    """The change from ``source`` to ``target`` (each a :class:`GeoFrame` or a georeferenced terrain); the identity
    when every ``probe`` position (K, 3, source frame; e.g. the flight's corners) moves by less than
    :data:`IDENTITY_TOL_M` and ``dz`` is 0."""
    change = FrameChange(source, target, float(dz))
    probe = np.asarray(probe, dtype=np.float64).reshape(-1, 3)
    moved = change.positions(probe) - probe
    change.identity = bool(dz == 0.0 and np.all(np.abs(moved[:, :2]) < IDENTITY_TOL_M))
    return change


def corners(pos: np.ndarray) -> np.ndarray:
    """(5, 3) the corners and centre of the horizontal box around ``pos`` (K, 3), at down 0."""
    p = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
    lo, hi = p[:, :2].min(axis=0), p[:, :2].max(axis=0)
    box = [(lo[0], lo[1]), (lo[0], hi[1]), (hi[0], lo[1]), (hi[0], hi[1]), ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2)]
    return np.array([[n, e, 0.0] for n, e in box])


def latlon_extent(frame, pos: np.ndarray) -> str:
    """'lat a…b°, lon c…d°' of positions ``pos`` (K, 2 or 3) in ``frame`` (anything with ``ne_to_latlon``)."""
    p = np.asarray(pos, dtype=np.float64)
    lat, lon = frame.ne_to_latlon(p[:, 0], p[:, 1])
    return f"lat {np.min(lat):.5f}…{np.max(lat):.5f}°, lon {np.min(lon):.5f}…{np.max(lon):.5f}°"
