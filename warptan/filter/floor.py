"""The exact information floor of a flight under a correlated map error: the posterior Cramér–Rao bound with the map's
error field in the state (:func:`exact_pcrb`), beside the fast per-scan bound of :mod:`warptan.filter.bound`.

The fast bound marginalises the field over each scan's footprint and counts each mode ``κ`` times along the track; the
field is one and the same for every scan that sees the same ground, so that rule is an approximation (too pessimistic
on rough ground, too optimistic on smooth ground with a short correlation length). Here the field is a state:

- the map's error ``e(p) = b + f(p)``: a bias ``b ~ N(0, σ_b²)`` and a Gaussian process ``f`` of RMS ``σ_f`` and
  covariance ``σ_f² exp(−|p − p'|² / L²)`` (the form the likelihood states, design notes §6b);
- ``f`` on a square grid of nodes of spacing ``0.4 L`` over the ground the scans read (:data:`NODE_SPACING`); a
  point's ``f`` is the nodes' kriging interpolation ``a(p)ᵀ f_nodes`` from the nodes within ``1.5 L``
  (:data:`READ_RADIUS`: the interpolation's error variance under ``1e-5 σ_f²``, added to the point's white noise);
- the 15 INS error states ``x`` move as the truth's error transition and the IMU grade's noise (as
  :func:`warptan.filter.bound.pcrb`); a point's height residual is ``z = g x + b + a(p)ᵀ f_nodes + v``, ``g`` the
  scan's rows (:func:`warptan.filter.bound.scan_rows`), ``v`` the sensor's white noise ``σ``;
- the bound is the covariance of the Kalman filter of that linear-Gaussian system at the truth (the PCRB of the
  linearised model is that covariance): ``[x, b, f_nodes]`` jointly, each scan's points jointly.

The node set is a window that moves with the flight: a node enters when a scan first reads within ``1.5 L`` of it,
its prior conditioned on every node held (the regression ``f_new = C_nh C_hh⁻¹ f_held + w``, ``w`` of the exact
conditional covariance: conditioning on the held nodes within 2.5 L only, the Gaussian kernel screens too little,
and the bound drifted 0.7 % from the oracle in 12 scans), and leaves when every point of a scan is ``3 L`` from it
(:data:`LEAVE_RADIUS`; dropping a state from a covariance is exact marginalisation: what a node that left says of
a new one, through the nodes held, is kept). Ground flown again after a node left is a new node: the floor is then
a little pessimistic (an orbit, a second pass). The dense oracle in the tests (all points of all scans jointly, no
grid) agrees to 2e-4 for a point cloud and 1.2e-3 for an altimeter, whose one point a scan feels the interpolation
most (``tests/test_floor.py``; at a 0.3 L spacing 2.5e-5, for 1.8× the nodes).
"""

from __future__ import annotations

import numpy as np

from warptan.filter.bound import interval_transition, scan_rows
from warptan.nav.ins import process_noise

NODE_SPACING = 0.4
"""Grid spacing of the field's nodes, in correlation lengths."""
READ_RADIUS = 1.5
"""Nodes within this many correlation lengths of a point interpolate its error."""
LEAVE_RADIUS = 3.0
"""A node leaves the window once every point of a scan is this many correlation lengths from it."""
JITTER = 1e-9
"""Relative diagonal loading of the nodes' prior covariance (a Gaussian kernel's matrix on a fine grid is near
singular)."""


def _kernel(a: np.ndarray, b: np.ndarray, corr_m: float) -> np.ndarray:
    d = a[:, None, :] - b[None, :, :]
    return np.exp(-np.einsum("ijk,ijk->ij", d, d) / (corr_m * corr_m))


class _FieldWindow:
    """The nodes held (grid indices, positions) and their columns in the state (after ``offset`` leading states)."""

    def __init__(self, rms_m: float, corr_m: float, offset: int):
        self.rms, self.corr, self.offset = rms_m, corr_m, offset
        self.step = NODE_SPACING * corr_m
        self.ij = np.zeros((0, 2), dtype=np.int64)
        self.xy = np.zeros((0, 2))
        self.n_left = 0

    def prior(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return self.rms * self.rms * _kernel(a, b, self.corr)

    def needed(self, pts: np.ndarray) -> np.ndarray:
        """Grid indices (K, 2) of the nodes within READ_RADIUS of any of ``pts``."""
        r = READ_RADIUS * self.corr
        lo = np.floor((pts.min(axis=0) - r) / self.step).astype(np.int64)
        hi = np.ceil((pts.max(axis=0) + r) / self.step).astype(np.int64)
        gi, gj = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij")
        ij = np.stack([gi.ravel(), gj.ravel()], axis=1)
        xy = ij * self.step
        d2 = ((xy[:, None, :] - pts[None, :, :]) ** 2).sum(axis=-1).min(axis=1)
        return ij[d2 <= r * r]

    def columns(self, ij: np.ndarray) -> np.ndarray:
        """State columns of held nodes ``ij`` (all held)."""
        key = {tuple(k): n for n, k in enumerate(self.ij.tolist())}
        return self.offset + np.array([key[tuple(k)] for k in ij.tolist()], dtype=np.int64)

    def enter(self, p: np.ndarray, ij: np.ndarray) -> np.ndarray:
        """``p`` grown by the nodes ``ij`` not yet held, conditioned on every node held."""
        held = {tuple(k) for k in self.ij.tolist()}
        new = np.array([k for k in ij.tolist() if tuple(k) not in held], dtype=np.int64).reshape(-1, 2)
        if not len(new):
            return p
        xy_new = new * self.step
        c_nn = self.prior(xy_new, xy_new) + JITTER * self.rms ** 2 * np.eye(len(new))
        n0 = p.shape[0]
        grown = np.zeros((n0 + len(new), n0 + len(new)))
        grown[:n0, :n0] = p
        if n0 > self.offset:  # (nodes held)
            c_hh = self.prior(self.xy, self.xy) + JITTER * self.rms ** 2 * np.eye(len(self.xy))
            c_rn = self.prior(self.xy, xy_new)
            gain = np.linalg.solve(c_hh, c_rn).T  # (new, held): f_new = gain f_held + w
            cols = np.arange(self.offset, n0)
            cross = gain @ p[cols, :]  # (new, n0)
            grown[n0:, :n0] = cross
            grown[:n0, n0:] = cross.T
            grown[n0:, n0:] = cross[:, cols] @ gain.T + c_nn - gain @ c_rn
        else:
            grown[n0:, n0:] = c_nn
        self.ij = np.concatenate([self.ij, new])
        self.xy = np.concatenate([self.xy, xy_new])
        return grown

    def leave(self, p: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """``p`` without the nodes every point of ``pts`` is LEAVE_RADIUS or more from (marginalised)."""
        if not len(self.ij):
            return p
        r = LEAVE_RADIUS * self.corr
        d2 = ((self.xy[:, None, :] - pts[None, :, :]) ** 2).sum(axis=-1).min(axis=1)
        keep = d2 < r * r
        if keep.all():
            return p
        self.ij, self.xy = self.ij[keep], self.xy[keep]
        self.n_left += int((~keep).sum())
        idx = np.concatenate([np.arange(self.offset), self.offset + np.flatnonzero(keep)])
        return p[np.ix_(idx, idx)]

    def read(self, pts: np.ndarray, ij: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Kriging weights (M, K) of the points ``pts`` on the held nodes ``ij`` and each point's interpolation error
        variance (M,)."""
        xy = ij * self.step
        c = self.prior(xy, xy) + JITTER * self.rms ** 2 * np.eye(len(ij))
        k = self.prior(pts, xy)
        w = np.linalg.solve(c, k.T).T
        resid = np.clip(self.rms ** 2 - np.einsum("mk,mk->m", w, k), 0.0, None)
        return w, resid


def exact_pcrb(truth, terrain, epochs, grade, p0: np.ndarray, *, dirs_body=None, sigma_m: float,
               baro_sigma_m: float | None = None, map_error_rms_m: float = 0.0, map_error_corr_m: float = 0.0,
               map_bias_m: float = 0.0, surface: bool = False, stats: dict | None = None) -> np.ndarray:
    """(T, 15) σ of the exact floor at the prior (t = 0) and after each update ``epochs`` (IMU sample indices), the
    map's error in the state (module docstring); the arguments as :func:`warptan.filter.bound.pcrb`, plus
    ``map_bias_m`` (the RMS of an offset shared by the whole map). ``dirs_body`` None: the altimeter (one nadir
    reading; with ``baro_sigma_m`` a barometer reads the altitude as well). ``stats``, a dict, receives the largest
    node window held (``max_nodes``), the nodes that left it (``nodes_left``) and the largest interpolation error
    variance met (``max_interp_var``, m²)."""
    if not (sigma_m > 0.0):
        raise ValueError(f"exact_pcrb: sigma_m = {sigma_m!r} must be > 0")
    if not (0.0 <= map_error_rms_m < np.inf and 0.0 <= map_bias_m < np.inf) or (
            map_error_rms_m > 0.0 and not 0.0 < map_error_corr_m < np.inf):
        raise ValueError(f"exact_pcrb: map error rms {map_error_rms_m!r} m, correlation {map_error_corr_m!r} m, "
                         f"bias {map_bias_m!r} m: the RMS and bias must be ≥ 0 and a correlated error's length > 0")
    q = process_noise(grade, 1.0 / truth.rate_hz)
    n_lead = 15 + int(map_bias_m > 0.0)
    field = _FieldWindow(map_error_rms_m, map_error_corr_m, n_lead) if map_error_rms_m > 0.0 else None
    p = np.zeros((n_lead, n_lead))
    p[:15, :15] = p0
    if map_bias_m > 0.0:
        p[15, 15] = map_bias_m ** 2
    out = [np.sqrt(np.diag(p0))]
    seen = {"max_nodes": 0, "max_interp_var": 0.0}
    k = 0
    for epoch in epochs:
        phi, qd = interval_transition(truth, k, epoch, q)
        k = epoch
        p[:15, :] = phi @ p[:15, :]
        p[:, :15] = p[:, :15] @ phi.T
        p[:15, :15] += qd
        pos = truth.pos_n[epoch]
        rows = scan_rows(terrain, pos, truth.quat_nb[epoch], dirs_body, surface)
        if rows is not None:
            off, g = rows
            pts = pos[:2] + off
            m = len(pts)
            white = np.full(m, sigma_m ** 2)
            cols = np.zeros(0, dtype=np.int64)
            if field is not None:
                p = field.leave(p, pts)
                ij = field.needed(pts)
                p = field.enter(p, ij)
                w, resid = field.read(pts, ij)
                cols = field.columns(ij)
                white += resid
                seen["max_nodes"] = max(seen["max_nodes"], len(field.ij))
                seen["max_interp_var"] = max(seen["max_interp_var"], float(resid.max()))
            h = np.zeros((m, p.shape[0]))
            h[:, :15] = g
            if map_bias_m > 0.0:
                h[:, 15] = 1.0
            if len(cols):
                h[:, cols] = w
            if dirs_body is None and baro_sigma_m is not None:
                h = np.vstack([h, np.eye(1, p.shape[0], 2)])
                white = np.append(white, baro_sigma_m ** 2)
            ph = p @ h.T
            s = h @ ph + np.diag(white)
            p = p - ph @ np.linalg.solve(s, ph.T)
            p = 0.5 * (p + p.T)
        out.append(np.sqrt(np.clip(np.diag(p[:15, :15]), 0.0, None)))
    if stats is not None:
        stats.update(seen, nodes_left=field.n_left if field is not None else 0)
    return np.array(out)
