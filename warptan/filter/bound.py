"""The best a filter can do on a flight: the posterior Cramér–Rao bound (PCRB) of the INS error along a simulated
flight (:func:`pcrb`), to set beside the filter's RMSE.

Linearised at the truth: the 15-state error of :mod:`warptan.nav.ins` moves with the exact error transition ``F`` of
each IMU step at the true state and ideal samples and the IMU grade's noise ``Q`` (the noise the simulated IMU has;
the filter's own tuning noise on the position is not part of the truth and is left out: a bound with it would not be
a bound); each update adds the information of the scan at the true pose, ``J_z = Hᵀ R⁻¹ H``: per point the map's
gradient under the ray, ``v = (∂h/∂n, ∂h/∂e, 1)`` on the position and ``−r vᵀ R(q) [u_b]×`` on the attitude error
(the ray of range r turned by it), with the sensor's noise σ taken as the height residual's (a range noise projects
to ``σ |u_d + ∇h · u_h|``, within a few percent of σ for the scenarios' scans of ±30° over moderate slopes: the
bound can be that much high) and the map's stated correlated error as modes over the footprint, each counted ``κ``
times along the track as the filter counts it (:func:`warptan.terrain.information.error_modes`). An altimeter with a
barometer reads the horizontal gradient and the barometer the altitude. The recursion is the Riccati of that linear
system, ``P ← F P Fᵀ + Q`` per IMU step and ``P ← (P⁻¹ + J_z)⁻¹`` per update, from the filter's prior; its
horizontal DRMS ``sqrt(P_nn + P_ee)`` is the bound.
"""

from __future__ import annotations

import numpy as np

from warptan.nav.frames import quat_to_mat
from warptan.nav.ins import error_transition, process_noise
from warptan.terrain.information import MIN_DOWN, error_modes, leg_shifts

TRACK_SCANS = 64
"""Scans along the track over which a map-error mode's sharing ``κ`` is counted."""


def _skew(u: np.ndarray) -> np.ndarray:
    """(M, 3, 3) cross-product matrices."""
    z = np.zeros(len(u))
    return np.stack([np.stack([z, -u[:, 2], u[:, 1]], -1), np.stack([u[:, 2], z, -u[:, 0]], -1),
                     np.stack([-u[:, 1], u[:, 0], z], -1)], axis=1)


def scan_rows(terrain, pos_n: np.ndarray, quat_nb: np.ndarray, dirs_body: np.ndarray | None, surface: bool = False,
              agl: float | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The rows of a scan at the true pose (see the module docstring): ``(off, g)``, each valid point's horizontal
    offset from the aircraft where its ray meets level ground at the aircraft's height above the map under it (M, 2)
    and the height residual's sensitivity to the 15 error states (M, 15); None where no ray reads a valid map.
    ``dirs_body`` None: the altimeter, one row under the aircraft, ``(∂h/∂n, ∂h/∂e, 1)`` on the position."""
    if agl is None:
        agl = -pos_n[2] - float(terrain.height_at(pos_n[0], pos_n[1]))
        if not (agl > 0.0):
            return None
    if dirs_body is None:
        gn, ge = terrain.gradient_at(np.array([pos_n[0]]), np.array([pos_n[1]]), surface)
        if not np.isfinite(gn[0] + ge[0]):
            return None
        g = np.zeros((1, 15))
        g[0, :3] = (gn[0], ge[0], 1.0)
        return np.zeros((1, 2)), g
    rot = quat_to_mat(quat_nb)
    u_b = dirs_body / np.linalg.norm(dirs_body, axis=1, keepdims=True)
    u_n = u_b @ rot.T
    keep = u_n[:, 2] > MIN_DOWN
    u_b, u_n = u_b[keep], u_n[keep]
    r = agl / u_n[:, 2]
    off = r[:, None] * u_n[:, :2]
    gn, ge = terrain.gradient_at(pos_n[0] + off[:, 0], pos_n[1] + off[:, 1], surface)
    ok = np.isfinite(gn + ge)
    if not ok.any():
        return None
    v = np.stack([gn, ge, np.ones_like(gn)], axis=1)[ok]
    g = np.zeros((int(ok.sum()), 15))
    g[:, 0:3] = v
    g[:, 6:9] = -r[ok, None] * np.einsum("pi,ij,pjk->pk", v, rot, _skew(u_b[ok]))
    return off[ok], g


def scan_information(terrain, pos_n: np.ndarray, quat_nb: np.ndarray, dirs_body: np.ndarray | None, sigma_m: float,
                     baro_sigma_m: float | None = None, map_error_rms_m: float = 0.0, map_error_corr_m: float = 0.0,
                     track_step_m: float = 10.0, surface: bool = False, kappa_cache: dict | None = None) -> np.ndarray:
    """J_z (15 × 15) of one scan at the true pose (see the module docstring); ``dirs_body`` None: the altimeter (one
    nadir reading; with ``baro_sigma_m`` a barometer fixes the altitude). Zero where the scan reads no valid map."""
    j = np.zeros((15, 15))
    agl = -pos_n[2] - float(terrain.height_at(pos_n[0], pos_n[1]))
    if not (agl > 0.0):
        return j
    rows = scan_rows(terrain, pos_n, quat_nb, dirs_body, surface, agl)
    if rows is None:
        return j
    off, g = rows
    if dirs_body is None:  # the altimeter: the terrain under the aircraft
        g = g[0, :3].copy()
        if baro_sigma_m is not None:
            g[2] = 0.0
            j[:3, :3] = np.outer(g, g) / max(sigma_m ** 2 + baro_sigma_m ** 2, 1e-6)
            j[2, 2] += 1.0 / max(baro_sigma_m, 1e-3) ** 2
        else:
            j[:3, :3] = np.outer(g, g) / max(sigma_m, 1e-3) ** 2
        return j
    rot = quat_to_mat(quat_nb)
    white = max(sigma_m, 1e-3) ** 2  # (a noiseless sensor would fix the position exactly: a bound of zero)
    if map_error_rms_m > 0.0:
        shifts = leg_shifts(rot[:2, 0], TRACK_SCANS, track_step_m)  # along the body's x axis
        first = kappa_cache is None or "kappa" not in kappa_cache
        modes, lam, kappa, white = error_modes(off, map_error_rms_m, map_error_corr_m, white,
                                               shifts if first else None)
        if kappa_cache is not None:  # κ of the first scan's footprint, mode by mode, for the whole flight (a lag
            kappa_cache.setdefault("kappa", kappa)  # costs a correlation matrix); a mode beyond them counts once
            cached = kappa_cache["kappa"]
            kappa = np.ones(len(lam))
            kappa[:min(len(lam), len(cached))] = cached[:len(lam)]
        lam = kappa * lam
        q = modes.astype(np.float64).T @ g  # (K, 15)
        j = (g.T @ g - (q.T * (lam / (white + lam))) @ q) / white
    else:
        j = g.T @ g / white
    return j


def interval_transition(truth, k0: int, k1: int, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Φ, Q_d)`` of the INS error from IMU sample ``k0`` to ``k1``: the product of the steps' exact transitions at
    the truth and the noise they accumulate (``Q_d ← F Q_d Fᵀ + q`` per step)."""
    dt = 1.0 / truth.rate_hz
    phi, qd = np.eye(15), np.zeros((15, 15))
    for i in range(k0, k1):
        f = error_transition(truth.state(i), truth.f_b[i], truth.w_b[i], dt)
        phi = f @ phi
        qd = f @ qd @ f.T + q
    return phi, qd


def pcrb(truth, terrain, epochs, grade, p0: np.ndarray, *, dirs_body=None, sigma_m: float, baro_sigma_m=None,
         map_error_rms_m: float = 0.0, map_error_corr_m: float = 0.0, surface: bool = False) -> np.ndarray:
    """(T, 15) σ of the bound at the prior (t = 0) and after each update ``epochs`` (IMU sample indices).

    Args:
        truth: The flight (:class:`~warptan.nav.trajectory.Trajectory`).
        terrain: The filter's map.
        epochs: IMU sample index of each update.
        grade: The IMU's grade (its noise is the process noise).
        p0: (15, 15) prior covariance of [dp, dv, dθ, b_a, b_g].
        dirs_body, sigma_m, baro_sigma_m, map_error_rms_m, map_error_corr_m, surface: The sensor and map
            (:func:`scan_information`).
    """
    dt = 1.0 / truth.rate_hz
    q = process_noise(grade, dt)
    p = np.array(p0, dtype=np.float64)
    out = [np.sqrt(np.diag(p))]
    step = float(np.linalg.norm(truth.vel_n[0])) * (epochs[1] - epochs[0]) * dt if len(epochs) > 1 else 10.0
    cache: dict = {}
    k = 0
    for epoch in epochs:
        phi, qd = interval_transition(truth, k, epoch, q)
        p = phi @ p @ phi.T + qd
        k = epoch
        jz = scan_information(terrain, truth.pos_n[epoch], truth.quat_nb[epoch], dirs_body, sigma_m, baro_sigma_m,
                              map_error_rms_m, map_error_corr_m, step, surface, cache)
        info = np.linalg.inv(p) + jz
        p = np.linalg.inv(0.5 * (info + info.T))
        p = 0.5 * (p + p.T)
        out.append(np.sqrt(np.clip(np.diag(p), 0.0, None)))
    return np.array(out)


def horizontal_drms(sigmas: np.ndarray) -> np.ndarray:
    """(T,) ``sqrt(σ_n² + σ_e²)`` of (T, 15) σ, m."""
    return np.hypot(sigmas[:, 0], sigmas[:, 1])
