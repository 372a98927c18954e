# Over 500 lines on purpose: the likelihood's settings carry the map-error modes' derivation (the modes, their
# sharing along a straight or turning track, the revisit memory), whose equations and measurements are in the
# docstrings; a split would separate the statement from the modes it defines.
"""The likelihood of a measurement model: the error a point's prediction carries (sensor, map, the map's stated
accuracy and its correlation along the track), the exponent of ground read again (:class:`RevisitMemory`), and how
the kernels are told (:class:`Likelihood`; the kernels' side is :mod:`warptan.kernels.likelihood`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from warptan.checks import FilterError
from warptan.device import one_blas_thread
from warptan.kernels import likelihood as klik

POSITION_PRIOR_PRECISION = 1.0e-4
"""Prior precision (m⁻², σ = 100 m) of the position in the attitude information's Schur complement
(:attr:`Likelihood.project_position`): negligible against a scan's position information, it only keeps Λ_pp
invertible where the ground says nothing horizontally."""

MAX_CONFIDENCE = 10.0
"""The widest factor a map-error statement may be right within (:attr:`Likelihood.map_error_confidence`)."""


def check_confidence(value) -> float:
    """``value`` as a map-error statement's confidence factor (:attr:`Likelihood.map_error_confidence`).

    Raises:
        FilterError: not a number in [1, :data:`MAX_CONFIDENCE`].
    """
    try:
        f = float(value)
    except (TypeError, ValueError):
        f = math.nan
    if not (math.isfinite(f) and 1.0 <= f <= MAX_CONFIDENCE):
        raise FilterError(f"map_error_confidence must be a factor in [1, {MAX_CONFIDENCE:g}] (the stated RMS is right "
                          f"within it), got {value!r}")
    return f

LIKELIHOODS = {"paper": klik.LIK_PAPER, "gaussian": klik.LIK_GAUSS, "student_t": klik.LIK_STUDENT}


MIN_FIX_SLOPE = 0.05
"""The smallest RMS slope :meth:`Likelihood.fix_sigma_m` divides by (a 1-in-20 ground: at most 20 times the
error as a fix error; the 90 m flat tile's 0.014 would make it 70 times, a filter that forgets its position)."""


def footprint_correlation(ratio: float) -> float:
    """``ρ̄``, the mean correlation ``exp(−r² / L²)`` between two points uniform on a square of side ``D = ratio ·
    L``: the square of the one-dimensional mean ``m(a) = √π erf(a) / a − (1 − e^(−a²)) / a²`` (``a = D / L``; 1 at
    ``a → 0``), the Gaussian covariance being separable."""
    a = float(ratio)
    if a < 1e-6:
        return 1.0
    m = math.sqrt(math.pi) * math.erf(a) / a - (1.0 - math.exp(-a * a)) / (a * a)
    return m * m


def without_offset(cov: np.ndarray, o: np.ndarray | None) -> np.ndarray:
    """``P cov P`` with ``P = I − o oᵀ`` (``o`` a unit vector: the offset direction the particles' altitude carries,
    :meth:`Likelihood.error_modes`' ``absorb_offset``); ``cov`` itself for ``o`` None."""
    if o is None:
        return cov
    project = np.eye(len(o)) - np.outer(o, o)
    return project @ cov @ project


def _turn_sharing(xy, aa, vec, lam, along, turn, lags, length, step) -> np.ndarray:
    """The attitude's sharing ``κᵃ_i`` of each mode (``vec``, ``lam``: the kept modes of the footprint ``xy`` with the
    sensitivities' products ``aa``) over a flight turning by ``turn`` rad per track step ``step`` (positive: the
    heading grows) at the lags ``lags`` (m of arc): ``1 + 2 Σ_k max(ρ_i, ρ_i cos Δψ_k)`` summed apart, ``ρ_i(l) = u_iᵀ
    A R(l) A u_i / λ_i`` with the later scan's footprint turned by ``Δψ = turn l / s`` about an aircraft moved along
    the arc (read at up to 17 lags, by the trapezoid; 0 when the heading turns by less than 0.01 rad over the lags, a
    straight flight's heading noise included: the straight pass's ``κ_i`` holds, and no arc is summed)."""
    if abs(turn) * float(lags[-1]) / step < 0.01:
        return np.zeros(len(lam))
    read = sorted(set(range(0, len(lags), max(1, len(lags) // 16))) | {len(lags) - 1})
    normal = np.array([-along[1], along[0]])
    plain, turned = [], []
    for arc in lags[read]:
        dpsi = turn * arc / step
        c, s = math.cos(dpsi), math.sin(dpsi)
        shift = arc * (math.sin(dpsi) / dpsi * along + (1.0 - c) / dpsi * normal) if dpsi else arc * along
        later = xy @ np.array([[c, s], [-s, c]]) + shift  # the footprint turned by Δψ (rows: Rot(Δψ) x), moved
        d2 = np.sum((xy[:, None, :] - later[None, :, :]) ** 2, axis=2)
        rho = np.sum(vec * ((aa * np.exp(-d2 / (length * length))) @ vec), axis=0) / lam
        plain.append(rho)
        turned.append(rho * c)

    def summed(values):  # Σ_{k≥1} by the trapezoid over the lags read (the sum itself when every step's lag is read)
        v, at = np.array(values), lags[read]
        ends = 0.5 * (v[0] + v[-1]) if len(at) > 1 else v[0]
        return np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(at)[:, None], axis=0) / step + ends

    return 1.0 + 2.0 * np.maximum(summed(plain), summed(turned))


@dataclass(frozen=True)
class Likelihood:
    """How residuals become a log-likelihood.

    Attributes:
        kind: "paper" (Gaussian on the scalar error), "gaussian" or "student_t" (per point).
        r_err: Variance of the paper's scalar error, m².
        sigma_m: Per-point residual scale σ, m; None = calibrated (:meth:`sigma_eff`).
        nu: Student-t degrees of freedom.
        outlier_sigmas: A point the particle cannot predict (off the map, nodata, no hit; under a stated map
            error also a residual the stated error cannot make, :func:`warptan.kernels.likelihood.gross_miss`)
            scores as a residual of this many σ (per point); the paper form blends its score with
            ``-0.5 outlier_sigmas²`` by the fraction of unpredictable points.
        sensor_sigma_m: Noise of one measured residual, m (range noise; the altimeter's noise).
        map_sigma_m: Known error of the map, m, added to the model's own surface mismatch (calibrated σ only).
        map_correlation: Consecutive updates over which a point sees the same map error (≥ 1): a moving scan
            reads the same DEM cells for about ``post spacing / (speed / measurement rate)`` updates, so the map
            part of σ² is multiplied by it (the standard inflation of a white-noise model for a correlated
            error; without it the filter counts one map error several times and its 3σ shrinks below the truth).
        footprint_correlation: Consecutive updates over which a scan reads the same ground (its along-track
            footprint over the distance flown per update; ≥ 1). The attitude information of a scan (the Kalman
            update of the linear states) is a regression of the whole footprint's residuals, so the map part of
            its error persists until the footprint is renewed, not only while a point stays in its cell: the
            attitude information uses ``σ_att² = σ² + (max(footprint, map_correlation) - map_correlation) ·
            (map² + mismatch²)`` (:meth:`sigma_att`). Measured (S1, 120 s, map = world, bilinear model):
            without it the attitude error is a terrain-fixed bias the same in both seeds looked at (roll +0.0025°,
            yaw +0.008–0.012°) and the reported σ is 3–5× below the RMSE (4 seeds); the weights keep σ (position
            stays honest: its process noise forgets faster than the footprint renews).
        fix_corr_m: Correlation length (m) of the terrain's slope under a stated map error: the scale on which
            the position fix the map error causes changes (:meth:`fix_process`); 0: the error's own length.
        fix_slope: The map's RMS slope (:attr:`~warptan.terrain.grid.Terrain.slope_rms`, at least
            :data:`MIN_FIX_SLOPE`): a vertical error e moves the fix by about e / slope (:meth:`fix_process`); 1:
            a slope of 1.
        fix_footprint_m: The scan's along-track footprint under a stated map error, m: the share of the error its
            offset does not absorb across the footprint moves the fix (:meth:`fix_process`); 0: all of it.
        map_error_learn: The stated ``map_error_sigma_m`` is a prior that the filter corrects in flight from its own
            residuals (:class:`~warptan.sensing.learner.MapErrorLearner`; a filter of one run, not a batch).
        map_error_confidence: The factor ``F`` (1–10) within which the stated (or default) RMS is right, when it is
            a prior (``map_error_learn``): the learner may raise σ_e to at most ``F`` times it (lower, freely), and
            the offset of the map under the scan, which no scan can see (the particles' altitude carries it:
            :meth:`offset_process`), is reported at the statement's upper end, ``F σ_e``. 1: the RMS is an upper
            bound known exactly. Without learning the statement is taken as exact and ``F`` is not used.
        revisit_correlation: Correlation ρ ∈ [0, 1) of the position fixes of two passes over the same ground under
            a stated map error (:class:`RevisitMemory`): the share of a pass's fix that is the map's error, which
            a pass over the same ground reads again; 0: passes independent.
        project_position: The attitude information the Kalman update reads is the part of the residuals' information
            on dθ that a position offset cannot explain (the Schur complement ``Λ_θθ - Λ_θp Λ_pp⁻¹ Λ_pθ`` and ``b``
            likewise, :func:`warptan.kernels.likelihood.attitude_information`; a weak prior of
            :data:`POSITION_PRIOR_PRECISION` keeps ``Λ_pp`` invertible over flat ground). A particle's position is
            only as good as the cloud (tens of cm), while a scan's attitude information is at the level of a
            hundredth of a millidegree (1 cm at 650 m): without the projection each particle's Kalman mean
            absorbs its own position offset as attitude, every resampling passes one lineage's absorbed offsets to
            all particles, and neither P nor the spread of the means shows it. Measured (CPU, 120 s, 4 seeds of
            the worst seeds of the 20-seed run): S3 attitude 3σ coverage 72/56/50 % (σ/RMSE 0.44) without, 99/100/100 %
            (0.85/0.73/0.75) with, and the attitude RMSE halved (pitch 0.0019° → 0.0009°). The weights
            (the attitude marginal) always use the whole information.
    """

    kind: str = "paper"
    r_err: float = 1.0
    sigma_m: float | None = None
    nu: float = 4.0
    outlier_sigmas: float = 4.0
    sensor_sigma_m: float = 0.5
    map_sigma_m: float = 0.0
    map_correlation: float = 1.0
    footprint_correlation: float = 1.0
    project_position: bool = True
    map_error_sigma_m: float = 0.0
    map_error_corr_m: float = 0.0
    track_step_m: float = 0.0
    fix_corr_m: float = 0.0
    fix_slope: float = 1.0
    fix_footprint_m: float = 0.0
    revisit_correlation: float = 0.9
    map_error_learn: bool = False
    map_error_confidence: float = 2.0

    def __post_init__(self):
        if self.kind not in LIKELIHOODS:
            raise FilterError(f"unknown likelihood {self.kind!r}; choose one of {', '.join(LIKELIHOODS)}")
        for name in ("r_err", "sigma_m", "nu", "outlier_sigmas"):
            value = getattr(self, name)
            if name == "sigma_m" and value is None:
                continue
            if not (np.isfinite(value) and value > 0):
                raise FilterError(f"likelihood {name} must be a positive number, got {value!r}")
        for name in ("sensor_sigma_m", "map_sigma_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise FilterError(f"likelihood {name} must be a number ≥ 0, got {value!r}")
        for name in ("map_correlation", "footprint_correlation"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 1):
                raise FilterError(f"likelihood {name} must be a number ≥ 1, got {value!r}")
        if not (np.isfinite(self.fix_slope) and self.fix_slope > 0):
            raise FilterError(f"likelihood fix_slope must be a positive number, got {self.fix_slope!r}")
        for name in ("map_error_sigma_m", "map_error_corr_m", "track_step_m", "fix_corr_m", "fix_footprint_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise FilterError(f"likelihood {name} must be a number ≥ 0, got {value!r}")
        check_confidence(self.map_error_confidence)
        if not (np.isfinite(self.revisit_correlation) and 0.0 <= self.revisit_correlation < 1.0):
            raise FilterError(f"likelihood revisit_correlation must be in [0, 1), got {self.revisit_correlation!r}")
        if self.map_error_sigma_m > 0 and self.map_error_corr_m <= 0:
            raise FilterError("likelihood map_error_corr_m must be > 0 when map_error_sigma_m is stated, got "
                              f"{self.map_error_corr_m!r}")

    @property
    def models_map_error(self) -> bool:
        """The likelihood marginalises a stated correlated map error (per-point forms only)."""
        return self.map_error_sigma_m > 0 and self.kind != "paper"

    def error_modes(self, xy: np.ndarray, sensitivity: np.ndarray, sigma_m: float,
                    along: tuple[float, float] = (1.0, 0.0), absorb_offset: bool = False,
                    turn: float = 0.0) -> tuple[np.ndarray, dict]:
        """The map-error mode table of a scan: ``(M + MODE_EXTRA_ROWS, MAX_MODES)`` float32 (rows named in
        :mod:`warptan.kernels.likelihood`): the modes ``u_ji``, then per mode its one-scan variance ``k⁰_i``, its
        one-scan weight ``c⁰_i`` (the NIS), its scan-to-scan correlation ``ρ_i``, the attitude information's weight
        ``cᵃ_i = κᵃ_i k⁰_i / (1 + κᵃ_i k⁰_i)`` (each mode read once per κᵃ_i scans that share it, below) and the
        basis change ``T`` from the previous table (identity here; the model fills it when it rebuilds), and a
        summary.

        The stated error is a Gaussian random field of RMS ``σ_e = map_error_sigma_m`` and covariance
        ``σ_e² exp(−(r/L)²)``, ``L = map_error_corr_m``. At the scan's ground points ``x_j`` (``xy``: horizontal
        offsets in the navigation frame, m) a residual sees ``a_j e(x_j)`` (``sensitivity`` a_j: 1 for a height
        residual, 1/cos of the ray's angle from the vertical for a range), so the whitened residuals ``z = r/σ``
        carry ``(σ_e²/σ²) A R A`` with ``R_jk = exp(−(|x_j − x_k|/L)²)``. Its leading eigenvectors ``u_i``
        (eigenvalues λ_i) are the map-error modes (offset, tilts, curvatures, …), ``z = Σ_i α_i u_i + n`` with
        amplitudes ``α_i`` of variance ``k⁰_i = σ_e² λ_i / σ²`` in one scan. A mode's error is shared by the
        consecutive scans that see the same ground: ``κ_i = Σ_k ρ_i(k s)``, with ``ρ_i(d) = u_iᵀ A R(d) A u_i /
        λ_i`` the mode's correlation with the scan ``d`` metres further along ``along`` (the flight's horizontal
        unit vector; ``s = track_step_m``; ``κ_i = 1`` without it; beyond 64 steps the sum is the trapezoid
        integral ``(1/s) ∫ ρ_i`` over 64 lags up to 4 L).

        The attitude's sharing ``κᵃ_i`` (at least κ_i) follows the flight's turn, ``turn`` rad of heading per track
        step (the model reads it from the heading at its looks): ``1 + 2 Σ_k max(ρ_i(l_k), ρ_i(l_k) cos Δψ_k)``
        along the arc, the later scan's footprint turned by ``Δψ_k`` with the aircraft (:func:`_turn_sharing`). A
        mode shaped like a derivative along the track (the along-track slope, the odd curvatures) has ``∫ ρ_i = 0`` on
        a straight line: its error telescopes, the mean along-track slope of a pass being the difference of its
        ends, so κ_i = 1 counts every scan's read of it as new. That holds for one straight pass, not for the
        attitude, a navigation-frame state, in a turn: the aircraft reads the same ground slope along another axis
        (the ``cos Δψ``: a roll or pitch read turned by Δψ), and an orbit inside one correlation length reads it
        again and again. Measured (``learn_study.py --families biased --modes learn --seeds 8 --worlds 4``: 10 m over
        3 km and a 5 m bias, CPU; roll / pitch 3σ coverage): with κ_i in ``cᵃ`` S1 (S-turns) 3.62 ± 0.80 m, 45 / 57
        %, the velocity 70 / 68 %; along the arc 2.58 ± 0.54 m, 94 / 95 %, 89 / 93 %; S2 (tactical IMU) 5.44 ±
        1.71 m, 72 / 75 % against 4.22 ± 1.26 m, 96 / 98 %. The orbits (S5, S6) it leaves as they were: their
        roll is short for another reason. The magnitude ``1 + 2 Σ |ρ_i|`` on the straight line (whatever the
        turn) gave S1 2.65 ± 0.56 m, 98 / 100 %, but cost the tactical IMU, which needs its attitude read (S2 over
        2 m / 300 m: 9.23 ± 2.09 m at σ/RMSE 0.64 / 0.57, against 6.80 ± 1.90 m at 0.83 / 0.75 along the arc, the
        same 8 seeds).

        The filter carries the amplitudes (Rao–Blackwellised: a mean per particle, a variance per filter; the map
        error under a hypothesis belongs to the hypothesis) from scan to scan as first-order processes of
        correlation ``ρ_i = (κ_i − 1)/(κ_i + 1)`` per scan, which holds the same number of independent scans
        (``Σ_k ρ^|k| = κ_i``) as the field. A particle's weight is then the exact predictive density of its scan
        given what its earlier scans said about the error under it: with prior ``(μ_i, P_i)`` and ``p_i = u_iᵀ
        z``, ``(z − Uμ)ᵀ(I + U P Uᵀ)⁻¹(z − Uμ) = zᵀz − Σ_i [p_i² − (1 − c_i)(p_i − μ_i)²]``, ``c_i = P_i / (1 +
        P_i)``, and the amplitudes' posterior ``μ_i + c_i (p_i − μ_i)`` (:func:`warptan.kernels.likelihood.
        acc_set_modes`). A particle tens of metres off fits each scan's smooth misfit into the modes only once:
        the next scans must agree with the amplitudes it claimed. The earlier form, each scan independent with its
        modes' variance times κ_i (the same information on average), let such a particle explain a new misfit in
        every scan: S2 (tactical IMU, 5 m / 1 km worlds, 20 seeds, ``results/world``) ran away to 86 m mean and
        S5 to 168 m; with the amplitudes carried, 4.7 ± 0.7 m and 6.4 ± 1.0 m. The integrity monitor's NIS
        judges one scan against the error as stated (weights ``c⁰_i``, μ = 0): whatever a filter believes about
        the error, a misfit larger than it is not a 5 m map error. Modes past ``MAX_MODES`` or below 1e-6 of the
        largest are dropped; ``remainder`` is the share of the error's variance they hold, and ``truncation_unit``
        (per unit of ``σ_e²``) the per-point variance that stands for them, white within a scan and shared by
        ``κ_r`` scans: ``t = κ_r Σ_dropped λ_i / Σ_j a_j²`` (``dropped_unit``: the same without ``κ_r``), with
        ``κ_r = 1 + 2 (tr(P S P) − Σ_kept u_iᵀ S u_i) / Σ_dropped λ_i`` (``S`` the lags' summed covariance below:
        the remainder's correlation along the track). The model adds ``σ_e² t`` to the per-point variance
        (:meth:`~warptan.sensing.measurement.MeasurementModel.sigma_m`): an error correlated over less than the
        footprint has more structure than :data:`MAX_MODES` modes hold (S2 told 10 m / 300 m: 16 modes leave 2.7 %
        of the error's variance, 2.7 m² a point against the sensor's 0.25 m², and the filter, taking that for
        information, was lost by kilometres in every seed).

        ``absorb_offset`` (a model whose prediction moves with the particle's altitude: ray casts, the sliding
        grid, the altimeter without a barometer): the map error's offset over the scan, ``A e = o (oᵀ A e) + P A
        e`` with ``o = a / |a|`` and ``P = I − o oᵀ``, is exactly a vertical shift of the aircraft by ``b = oᵀ A e
        / |a|`` (lowering the aircraft by d changes residual j by ``a_j d``), so the particles' altitude carries it
        (they track the height above the map, not above the world) and the modes are those of ``P A R A P``. The
        summary's ``offset_var`` is ``var b = σ_e² oᵀ A R A o / |a|²`` (m²). Marginalising the offset as a mode
        instead (each scan independent with κ-shared variance) throws away what consecutive scans say about the
        vertical motion (their offsets differ by the little the map error changes between them): measured on
        S2 (tactical IMU, 5 m / 1 km error, seed 0) the altitude ran away by 750 m with a 3σ of 3 m. The
        filter's side of it (the offset's change along the track as vertical-velocity noise, its variance added to
        the reported altitude variance) is :meth:`offset_process`."""
        from warptan.kernels.likelihood import MAX_MODES, MODE_C0, MODE_CA, MODE_EXTRA_ROWS, MODE_K0, MODE_RHO, MODE_T

        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        a = np.asarray(sensitivity, dtype=np.float64).reshape(-1)
        m, length = len(xy), self.map_error_corr_m
        table = np.zeros((m + MODE_EXTRA_ROWS, MAX_MODES), dtype=np.float32)
        table[m + MODE_T:] = np.eye(MAX_MODES, dtype=np.float32)
        if not self.models_map_error or m == 0:
            return table, {"n_modes": 0}

        direction = np.asarray(along, dtype=np.float64).reshape(2)
        direction = direction / max(float(np.linalg.norm(direction)), 1e-12)

        delta = xy[:, None, :] - xy[None, :, :]
        d2, along_d = np.sum(delta * delta, axis=2), delta @ direction  # |x_j − x_k|², (x_j − x_k) · along
        aa = a[:, None] * a[None, :]

        scan = aa * np.exp(-d2 / (length * length))  # A R A over the scan
        offset_var, o = 0.0, None
        if absorb_offset:
            o = a / max(float(np.linalg.norm(a)), 1e-300)
            offset_var = self.map_error_sigma_m**2 * float(o @ scan @ o) / float(a @ a)

        with one_blas_thread():
            lam, vec = np.linalg.eigh(without_offset(scan, o))
        order = np.argsort(lam)[::-1]
        lam, vec = np.maximum(lam[order], 0.0), vec[:, order]
        keep = [i for i in range(min(MAX_MODES, m)) if lam[i] > 1e-6 * lam[0]]
        lam_k, vec_k = lam[keep], vec[:, keep]
        sharing = sharing_att = np.ones(len(keep))
        rest = max(float(lam.sum() - lam_k.sum()), 0.0)  # the dropped modes' share of tr(P A R A P)
        rest_shared = 0.0
        step = self.track_step_m
        if step > 0 and keep:
            k_max = math.ceil(4.0 * length / step)
            lags = np.arange(1, k_max + 1) * step if k_max <= 64 else np.linspace(step, k_max * step, 64)
            # Σ_{k≥1} ρ_i(k s): the lags' sum, or beyond 64 steps (1/s) ∫_s^∞ ρ + ρ(s)/2 by the trapezoid over them; a
            # weighted sum of ρ_i(l_k) = u_iᵀ C(l_k) u_i / λ_i (the kept modes lie in the projection's range, P u_i =
            # u_i, so u_iᵀ P C P u_i = u_iᵀ C u_i): one matrix Σ_k w_k C(l_k) read by the modes. The lags are evenly
            # spaced (l_k = l_0 + k Δ), so C(l_k) = aa ∘ exp(−(d2 − 2 l_k along_d)/L²) · exp(−l_k²/L²) with the first
            # factor a running product (one exp per element for all lags, bounded by aa e^16: its exponent is at most
            # (l_k/L)² ≤ 16)
            if k_max <= 64:
                weights = np.ones(len(lags))
            else:
                weights = np.r_[0.5, np.ones(len(lags) - 2), 0.5] * (lags[1] - lags[0]) / step
                weights[0] += 0.5
            scale = 1.0 / (length * length)
            running = aa * np.exp(-(d2 - 2.0 * lags[0] * along_d) * scale)
            grow = np.exp(2.0 * (lags[1] - lags[0]) * along_d * scale) if len(lags) > 1 else None
            summed = np.zeros_like(running)
            for k, d in enumerate(lags):
                summed += (weights[k] * math.exp(-d * d * scale)) * running
                if grow is not None and k + 1 < len(lags):
                    running *= grow
            total = np.sum(vec_k * (summed @ vec_k), axis=0) / lam_k
            sharing = np.maximum(1.0 + 2.0 * total, 1.0)
            if rest > 0.0:  # tr(P S P) − Σ_i u_iᵀ S u_i: the dropped modes' share of the scans' summed covariance
                shared = float(np.trace(summed)) - (0.0 if o is None else float(o @ summed @ o))  # (P = I − o oᵀ)
                rest_shared = max(shared - float(np.sum(total * lam_k)), 0.0)
            with one_blas_thread():
                turned = _turn_sharing(xy, aa, vec_k, lam_k, direction, turn, lags, length, step)
            sharing_att = np.maximum(turned, sharing)
        dropped = rest / max(float(a @ a), 1e-300)  # the dropped modes' variance a point, per unit σ_e² and gain²
        kappa_rest = max(1.0 + 2.0 * rest_shared / rest, 1.0) if rest > 0.0 else 1.0  # the scans that share it
        k_one = self.map_error_sigma_m**2 * lam_k / sigma_m**2  # k⁰_i: one scan's
        rho = (sharing - 1.0) / (sharing + 1.0)
        table[:m, :len(keep)] = vec_k.astype(np.float32)
        table[m + MODE_K0, :len(keep)] = k_one.astype(np.float32)
        table[m + MODE_C0, :len(keep)] = (k_one / (1.0 + k_one)).astype(np.float32)
        table[m + MODE_RHO, :len(keep)] = rho.astype(np.float32)
        table[m + MODE_CA, :len(keep)] = (sharing_att * k_one / (1.0 + sharing_att * k_one)).astype(np.float32)
        return table, {"n_modes": len(keep), "eigenvalues": lam_k.tolist(), "sharing": sharing.tolist(),
                       "sharing_att": sharing_att.tolist(),
                       "k0": k_one.tolist(), "rho": rho.tolist(),
                       "remainder": float(1.0 - lam_k.sum() / max(lam.sum(), 1e-300)), "offset_var": offset_var,
                       "dropped_unit": dropped, "truncation_unit": dropped * kappa_rest}

    def mode_spectrum(self, xy: np.ndarray, sensitivity: np.ndarray, modes: np.ndarray, sigma_m: float,
                      lengths: np.ndarray, absorb_offset: bool = False) -> np.ndarray:
        """Each mode's one-scan variance per unit error variance (m⁻²) were the error correlated over each of
        ``lengths``: ``(len(lengths), n)``, ``u_iᵀ P A R(L) A P u_i / σ²`` for the modes ``u_i`` (``modes``, M × n,
        of a table of :meth:`error_modes` for these ``xy``, ``sensitivity``, ``sigma_m`` and ``absorb_offset``,
        whose projection ``P`` of the offset it applies too). At the table's own length it is ``λ_i / σ²`` (``k⁰_i /
        σ_e²``). :class:`~warptan.sensing.learner.MapErrorLearner` weighs the correlation length with it: an error
        shorter than stated puts more of its variance into the higher modes."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        a = np.asarray(sensitivity, dtype=np.float64).reshape(-1)
        u = np.asarray(modes, dtype=np.float64)
        if absorb_offset:
            o = a / max(float(np.linalg.norm(a)), 1e-300)
            u = u - np.outer(o, o @ u)
        au = a[:, None] * u
        d2 = np.sum((xy[:, None, :] - xy[None, :, :]) ** 2, axis=2)
        return np.array([np.sum(au * (np.exp(-d2 / (length * length)) @ au), axis=0)
                         for length in np.asarray(lengths, dtype=np.float64)]) / sigma_m**2

    @staticmethod
    def rescale_error_modes(table: np.ndarray, m: int, factor: float) -> np.ndarray:
        """A mode table of :meth:`error_modes` (``m`` points) for a map-error variance ``factor`` times the one it was
        built for: the same modes and correlations ``ρ_i``, the one-scan variances ``k⁰_i`` scaled, the weights
        ``c⁰_i`` from them and ``cᵃ_i`` from its odds ``κᵃ_i k⁰_i = cᵃ_i / (1 − cᵃ_i)`` scaled, no basis change
        (``T = I``)."""
        from warptan.kernels.likelihood import MAX_MODES, MODE_C0, MODE_CA, MODE_K0, MODE_T

        out = table.copy()
        k = table[m + MODE_K0].astype(np.float64) * float(factor)
        ca = np.clip(table[m + MODE_CA].astype(np.float64), 0.0, 1.0 - 1e-7)
        odds = ca / (1.0 - ca) * float(factor)  # κᵃ_i k⁰_i, scaled
        out[m + MODE_K0] = k.astype(np.float32)
        out[m + MODE_C0] = (k / (1.0 + k)).astype(np.float32)
        out[m + MODE_CA] = (odds / (1.0 + odds)).astype(np.float32)
        out[m + MODE_T:] = np.eye(MAX_MODES, dtype=np.float32)
        return out

    def offset_process(self, speed_mps: float) -> tuple[float, float]:
        """What the filter adds for a map-error offset its particles' altitude carries (``absorb_offset`` of
        :meth:`error_modes`): ``(var_b, q_v)``, the offset's variance (m², added to the reported altitude
        variance: the particles know the height above the map, the truth differs by b) and the vertical-velocity
        noise density (m²/s³) that lets the filter follow the offset's change along the track.

        Along the track at speed v the offset b(t) is a smooth process of covariance ``σ_b² exp(−(v τ / L)²)``,
        so ``var ḃ = 2 σ_b² v² / L²`` with correlation time ``τ = L / v``; ``q_v = 2 var ḃ / τ = 4 σ_b² v³ / L³``
        (a first-order Gauss–Markov ḃ's driving noise; the integrated position variance over τ, ``q_v τ³ / 3 =
        4σ_b²/3``, matches the offset's structure function ``2σ_b²(1 − e⁻¹) = 1.26 σ_b²`` there). ``σ_b = σ_e``
        bounds the offset of any footprint (its average over the footprint varies less) and ``L`` bounds the
        offset's correlation length from below (the footprint's average is smoother): both on the safe side.
        ``(0, 0)`` without a stated map error.

        A statement that is a prior (``map_error_learn``) reports ``var_b = (F σ_e)²``, ``F`` its
        ``map_error_confidence``: no residual sees the offset (a map 10 m high everywhere looks exact to every scan),
        so the learner cannot tell its level, and the statement's upper end is what the altitude's σ can honestly
        claim. ``q_v`` uses σ_e itself (the offset's change along the track is the learned error's)."""
        if not self.models_map_error:
            return 0.0, 0.0
        var_e = self.map_error_sigma_m**2
        var_b = var_e * (self.map_error_confidence**2 if self.map_error_learn else 1.0)
        v = max(float(speed_mps), 0.0)
        return var_b, 4.0 * var_e * v**3 / self.map_error_corr_m**3

    def fix_process(self, speed_mps: float) -> float:
        """The position noise density (m²/s) the Kalman part adds to ``Q^n`` under a stated map error: the
        particles follow where the map fits best, which differs from the truth by a fix error that the map error
        moves along the track. The Kalman part reads the particles' paths as velocity (``N_k``, ``L_k``), so it must
        allow that wander: a first-order process of variance ``σ_d²`` and correlation time ``τ = ℓ / v`` has
        increments of variance ``2 σ_d² dt / τ`` over ``dt ≪ τ``, i.e. a noise density ``2 σ_d² v / ℓ``, with
        ``σ_d = σ_e`` (a fix error as large as the vertical error: a terrain slope of 1, as in
        :meth:`offset_process`) and ``ℓ = min(L, fix_corr_m)``: the fix turns the map error into a position through
        the terrain's gradients under the footprint, so it changes as fast as the shorter of the error's correlation
        length and the slope's (``fix_corr_m``: :attr:`warptan.terrain.grid.Terrain.slope_correlation_m` of the map,
        set by :func:`warptan.sim.scenarios.scenario_likelihood`; 0: L alone). Measured (S2, tactical IMU, 5 m / 1 km
        world, seeds 0–1, CPU): with the attitude's information counted once per independent patch
        (:func:`warptan.kernels.likelihood.attitude_information`) and without this noise the velocity ran away
        (3–10 m/s error at 17–52 σ, 27–140 m); with ``ℓ = L`` 3.4/2.5 m at 96/98 % coverage. With the slope's
        length (the 90 m rugged tile's 260 m, 4× the density; world 1003, seeds 15–16): north/east 3σ coverage
        84/84 → 96/98 %, σ/RMSE 0.51/0.48 → 0.70/0.70, RMSE 6.5 → 6.2 m; ℓ = 4L (a quarter of the density with
        L) gave 66/73 %; ``results/world`` (20 seeds): S2 σ/RMSE 0.64/0.74 → 0.86/0.96. Only for models whose one scan
        fixes the position
        (``MeasurementModel.fixes_per_scan``: point clouds): an altimeter's fix builds up over many scans, and with
        this noise S9/S12 (20 seeds, H100) went from 19 m mean to 177/187 m (a seed 2.8 km off, flagged). 0
        without a stated map error."""
        if not self.models_map_error:
            return 0.0
        length = min(self.map_error_corr_m, self.fix_corr_m) if self.fix_corr_m > 0 else self.map_error_corr_m
        return 2.0 * self.fix_sigma_m()**2 * max(float(speed_mps), 0.0) / length

    def fix_sigma_m(self) -> float:
        """``σ_d``, the σ of the fix error a stated map error causes (:meth:`fix_process`): ``σ_d = σ_e √(1 − ρ̄) /
        s``. The altitude absorbs the error's mean over the footprint (:meth:`offset_process`); what is left, of
        variance ``σ_e² (1 − ρ̄)`` with ``ρ̄`` the error's mean correlation between two points of a square footprint
        of side ``D`` (``fix_footprint_m``; :func:`footprint_correlation`), is matched by moving the fix, and a
        vertical error e is matched by a move of e / s on ground of slope s (``fix_slope``, the map's RMS slope).
        Before, ``σ_d = σ_e`` (a slope of 1, the whole error): on the 90 m rugged tile (RMS slope 0.14, S8's
        footprint 693 m) σ_d is 5.8 σ_e for L = 300 m, 2.7 σ_e for 1 km and 0.9 σ_e for 3 km. With σ_d = σ_e the
        reported σ fell below the error on short-correlated and cluttered worlds, most in the stretches where the
        terrain fixes the position weakly; with this σ_d
        the ``short`` and ``clutter`` rows of S7 and S8 went from σ/RMSE 0.6–0.75 to 0.9–1.1 for about 10 % of RMSE
        (``results/learned``, 20 seeds)."""
        share = 1.0 - footprint_correlation(self.fix_footprint_m / self.map_error_corr_m) if (
            self.fix_footprint_m > 0 and self.map_error_corr_m > 0) else 1.0
        return self.map_error_sigma_m * math.sqrt(max(share, 0.0)) / self.fix_slope

    def point_sharing(self) -> float:
        """Consecutive scans of a straight pass that read the stated error under one ground point: ``κ = 1 + 2
        Σ_k exp(−(k s / L)²)`` over the track step ``s`` (``track_step_m``; ≈ √π L / s); 1 without a step or a
        stated error."""
        step, length = self.track_step_m, self.map_error_corr_m
        if not self.models_map_error or step <= 0:
            return 1.0
        k = np.arange(1, math.ceil(4.0 * length / step) + 1)
        return float(1.0 + 2.0 * np.exp(-((k * step / length) ** 2)).sum())

    def sigma_eff(self, model_mismatch_m: float) -> float:
        """The per-point σ in m: ``sigma_m`` when given, else
        ``sqrt(sensor² + map_correlation · (map² + model_mismatch²))`` (at least 1 cm)."""
        if self.sigma_m is not None:
            return float(self.sigma_m)
        map_var = self.map_correlation * (self.map_sigma_m**2 + model_mismatch_m**2)
        return max(0.01, math.sqrt(self.sensor_sigma_m**2 + map_var))

    def sigma_att(self, model_mismatch_m: float) -> float:
        """The per-point σ of the attitude information in m (see ``footprint_correlation``)."""
        extra = max(self.footprint_correlation - self.map_correlation, 0.0)
        return math.sqrt(self.sigma_eff(model_mismatch_m) ** 2 + extra * (self.map_sigma_m**2 + model_mismatch_m**2))


class RevisitMemory:
    """The log-likelihood's exponent of each filter's next update over ground whose map error it has read before.

    The map-error modes carry their amplitudes from scan to scan as first-order processes (:meth:`Likelihood.
    error_modes`): they remember an error for about the scans of one straight pass over it, ``κ`` of
    :meth:`Likelihood.point_sharing` (177 at 10 m per scan and L = 1 km). Ground read again after that (an orbit,
    a racetrack, a return leg) is the same error read anew, and without a discount each pass over it counts that
    one error once more: its bias on the position is taken for information. With the earlier passes over this
    ground ``C = (1/κ) Σ_k exp(−|x − x_k|² / L²)`` (the scans ``k`` older than ``κ`` scans, ``x`` the scan's ground
    point; one straight pass through ``x`` makes ``C ≈ 1``), the update weighs what one more pass adds to passes
    whose fixes are correlated by ``ρ`` (``revisit_correlation``): ``n`` such passes hold ``n / (1 + (n − 1) ρ)``
    passes' information, so the exponent is ``(1 − ρ) / ((1 + C ρ)(1 + (C − 1) ρ))`` for ``C ≥ 1`` (a second pass
    ``(1 − ρ) / (1 + ρ)``, all passes together never more than ``1/ρ`` passes) and, over part of a pass read
    before, that of a second pass correlated by ``ρ C``: ``(1 − ρ C) / (1 + ρ C)`` (1 over new ground). What a pass
    adds besides the shared error is the sensor's noise and the ground seen from another side; an error shared in
    full (ρ → 1) would make it 0. Measured (S5 and S6, 60° bank, an orbit of 37 s inside one correlation length;
    5 m / 1 km world of seed 1003, seeds 15–16, CPU; north 3σ coverage, σ/RMSE north): without a discount 79/78 %,
    0.40 (S5) and 88/85 %, 0.50 (S6); ``(1 + C)⁻¹`` 81/83 %, 0.45 and 92/90 %, 0.55; ``(1 + C)⁻²`` 92/90 %, 0.55
    and 96/94 %, 0.62, the RMSE not worse (S5 6.5/6.9 → 5.7/6.3 m). After the estimator's later work, ``(1 + C)⁻²``
    (ρ ≈ 0.6 at C = 1 and 2, but 1.64 passes in all) left S5's north σ/RMSE at 0.75 over 20 seeds
    (``results/world``, 4 worlds, H100): ρ = 0.8 0.81, RMSE 6.10 m; ρ = 0.9 0.88, 5.98 m (6.18 m before); S6 east
    1.39 and 1.49, S2 unchanged (0.87/0.95). A told stated error is what a pass mostly reads (S5: 5 m against the
    sensor's 0.5 m): ρ = 0.9 is the default; an orbit's second pass (C about 0.8) then weighs about a sixth. A
    straight flight's older scans are 1.8 km behind: C < 0.01, an exponent ≥ 0.98. The positions are kept every
    ``κ/16`` scans (each standing for the scans since the one kept before): the host work of an update is
    O(flight length / κ) per filter, never O(particles). A caller may read the memory every few scans
    (``exponents(ground, scans=k)``: this ground stands for the ``k`` scans since the last reading; the filter does so
    every :data:`~warptan.filter.mpf.MarginalizedParticleFilter.PLATFORM_EVERY` updates)."""

    def __init__(self, likelihood: Likelihood, n_filters: int):
        self.likelihood = likelihood
        self.kappa = likelihood.point_sharing()
        self.stride = max(1, int(self.kappa // 16))
        self.n_filters = int(n_filters)
        self.count = 0  # scans seen
        self._kept = np.zeros((0, self.n_filters, 2))  # (K, B, 2) ground points, one per ≥ stride scans
        self._scans = np.zeros(0)  # (K,) the scans each kept point stands for
        self._at = np.zeros(0, dtype=np.int64)  # (K,) the scan index at which each was kept
        self._block = 0  # the stride block of the last kept point

    def restate(self, likelihood: Likelihood) -> None:
        """The same memory under a new statement (a learned correlation length): the ground read so far stays read
        (an orbit's earlier passes are still its earlier passes); ``κ`` and the kept points' spacing follow the new
        length. A new memory at every restated length forgot the passes, and each one was counted anew: S6 (an
        orbit inside one correlation length) went from σ/RMSE 0.9–1.6 told and not learning to 0.6–0.9 learning."""
        self.likelihood = likelihood
        self.kappa = likelihood.point_sharing()
        self.stride = max(1, int(self.kappa // 16))
        self._block = max(self.count - 1, 0) // self.stride

    def exponents(self, ground: np.ndarray, scans: int = 1) -> np.ndarray:
        """The exponents (B,) of the update whose ground points are ``ground`` (B, 2, m, navigation frame), which
        it then remembers as the ground of the ``scans`` scans since the last call."""
        ground = np.asarray(ground, dtype=np.float64).reshape(self.n_filters, 2)
        self.count += int(scans)
        now = self.count - 1  # (this ground's scan: the newest of them)
        old = self._at <= now - math.ceil(self.kappa)  # kept points older than κ scans
        passes = np.zeros(self.n_filters)
        if self.kappa > 1 and old.any():
            d2 = np.sum((self._kept[old] - ground[None]) ** 2, axis=2)
            weight = self._scans[old][:, None]
            passes = (weight * np.exp(-d2 / self.likelihood.map_error_corr_m**2)).sum(axis=0) / self.kappa
        block = now // self.stride
        if len(self._at) == 0 or block > self._block:  # a copy per kept point: O(K) every κ/16 scans
            if len(self._at):
                self._scans[-1] = now - self._at[-1]  # (the one before stands for the scans up to this one)
            self._kept = np.concatenate([self._kept, ground[None]])
            self._scans = np.append(self._scans, float(max(self.stride, scans)))
            self._at = np.append(self._at, now)
            self._block = block
        rho = self.likelihood.revisit_correlation
        again = (1.0 - rho) / ((1.0 + passes * rho) * (1.0 + (passes - 1.0) * rho))
        part = rho * np.minimum(passes, 1.0)
        return np.where(passes >= 1.0, again, (1.0 - part) / (1.0 + part))
