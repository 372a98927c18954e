"""Where terrain navigation works: the Fisher information of a scan about the horizontal position at every post of
a DEM, and the 1σ position bound it gives (:func:`information_map`; ``Terrain.information_map``; ``warptan terrain
info DEM --information``).

The aircraft flies level at ``altitude_agl_m`` above each cell, heading ``heading_deg``; its scan (unit ray
directions in the body frame, x forward, y right, z down) reads the map at the nominal footprint, the rays met by
flat ground at that height (the footprint the filter's map-error modes use too). Each point's residual has the
sensor's white noise ``sigma_m`` (taken as the height residual's: a range noise projects to ``σ |u_d + ∇h · u_h|``,
within a few percent of σ for scans of ±30° over moderate slopes), the map's post noise ``map_noise_m`` and its
stated correlated error (RMS ``map_error_rms_m``, covariance ``exp(−(r/L)²)``, ``L = map_error_corr_m``; its leading
modes over the footprint, the rest folded into the white part). A point cloud also reads the altitude (the position
error is 3-D and the bound is the horizontal block of its inverse, i.e. the vertical marginalised); an altimeter
with a barometer does not (``vertical_known``). The bound is the DRMS ``sqrt(tr(J_h⁻¹))`` in metres, of one scan and of
``n_scans`` scans ``scan_step_m`` apart along a straight leg centred on the cell (their information summed, the
altitude error common): infinite where the terrain does not fix the position (flat ground, a plane; an altimeter's
single reading fixes one direction at most). Along the leg each map-error mode is shared by the scans that see the
same ground: its variance counts ``κ_k = Σ_|l|<N (1 − |l|/N) ρ_k(l · step)`` times in each scan (ρ_k the mode's
correlation with the footprint ``l`` steps further), which is exact for a mode shared by every scan (κ = N) and for
independent ones (κ = 1), as the filter's own mode model (:meth:`warptan.sensing.likelihood.Likelihood.
error_modes`). The kernels: :mod:`warptan.kernels.information`.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warptan.device import resolve_device
from warptan.kernels import information as kinfo
from warptan.terrain.raster import TerrainError

MIN_DOWN = 1e-3
"""A ray whose body-frame down component is below this never meets level ground (at or above the horizon)."""
MAX_POINTS = 20_000
"""Most footprint points (rays of a scan, or scans of a leg) a map is computed with."""


@dataclass
class InformationMap:
    """Fisher information and 1σ horizontal position bounds over a DEM's posts (every ``stride``-th)."""

    north_m: np.ndarray
    """(rows,) north of the output rows, m (the DEM's NED frame)."""
    east_m: np.ndarray
    """(cols,) east of the output columns, m."""
    info_scan: np.ndarray = field(repr=False)
    """(rows, cols, 3, 3) information of one scan about (north, east, down), m⁻²; NaN where the footprint leaves
    the map or reads nodata."""
    info_leg: np.ndarray = field(repr=False)
    """(rows, cols, 3, 3) the same for the ``n_scans`` of the leg."""
    bound_scan_m: np.ndarray
    """(rows, cols) 1σ horizontal bound (DRMS) of one scan, m; inf: no fix; NaN: no footprint on the map."""
    bound_leg_m: np.ndarray
    """(rows, cols) the same for the leg."""
    settings: dict
    """What the map was computed for (sensor, altitude, heading, σ, map error, scans, modes kept)."""
    crs_wkt: str | None = None
    origin_xy: tuple[float, float] = (0.0, 0.0)

    def horizontal_info(self, leg: bool = False) -> np.ndarray:
        """(rows, cols, 2, 2) information about the horizontal position (the vertical marginalised unless it is
        known)."""
        return _horizontal(self.info_leg if leg else self.info_scan, self.settings["vertical_known"])

    def save_geotiff(self, path: str | os.PathLike) -> str:
        """The two bounds (band 1: one scan, band 2: the leg; metres, NaN no footprint, inf no fix) as a GeoTIFF in
        the DEM's CRS (for QGIS).

        Raises:
            TerrainError: the DEM has no CRS (a local grid cannot be placed on the Earth).
        """
        check_geotiff_target(path, self.crs_wkt)
        import rasterio
        from rasterio.transform import from_origin

        dn = float(self.north_m[1] - self.north_m[0]) if len(self.north_m) > 1 else 1.0
        de = float(self.east_m[1] - self.east_m[0]) if len(self.east_m) > 1 else 1.0
        x0 = self.east_m[0] + self.origin_xy[0] - 0.5 * de
        y0 = self.north_m[-1] + self.origin_xy[1] + 0.5 * dn
        bands = np.stack([self.bound_scan_m[::-1], self.bound_leg_m[::-1]]).astype(np.float32)
        with rasterio.open(os.fspath(path), "w", driver="GTiff", height=bands.shape[1], width=bands.shape[2], count=2,
                           dtype="float32", crs=rasterio.crs.CRS.from_wkt(self.crs_wkt),
                           transform=from_origin(x0, y0, de, dn)) as dst:
            dst.write(bands)
            dst.set_band_description(1, "1-sigma horizontal position bound of one scan (m)")
            dst.set_band_description(2, f"1-sigma horizontal position bound of {self.settings['n_scans']} scans (m)")
            dst.update_tags(**{k: str(v) for k, v in self.settings.items()})
        return os.fspath(path)

    def save_png(self, path: str | os.PathLike, title: str = "") -> str:
        """The two bounds side by side on a logarithmic colour scale in metres (2nd to 98th percentile, larger
        bounds at its top; grey: no fix; white: no footprint on the map)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import matplotlib.ticker
        from matplotlib.colors import LogNorm

        extent = [self.east_m[0] / 1e3, self.east_m[-1] / 1e3, self.north_m[0] / 1e3, self.north_m[-1] / 1e3]
        finite = np.concatenate([b[np.isfinite(b)] for b in (self.bound_scan_m, self.bound_leg_m)])
        lo, hi = (np.percentile(finite, [2, 98]) if finite.size else (0.1, 100.0))
        norm = LogNorm(vmin=max(lo, 1e-3), vmax=max(hi, 2 * max(lo, 1e-3)))
        fig, axes = plt.subplots(1, 2, figsize=(12, 5.2), constrained_layout=True)
        cmap = plt.get_cmap("viridis").copy()
        cmap.set_over("0.6")
        cmap.set_bad("white")
        for ax, bound, what in ((axes[0], self.bound_scan_m, "one scan"),
                                (axes[1], self.bound_leg_m, f"{self.settings['n_scans']} scans along the leg")):
            # no fix (inf) above the scale's top, where the colour map's "over" paints it grey (imshow masks an inf
            # as bad: white, which is for no footprint, NaN); a finite bound at most the top
            shown = np.where(np.isinf(bound), 10.0 * norm.vmax, np.minimum(bound, norm.vmax))
            im = ax.imshow(shown, origin="lower", extent=extent, cmap=cmap, norm=norm, interpolation="nearest")
            fixed = np.isfinite(bound)
            on_map = ~np.isnan(bound)
            median = f"median {np.median(bound[fixed]):.2g} m" if fixed.any() else "no fix"
            ax.set_title(f"{what}: {median}, {100 * fixed.sum() / max(on_map.sum(), 1):.0f} % of the map fixes")
            ax.set_xlabel("east (km)")
            ax.set_ylabel("north (km)")
        bar = fig.colorbar(im, ax=axes, extend="max", label="1σ horizontal position bound (m), grey: no fix")
        ticks = [t * 10.0**e for e in range(-3, 5) for t in (1, 2, 5) if norm.vmin <= t * 10.0**e <= norm.vmax]
        bar.set_ticks(ticks, labels=[f"{t:g}" for t in ticks])  # (1-2-5 in metres, not 4×10⁰)
        bar.ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        s = self.settings
        fig.suptitle(title or f"{s['sensor']} at {s['altitude_agl_m']:g} m AGL, heading {s['heading_deg']:g}°")
        fig.savefig(os.fspath(path), dpi=110)
        plt.close(fig)
        return os.fspath(path)


def check_geotiff_target(path, crs_wkt: str | None) -> None:
    """Refuse (TerrainError) a GeoTIFF of a DEM without CRS, before any work."""
    if path is not None and os.fspath(path).lower().endswith((".tif", ".tiff")) and not crs_wkt:
        raise TerrainError(f"{os.fspath(path)}: a GeoTIFF needs the DEM's CRS and this DEM has none (a local grid); "
                           "write a .png, or load a georeferenced DEM")


MAX_LEG_SCANS = 10_000
"""Scans along the information map's leg at most: 100 km at 10 m a scan, longer than any DEM a run loads (its work is
posts × scans; a billion scans filled 10 GB of memory before anything was computed)."""


def leg_shifts(direction, n_scans: int, step_m: float) -> np.ndarray:
    """(n, 2) offsets (north, east; m) of ``n_scans`` scans ``step_m`` apart along the horizontal ``direction``,
    centred on 0.

    Raises:
        TerrainError: a scan count that is not a whole number ≥ 1, a step that is not a positive number of metres.
    """
    if isinstance(n_scans, bool) or not isinstance(n_scans, (int, np.integer)) or n_scans < 1:
        raise TerrainError(f"n_scans = {n_scans!r} must be a whole number ≥ 1")
    if n_scans > MAX_LEG_SCANS:
        raise TerrainError(f"n_scans = {n_scans} scans along the leg: at most {MAX_LEG_SCANS} (a leg of "
                           f"{MAX_LEG_SCANS * float(step_m) / 1000.0:g} km at {float(step_m):g} m a scan; every post "
                           "sums every scan of its leg)")
    if not (math.isfinite(float(step_m)) and step_m > 0.0):
        raise TerrainError(f"scan_step_m = {step_m!r} must be a positive number of metres")
    d = np.asarray(direction, dtype=np.float64)[:2]
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    return (np.arange(n_scans) - 0.5 * (n_scans - 1))[:, None] * float(step_m) * d[None, :]


def scan_footprint(dirs_body, altitude_agl_m: float, heading_deg: float = 0.0, n_scans: int = 1,
                   scan_step_m: float = 10.0) -> np.ndarray:
    """(P, 2) horizontal offsets (north, east; m) from the aircraft of the points its scans read on level ground
    ``altitude_agl_m`` below: each ray met by the ground, for ``n_scans`` scans ``scan_step_m`` apart along the
    heading, centred on the aircraft.

    Raises:
        TerrainError: a bad altitude, heading, step or scan count; no ray meets the ground.
    """
    agl = float(altitude_agl_m)
    if not (math.isfinite(agl) and agl > 0.0):
        raise TerrainError(f"altitude_agl_m = {altitude_agl_m!r}: the aircraft must fly above the terrain "
                           "(a height above it in metres, > 0)")
    if not math.isfinite(float(heading_deg)):
        raise TerrainError(f"heading_deg = {heading_deg!r} must be a finite number of degrees")
    psi = math.radians(float(heading_deg))
    c, s = math.cos(psi), math.sin(psi)
    shifts = leg_shifts((c, s), n_scans, scan_step_m)
    d = np.asarray(dirs_body, dtype=np.float64).reshape(-1, 3)
    down = d[:, 2] > MIN_DOWN
    if not np.isfinite(d).all():
        raise TerrainError("the scan's ray directions must be finite")
    if not down.any():
        raise TerrainError(f"empty footprint: none of the scan's {len(d)} rays points below the horizon, so none "
                           "meets the ground")
    d = d[down] / np.linalg.norm(d[down], axis=1, keepdims=True)
    xy = agl * d[:, :2] / d[:, 2:3]  # body x forward, y right
    one = np.stack([c * xy[:, 0] - s * xy[:, 1], s * xy[:, 0] + c * xy[:, 1]], axis=1)
    out = (one[None, :, :] + shifts[:, None, :]).reshape(-1, 2)
    if len(out) > MAX_POINTS:
        raise TerrainError(f"{len(out)} footprint points ({len(one)} rays × {n_scans} scans): at most {MAX_POINTS}")
    return out


def _correlation(a: np.ndarray, b: np.ndarray, corr_m: float) -> np.ndarray:
    diff = a[:, None, :] - b[None, :, :]
    return np.exp(-np.einsum("ijk,ijk->ij", diff, diff) / (corr_m * corr_m))


def error_modes(offsets: np.ndarray, rms_m: float, corr_m: float, white_var: float, shifts: np.ndarray | None = None,
                max_modes: int = kinfo.MAX_INFO_MODES):
    """The map's correlated error over the footprint as modes: ``(U (P, K), λ (K), κ (K), white variance)`` with
    ``R = white I + Σ_k λ_k u_k u_kᵀ`` and κ_k the mode's count along a leg of scans ``shifts`` apart (the module
    docstring; 1 without ``shifts``). The variance of the modes beyond ``max_modes`` (or under 1e-9 of the largest)
    is added to the white part, spread evenly over the points."""
    p = len(offsets)
    if rms_m <= 0.0:
        return np.zeros((p, 1), np.float32), np.zeros(1), np.ones(1), white_var
    lam, vec = np.linalg.eigh(_correlation(offsets, offsets, corr_m))
    order = np.argsort(lam)[::-1]
    lam, vec = np.clip(lam[order], 0.0, None), vec[:, order]
    keep = min(max_modes, int((lam > 1e-9 * lam[0]).sum()))
    var = rms_m * rms_m
    white = white_var + var * float(lam[keep:].sum()) / p
    u, mu = vec[:, :keep], lam[:keep]
    kappa = np.ones(keep)
    if shifts is not None and len(shifts) > 1:
        n = len(shifts)
        kappa = np.zeros(keep)
        for lag in range(-(n - 1), n):  # ρ_k(l) = u_kᵀ C(l) u_k / μ_k, C(l) the footprint against itself l scans on
            step = shifts[max(lag, 0)] - shifts[max(-lag, 0)]
            rho = np.einsum("pk,pq,qk->k", u, _correlation(offsets, offsets + step, corr_m), u) / mu
            kappa += (1.0 - abs(lag) / n) * rho
        kappa = np.clip(kappa, 1.0, float(n))
    return u.astype(np.float32), var * mu, kappa, white


def information_map(terrain, dirs_body, altitude_agl_m: float, sigma_m: float, *, heading_deg: float = 0.0,
                    n_scans: int = 10, scan_step_m: float = 10.0, map_noise_m: float = 0.0,
                    map_error_rms_m: float = 0.0, map_error_corr_m: float = 0.0, vertical_known: bool = False,
                    surface: str = "bilinear", stride: int = 1, sensor: str = "scan", device=None) -> InformationMap:
    """The information map of ``terrain`` for a scan of rays ``dirs_body`` (see the module docstring).

    Args:
        terrain: The DEM (:class:`~warptan.terrain.grid.Terrain`).
        dirs_body: (M, 3) ray directions in the body frame (x forward, y right, z down; an altimeter: one ray).
        altitude_agl_m: Height of the aircraft above each cell, m.
        sigma_m: The sensor's noise per point (range σ; altimeter ⊕ barometer for an altimeter), m.
        heading_deg: Heading of the flight, degrees from north.
        n_scans: Scans along the leg of the second bound; ``scan_step_m`` apart (speed / measurement rate).
        map_noise_m: White noise of the map's posts, m.
        map_error_rms_m, map_error_corr_m: The DEM's stated correlated error (RMS and correlation length, m).
        vertical_known: A barometer fixes the altitude (the altimeter): the residuals do not read it.
        surface: ``bilinear`` or ``triangles``: the map surface the gradients are taken of.
        stride: Every ``stride``-th post in each direction.
        sensor: The sensor's name for the outputs.
        device: Warp device of the kernel.

    Raises:
        TerrainError: a bad altitude (not above the terrain), an empty footprint, a bad σ or map error, before work.
    """
    if not (math.isfinite(float(sigma_m)) and sigma_m > 0.0):
        raise TerrainError(f"sigma_m = {sigma_m!r} must be a positive number of metres (the sensor's noise)")
    for name, value in (("map_noise_m", map_noise_m), ("map_error_rms_m", map_error_rms_m),
                        ("map_error_corr_m", map_error_corr_m)):
        if not (math.isfinite(float(value)) and value >= 0.0):
            raise TerrainError(f"{name} = {value!r} must be a number of metres ≥ 0")
    if map_error_rms_m > 0.0 and map_error_corr_m <= 0.0:
        raise TerrainError(f"map_error_rms_m = {map_error_rms_m:g} needs map_error_corr_m > 0 (its correlation "
                           "length, m)")
    if surface not in ("bilinear", "triangles"):
        raise TerrainError(f"surface = {surface!r} must be 'bilinear' or 'triangles'")
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise TerrainError(f"stride = {stride!r} must be a whole number ≥ 1")
    if min((n + stride - 1) // stride for n in terrain.shape) < 2:
        raise TerrainError(f"stride = {stride} leaves fewer than 2×2 cells of the terrain's "
                           f"{terrain.shape[0]}×{terrain.shape[1]} posts (no map to compute: it said 'no fix'); "
                           f"use at most {max(1, (min(terrain.shape) - 1) // 2)}")
    scan = scan_footprint(dirs_body, altitude_agl_m, heading_deg, 1, scan_step_m)
    psi = math.radians(float(heading_deg))
    leg = leg_shifts((math.cos(psi), math.sin(psi)), n_scans, scan_step_m)  # the scans' centres
    span = np.ptp(scan, axis=0) + np.ptp(leg, axis=0)  # (the extent of the leg's scans' points)
    extent = ((terrain.shape[0] - 1) * terrain.dn, (terrain.shape[1] - 1) * terrain.de)
    if span[0] >= extent[0] or span[1] >= extent[1]:
        raise TerrainError(f"at {altitude_agl_m:g} m above the terrain the scans cover {span[0]:.4g} × {span[1]:.4g} m "
                           f"(north × east), more than the DEM's {extent[0]:.4g} × {extent[1]:.4g} m: no cell can be "
                           "evaluated (it said 'no fix'); fly lower or give a larger DEM")
    d = resolve_device(device)
    grid = terrain.grid(d)
    rows, cols = (terrain.shape[0] + stride - 1) // stride, (terrain.shape[1] + stride - 1) // stride
    white = float(sigma_m) ** 2 + float(map_noise_m) ** 2
    modes, lam, kappa, white = error_modes(scan, float(map_error_rms_m), float(map_error_corr_m), white, leg)
    offsets = wp.array(scan.astype(np.float32), dtype=wp.vec2, device=d)
    modes_d = wp.array(modes, dtype=wp.float32, device=d)
    fields = []
    for count in (np.ones_like(kappa), kappa):  # one scan; one scan of the leg (its modes counted κ times)
        weights = count * lam / (white + count * lam)
        out = wp.empty((rows, cols), dtype=wp.mat33d, device=d)
        wp.launch(kinfo.scan_information_kernel, dim=(rows, cols),
                  inputs=[grid, int(surface == "triangles"), int(stride), offsets, modes_d,
                          wp.array(weights.astype(np.float64), dtype=wp.float64, device=d), len(weights),
                          0.0 if vertical_known else 1.0, 1.0 / white],
                  outputs=[out], device=d)
        fields.append(out)
    leg_info = wp.empty((rows, cols), dtype=wp.mat33d, device=d)
    wp.launch(kinfo.leg_information_kernel, dim=(rows, cols),
              inputs=[fields[1], float(stride * terrain.dn), float(stride * terrain.de),
                      wp.array(leg.astype(np.float32), dtype=wp.vec2, device=d)],
              outputs=[leg_info], device=d)
    infos = [fields[0].numpy(), leg_info.numpy()]
    kept = [int((lam > 0).sum()), float(kappa.max()) if len(kappa) else 1.0]
    settings = {"sensor": sensor, "altitude_agl_m": float(altitude_agl_m), "heading_deg": float(heading_deg),
                "sigma_m": float(sigma_m), "map_noise_m": float(map_noise_m),
                "map_error_rms_m": float(map_error_rms_m), "map_error_corr_m": float(map_error_corr_m),
                "n_scans": int(n_scans), "scan_step_m": float(scan_step_m), "rays": len(scan),
                "vertical_known": bool(vertical_known), "surface": surface, "stride": int(stride),
                "error_modes": kept[0], "error_mode_kappa_max": kept[1], "terrain": terrain.name}
    return InformationMap(
        north_m=terrain.n0 + np.arange(rows) * stride * terrain.dn,
        east_m=terrain.e0 + np.arange(cols) * stride * terrain.de,
        info_scan=infos[0], info_leg=infos[1], bound_scan_m=drms_bound(_horizontal(infos[0], vertical_known)),
        bound_leg_m=drms_bound(_horizontal(infos[1], vertical_known)), settings=settings, crs_wkt=terrain.crs_wkt,
        origin_xy=tuple(terrain.origin_xy))


def _horizontal(info: np.ndarray, vertical_known: bool) -> np.ndarray:
    """(…, 2, 2) information about (north, east): the horizontal block, with the vertical marginalised (Schur
    complement) unless it is known."""
    h = info[..., :2, :2]
    if vertical_known:
        return h.copy()
    vv = info[..., 2, 2]
    hv = info[..., :2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        schur = np.where(vv[..., None, None] > 0, hv[..., :, None] * hv[..., None, :] / vv[..., None, None], 0.0)
    return h - schur


def drms_bound(info_h: np.ndarray) -> np.ndarray:
    """``sqrt(tr(J⁻¹))`` of (…, 2, 2) information, m: infinite where J is singular to 1e-9 of its trace (no fix in
    some direction), NaN where J is NaN."""
    a, b, d = info_h[..., 0, 0], info_h[..., 0, 1], info_h[..., 1, 1]
    tr, det = a + d, a * d - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.sqrt(tr / det)
        singular = ~(det > 1e-9 * tr * tr)
    return np.where(np.isnan(tr), np.nan, np.where(singular, np.inf, bound))
