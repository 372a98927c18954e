"""A flight as a plan (a scenario's ``[flight]`` table): pattern, speed, heading, bank, where it goes over the DEM
and how high, and the truth :class:`~warptan.nav.trajectory.Trajectory` it gives over a terrain
(:meth:`FlightPlan.fly`).

* Patterns: ``straight`` (bank 0); ``s_turns`` (10 s straight, then turns of ±150° alternating at the bank angle
  until the end); ``orbit`` (5 s straight, then circling at the bank angle).
* Placement: ``centre`` (the track's box centred on the DEM) or ``hilltop`` (the circle passes ``hill_offset_m``
  beside the highest hill that is at least ``margin_m`` inside the DEM, the hill outside the circle, so that the
  banked sensor looks away from it, into open ground).
* Altitude: ``high`` = 600 m above the highest terrain within 2 km of the track; ``low`` = 150 m within 1 km
  (design notes §7); constant along the track.
* The track must stay ``margin_m`` inside the DEM (the footprint of the scan and the initial error) and off nodata.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from warptan.nav.trajectory import Orbit, Straight, Trajectory, Turn
from warptan.terrain.grid import Terrain

PATTERNS = ("straight", "s_turns", "orbit")
ALTITUDE_RULES = ("high", "low")
PLACEMENTS = ("centre", "hilltop")
ABOVE_TERRAIN_M = {"high": 600.0, "low": 150.0}
"""Clearance of the altitude rules over the highest terrain near the track, m."""
NEAR_TRACK_M = {"high": 2000.0, "low": 1000.0}
"""How far from the track (horizontally, m) the altitude rules look for the highest terrain."""


class FlightPlanError(ValueError):
    """A plan that does not fly over the terrain given (the track leaves it, passes over nodata, is not finite)."""


@dataclass(frozen=True)
class FlightPlan:
    """A scenario's ``[flight]`` table (validated by :mod:`warptan.sim.scenario_config`)."""

    speed_mps: float
    """Speed over ground, m/s."""
    duration_s: float
    """Length of the flight, s."""
    heading_deg: float
    """Initial heading, degrees from north."""
    pattern: str
    """One of :data:`PATTERNS`."""
    bank_deg: float
    """Bank of the turns and orbits, degrees (0 for ``straight``)."""
    altitude_rule: str
    """One of :data:`ALTITUDE_RULES` (a replay of a recorded flight says ``recorded``)."""
    placement: str
    """One of :data:`PLACEMENTS`."""
    hill_offset_m: float
    """``hilltop``: distance of the circle from the hill, m."""
    margin_m: float
    """The track stays this far inside the DEM, m."""

    def segments(self) -> list:
        """The trajectory segments of the pattern."""
        duration, bank = self.duration_s, self.bank_deg
        if self.pattern == "straight":
            return [Straight(duration)]
        if self.pattern == "orbit":
            lead = min(5.0, 0.1 * duration)
            return [Straight(lead), Orbit(duration - lead, bank_deg=bank, roll_time_s=3.0)]
        segments, t, sign = [Straight(min(10.0, 0.2 * duration))], min(10.0, 0.2 * duration), 1.0
        rate = 9.80665 * math.tan(math.radians(bank)) / self.speed_mps
        turn_time = math.radians(150.0) / rate + 3.0
        while t + turn_time <= duration:
            segments.append(Turn(sign * 150.0, bank_deg=bank, roll_time_s=3.0))
            t += turn_time
            sign = -sign
        if duration - t > 1e-6:
            segments.append(Straight(duration - t))
        return segments

    def fly(self, terrain: Terrain, rate_hz: float) -> Trajectory:
        """The truth trajectory over ``terrain`` sampled at ``rate_hz`` (placement and altitude rule applied).

        Raises:
            FlightPlanError: the track does not fit ``margin_m`` inside the DEM, passes over nodata, or is not
                finite.
        """
        shape = Trajectory.build(self.segments(), self.speed_mps, [0.0, 0.0, 0.0], self.heading_deg,
                                 rate_hz=rate_hz)
        n_min, n_max, e_min, e_max = terrain.bounds_ne
        path = shape.pos_n[:, :2]
        if self.placement == "hilltop":
            inner = terrain.heights_m.copy()
            ci = math.ceil(self.margin_m / terrain.dn) + 1
            cj = math.ceil(self.margin_m / terrain.de) + 1
            inner[:ci], inner[-ci:], inner[:, :cj], inner[:, -cj:] = np.nan, np.nan, np.nan, np.nan
            i, j = np.unravel_index(np.nanargmax(inner), inner.shape)
            hill = np.array([terrain.n0 + i * terrain.dn, terrain.e0 + j * terrain.de])
            centre = path[len(path) // 10:].mean(axis=0)  # centre of the circling part
            radius = np.median(np.linalg.norm(path[len(path) // 10:] - centre, axis=1))
            towards_middle = np.array([0.5 * (n_min + n_max), 0.5 * (e_min + e_max)]) - hill
            towards_middle /= max(np.linalg.norm(towards_middle), 1e-9)
            offset = hill + (radius + self.hill_offset_m) * towards_middle - centre
        else:
            mid = 0.5 * (path.min(axis=0) + path.max(axis=0))
            offset = np.array([0.5 * (n_min + n_max), 0.5 * (e_min + e_max)]) - mid
        track = path + offset
        if not np.isfinite(track).all():
            raise FlightPlanError(f"the track is not finite (flight.speed_mps = {self.speed_mps:g}, duration_s = "
                                  f"{self.duration_s:g})")
        problem = track_problem(terrain, track, self.margin_m, "DEM")
        if problem:
            raise FlightPlanError(f"{problem}; shorten flight.duration_s or use a larger DEM")
        sub = track[:: max(1, int(rate_hz))]
        altitude = (max_height_near(terrain, sub[:, 0], sub[:, 1], NEAR_TRACK_M[self.altitude_rule])
                    + ABOVE_TERRAIN_M[self.altitude_rule])
        return Trajectory.build(self.segments(), self.speed_mps, [track[0, 0], track[0, 1], -altitude],
                                self.heading_deg, rate_hz=rate_hz)

    def footprint_m(self, half_angle_deg: float) -> float:
        """The along-track length of a scan of ``half_angle_deg`` at the altitude rule's clearance, m (the slant
        range of a banked turn or orbit lengthening it by ``1 / cos(bank)``)."""
        bank = self.bank_deg if self.pattern != "straight" else 0.0
        return 2.0 * ABOVE_TERRAIN_M[self.altitude_rule] * math.tan(math.radians(half_angle_deg)) / math.cos(
            math.radians(bank))


def max_height_near(terrain: Terrain, north, east, radius: float) -> float:
    """The highest post within ``radius`` metres (horizontal distance) of any of the points (north, east)."""
    rows, cols = terrain.shape
    best = -np.inf
    ri, rj = math.ceil(radius / terrain.dn) + 1, math.ceil(radius / terrain.de) + 1
    for n, e in zip(north, east, strict=True):
        i, j = round((n - terrain.n0) / terrain.dn), round((e - terrain.e0) / terrain.de)
        i0, i1, j0, j1 = max(0, i - ri), min(rows, i + ri + 1), max(0, j - rj), min(cols, j + rj + 1)
        if i0 >= i1 or j0 >= j1:
            continue
        dn = terrain.n0 + np.arange(i0, i1) * terrain.dn - n
        de = terrain.e0 + np.arange(j0, j1) * terrain.de - e
        inside = dn[:, None] ** 2 + de[None, :] ** 2 <= radius * radius
        window = np.where(inside, terrain.heights_m[i0:i1, j0:j1], np.nan)
        if np.isfinite(window).any():
            best = max(best, float(np.nanmax(window)))
    return best


def track_problem(terrain: Terrain, track: np.ndarray, margin: float, what: str) -> str | None:
    """Why ``terrain`` does not cover the horizontal ``track`` (K, 2: north, east, m) with ``margin`` metres around
    it (leaves its bounds, or passes over nodata), or None when it does. ``what`` names the terrain in the text."""
    n_min, n_max, e_min, e_max = terrain.bounds_ne
    if (track[:, 0].min() - margin < n_min or track[:, 0].max() + margin > n_max or
            track[:, 1].min() - margin < e_min or track[:, 1].max() + margin > e_max):
        return (f"the track (north {track[:, 0].min():.0f}…{track[:, 0].max():.0f} m, east {track[:, 1].min():.0f}…"
                f"{track[:, 1].max():.0f} m) with a {margin:.0f} m margin leaves the {what} (north {n_min:.0f}…"
                f"{n_max:.0f}, east {e_min:.0f}…{e_max:.0f})")
    heights = terrain.height_at(track[:, 0], track[:, 1])
    if np.isnan(heights).any():
        return (f"the track passes over nodata in the {what} ({int(np.isnan(heights).sum())} of {len(heights)} "
                "track points)")
    return None
