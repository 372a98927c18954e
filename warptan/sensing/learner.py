"""The map's error learned in flight (:class:`MapErrorLearner`): a stated (or default) map error is a prior that the
filter's own residuals correct, its RMS and its correlation length."""

from __future__ import annotations

import math

import numpy as np

from warptan.checks import FilterError
from warptan.kernels.filter.resampling import PROJ_HF, PROJ_HF_W, PROJ_SW


class MapErrorLearner:
    """The map error's RMS learned in flight: a stated (or default) ``σ_e`` is a prior that the filter's own
    residuals correct, so that neither silence nor a wrong statement fixes the likelihood's picture of the map.

    **Estimator.** The filter carries the amplitudes ``α_i`` of the map-error modes
    (:meth:`~warptan.sensing.likelihood.Likelihood.error_modes`: the error field's leading patterns over a scan,
    whitened by the point σ, one-scan variance ``k⁰_i = σ_e² λ_i / σ²``) as a Kalman mean per particle and a variance
    per filter. For a scan the modes rule (``k⁰_i ≥ 1``) the posterior second moment ``E[α_i²] = Σ_j w_j q_ij² + P⁺_i``
    (:func:`warptan.kernels.filter.resampling. map_error_moments_kernel`) has expectation ``k⁰_i`` exactly when the
    statement is right; a true error of variance ``σ_t²`` gives ``(1 + k_t,i) / k⁰_i`` with ``k_t,i = σ_t² λ_i / σ²``.
    The variance-component (EM) step for ``s = σ_e²`` is therefore ``s ← s · r̄`` with ``r̄`` the modes' mean ratio,
    whose fixed point is ``σ_t² + σ² / λ_i``: the true variance plus the noise a mode cannot tell from it (about (σ /
    8)² for a 10×10 scan). It is applied in the log domain with gain ``every / time_constant`` per reading (an
    exponential memory of ``time_constant`` updates, 30 s at 10 Hz by default: the error of one correlation length is
    read over 10 s at 100 m/s), the first readings faster (:attr:`PRIOR_READINGS`), each reading's ratio clipped to
    [1/4, 4]. Only the modes that lie mostly on points
    within 48° of the vertical are read (``MeasurementModel.mode_reads``): a banked scan's grazing rays, whose
    flat-ground sensitivity 1/u_z claims more error than a ray meeting a hill face sees, took the learned RMS of S5
    (60° bank) to a metre over a 5 m world.

    **Correlation length.** The modes' posterior moments lean on the statement: a mode the statement gives little
    variance (a curvature under a length three times too long: ``k⁰ ≈ 0.05``) keeps its prior whatever the scan says.
    The raw projections of the residuals do not: ``p_i = u_iᵀ r / σ`` at the particles, weighted by their likelihoods
    (:func:`~warptan.kernels.filter.resampling.mode_projection_kernel`), have ``E[p_i²] = c + s d_i(L)`` with ``d_i(L)``
    a mode's one-scan variance per unit error variance were the error correlated over ``L``
    (:meth:`~warptan.sensing.likelihood.Likelihood.mode_spectrum`), ``s = σ_e²`` and ``c`` the whitened noise's share
    (under 1: σ counts the map's interpolation noise too). Each reading fits ``(c, s)`` by maximum likelihood (the modes
    as independent Gaussians, on grids) for each length of ``LENGTH_FACTORS`` times the one in use and steps ``log L``
    towards the best with gain ``length_gain``; the length is restated (the table rebuilt) when it moved by 20 %, within
    ``[prior / length_range, prior · length_range]`` and at least ``min_corr_m``. Measured before it was wired in (S8,
    120 s, seed 0, one reading a second: ``every`` was 10 then): a 5 m / 1 km world told 3 km read 1.16 km (geometric
    mean of the readings after the first 20 s), told 1 km 0.80 km, and a 2 m / 300 m world from the default 500 m
    0.38 km.

    **Assumptions.** The error is a Gaussian covariance (one RMS, one length). The offset under the scan rides on the
    particles' altitude (it is not a mode), so the level and length are learned from the tilts and curvatures the
    scan sees.

    **Guard against a wrong lock confirming itself.** A filter locked in the wrong place explains its misfit with large
    mode amplitudes, which would raise ``σ_e`` and make the misfit look normal. So the learner reads only a converged
    filter (the particles' horizontal σ within ``max(converged_m, 3 σ_e)``), never while its integrity NIS (weighted
    over the particles) exceeds ``nis_max``, and ``σ_e`` stays within ``[floor_m, ceiling · prior]`` (``ceiling``: the
    statement's ``map_error_confidence``): the statement bounds how much worse the map may be learned to be, never how
    much better. The offset under the scan is not learned at all (no residual sees it): the altitude's σ counts the
    statement's upper end for it (:meth:`~warptan.sensing.likelihood.Likelihood.offset_process`).

    **The white error.** What varies from post to post (relief the map lacks, canopy, sub-post noise) the modes
    cannot hold: the likelihood counts it in the per-point σ as the map's own ``σ_map`` (``Likelihood.map_sigma_m``,
    from the DEM's own hold-out interpolation error unless stated; inflated by ``map_correlation`` for the
    consecutive scans that read the same cells). The residuals' energy outside the modes and the offset, per degree of
    freedom (``h`` of :func:`~warptan.kernels.filter.resampling.mode_projection_kernel`, weighted by the likelihoods:
    ``E[h σ²] = σ_sensor² + σ_map,true² + mismatch²`` at the truth), reads it. The learned ``σ_map²`` steps towards
    ``h σ² − σ_sensor² − mismatch²`` (gain ``length_gain`` per reading) when that energy exceeds
    :attr:`WHITE_EXCESS` times what the model expects, else back towards the prior; it stays within ``[prior, ceiling ·
    max(prior, σ_e prior)]``: unlike the RMS it is never learned below its prior, which is the DEM's own hold-out
    error, measured from the map itself rather than stated. The dead band keeps a map as good as modelled where it
    is: the particles' spread, the attitude's error and the modes' truncation add energy of their own. Only points
    within 48° of the vertical read it (``WHITE_MAX_GAIN``): a ray farther out has a slope-dependent sensitivity the
    modes do not hold, and its excess would read as white error. Only readings with a mode the scan rules read it, as
    the RMS: where no mode holds the correlated error, what is left of it reads as white (S5 under canopy: 1.8 → 4 m
    learned, the RMSE doubled). ``results/learned`` rows record what was learned
    (``white_learned_m``): the prior kept over a map that is the world and over the long and short families, about
    2.3–3 m over canopy and a smoothed product. The altimeter's one range has no degree of freedom for it.

    The filter (:class:`warptan.filter.mpf.MarginalizedParticleFilter`) runs one when its likelihood has
    ``map_error_learn``; ``scripts/learn_study.py`` measures it over six families of worlds. Not learned: anything in
    a batch. A single-range altimeter's filter rarely gets within the convergence guard, so it keeps its prior (S9,
    S12 in ``results/learned``). The weighted NIS cannot stand in for the white σ's evidence: at the truth it is ≈ 1
    over a map that is the world but ≈ 0.2 over a world of 5 m / 1 km error (the map part of σ² is inflated for the
    updates that read the same cells), and 0.6–0.7 under 8 m clutter, so its level depends on the model's own
    composition."""

    LENGTH_FACTORS = 2.0 ** (np.arange(-4, 5) / 2.0)
    """The correlation lengths weighed against each other at a reading, as factors of the one in use."""
    PRIOR_READINGS = 2.0
    """The prior's weight, in readings: the k-th reading that moves the RMS steps with gain ``max(every /
    time_constant, 1 / (PRIOR_READINGS + k))``, the running mean of its log ratios until the memory's time constant
    takes over (acquisition). At the memory's gain alone a reading moves ``log σ_e`` by at most ``ln 4 · every /
    600``: a statement 16 times the map's error needed the whole of a 120 s flight to come down."""
    WHITE_EXCESS = 1.5
    """The residuals' energy outside the modes, as a multiple of what the likelihood expects, above which the map's
    white error is learned to be larger than its prior."""

    def __init__(self, prior_sigma_m: float, every: int = 20, time_constant: float = 300.0, converged_m: float = 15.0,
                 nis_max: float = 4.0, floor_m: float = 0.05, ceiling: float = 2.0, prior_corr_m: float | None = None,
                 length_range: float = 4.0, min_corr_m: float = 0.0, length_gain: float | None = None,
                 white_prior_m: float | None = None, sensor_sigma_m: float = 0.0, mismatch_m: float = 0.0):
        if not (np.isfinite(prior_sigma_m) and prior_sigma_m > 0):
            raise FilterError(f"map-error prior must be a positive RMS in m, got {prior_sigma_m!r}")
        if prior_corr_m is not None and not (np.isfinite(prior_corr_m) and prior_corr_m > 0):
            raise FilterError(f"map-error prior correlation length must be positive, in m, got {prior_corr_m!r}")
        self.prior_sigma_m = float(prior_sigma_m)
        self.every = int(every)
        self.gain = min(1.0, self.every / float(time_constant))
        self.converged_m = float(converged_m)
        self.nis_max = float(nis_max)
        self.floor_m = float(floor_m)
        self.ceiling_m = float(ceiling) * self.prior_sigma_m
        self.log_var = 2.0 * math.log(self.prior_sigma_m)
        self.applied_sigma_m = self.prior_sigma_m
        self.readings = 0
        """Readings that moved the estimate."""
        self.prior_corr_m = None if prior_corr_m is None else float(prior_corr_m)
        self.log_len = None if prior_corr_m is None else math.log(self.prior_corr_m)
        self.applied_corr_m = self.prior_corr_m
        self.length_gain = 2.0 * self.gain if length_gain is None else float(length_gain)
        self.len_bounds = (0.0, 0.0)
        self._terms = None
        if prior_corr_m is not None:
            self.len_bounds = (math.log(max(self.prior_corr_m / length_range, min_corr_m)),
                               math.log(max(self.prior_corr_m * length_range, min_corr_m)))
        if white_prior_m is not None and not (np.isfinite(white_prior_m) and white_prior_m >= 0):
            raise FilterError(f"map white-error prior must be a non-negative RMS in m, got {white_prior_m!r}")
        self.white_prior_m = None if white_prior_m is None else float(white_prior_m)
        self.white_var = None if white_prior_m is None else self.white_prior_m**2
        """The learned white map error's variance, m² (None: not learned)."""
        self.applied_white_m = self.white_prior_m
        self.white_ceiling_m = float(ceiling) * max(self.white_prior_m or 0.0, self.prior_sigma_m)
        self.sensor_var = float(sensor_sigma_m) ** 2 + float(mismatch_m) ** 2

    @property
    def corr_m(self) -> float | None:
        """The learned correlation length, m (None: not learned)."""
        return None if self.log_len is None else math.exp(self.log_len)

    @property
    def white_m(self) -> float | None:
        """The learned white map error (the likelihood's ``map_sigma_m``), m (None: not learned)."""
        return None if self.white_var is None else math.sqrt(self.white_var)

    @property
    def sigma_m(self) -> float:
        """The learned RMS of the map error, m."""
        return math.exp(0.5 * self.log_var)

    def read(self, moments: np.ndarray, projections: np.ndarray | None = None, spectrum: np.ndarray | None = None,
             sigma_m: float | None = None, dropped_var: float = 0.0) -> tuple[float, float | None, float | None] | None:
        """One reading of :func:`~warptan.kernels.filter.resampling.map_error_moments_kernel`'s row (Σw, NIS, ratio,
        modes used, var north, var east) and, to learn the length and the white error, :func:`~warptan.kernels.
        filter.resampling.mode_projection_kernel`'s row (whitened by ``sigma_m``, the per-point σ it used) with the
        table's :meth:`~warptan.sensing.likelihood.Likelihood.mode_spectrum` at :attr:`LENGTH_FACTORS` times its
        length. Returns ``(RMS, correlation length, white error)`` to apply when any moved (the RMS by 10 %, the length
        by 20 %, the white error by 10 % of the per-point σ's map part) since last applied (the length and the white
        error None when not learned), else None. ``dropped_var`` (m²): the energy a point's residual holds from the
        modes the table drops (the stated error's structure beyond :data:`~warptan.kernels.likelihood.MAX_MODES`
        modes, :meth:`~warptan.sensing.likelihood.Likelihood.error_modes`' ``truncation_unit`` unshared), which is
        the statement's, not white error."""
        _sw, nis, ratio, used, var_n, var_e = (float(v) for v in moments[:6])
        spread = math.sqrt(max(var_n, 0.0) + max(var_e, 0.0))
        if spread > max(self.converged_m, 3.0 * self.sigma_m) or not (np.isfinite(nis) and nis <= self.nis_max):
            return None
        ruled = used >= 1 and np.isfinite(ratio) and ratio > 0
        if ruled:  # (no mode the scan rules: the RMS and the white error keep, the length reads)
            gain = max(self.gain, 1.0 / (self.PRIOR_READINGS + self.readings + 1))
            step = gain * math.log(min(max(ratio, 0.25), 4.0))
            lo, hi = 2.0 * math.log(self.floor_m), 2.0 * math.log(self.ceiling_m)
            self.log_var = min(max(self.log_var + step, lo), hi)
            self.readings += 1
        moved = False
        if self.log_len is not None and projections is not None and spectrum is not None:
            factor = self.length_factor(projections, spectrum)
            if factor is not None:
                target = math.log(self.applied_corr_m * factor)
                self.log_len = min(max(self.log_len + self.length_gain * (target - self.log_len), self.len_bounds[0]),
                                   self.len_bounds[1])
                moved = abs(self.log_len - math.log(self.applied_corr_m)) > math.log(1.2)
        white_moved = False
        if ruled and self.white_var is not None and projections is not None and sigma_m is not None:
            white_moved = self._read_white(np.asarray(projections, dtype=np.float64), float(sigma_m),
                                           float(dropped_var))
        if moved or white_moved or abs(math.log(self.sigma_m / self.applied_sigma_m)) > math.log(1.1):
            self.applied_sigma_m = self.sigma_m
            if moved:
                self.applied_corr_m = self.corr_m
            if white_moved:
                self.applied_white_m = self.white_m
            return self.applied_sigma_m, self.applied_corr_m, self.applied_white_m
        return None

    def _read_white(self, projections: np.ndarray, sigma_m: float, dropped_var: float = 0.0) -> bool:
        """Step the white error's variance with one reading's energy outside the modes; True when it moved by more
        than a tenth of the map part's scale since last applied."""
        sw = projections[PROJ_HF_W]
        if not (np.isfinite(sw) and sw > 0 and np.isfinite(projections[PROJ_HF])):
            return False
        energy = projections[PROJ_HF] / sw * sigma_m * sigma_m  # m²
        prior = self.white_prior_m**2
        target = prior
        if energy > self.WHITE_EXCESS * (self.sensor_var + dropped_var + prior):
            target = energy - self.sensor_var - dropped_var
        self.white_var = min(max(self.white_var + self.length_gain * (target - self.white_var), prior),
                             self.white_ceiling_m**2)
        scale = max(self.applied_white_m, 0.1 * math.sqrt(max(self.sensor_var, 1e-6)))
        return abs(self.white_m - self.applied_white_m) > 0.1 * scale

    _S_GRID = np.exp(np.linspace(math.log(0.05), math.log(400.0), 48))
    _C_GRID = np.exp(np.linspace(math.log(0.02), math.log(2.0), 12))

    def length_factor(self, projections: np.ndarray, spectrum: np.ndarray) -> float | None:
        """The factor of :attr:`LENGTH_FACTORS` under which the modes' raw second moments (``projections``: Σ w p_i²
        per mode, then Σ w) are likeliest, ``E[p_i²] = c + s d_i(L)`` with ``(c, s)`` fitted on grids; None with
        fewer than four modes or no weight."""
        projections = np.asarray(projections, dtype=np.float64)
        n = spectrum.shape[1]
        sw = projections[PROJ_SW]
        if not (np.isfinite(sw) and sw > 0):
            return None
        second = projections[:n] / sw
        held = np.all(spectrum > 0, axis=0)
        use = held & np.isfinite(second)
        if np.count_nonzero(use) < 4:
            return None
        if self._terms is None or self._terms[0] is not spectrum or not np.array_equal(use, held):
            d = spectrum[:, use]
            var = self._C_GRID[None, :, None, None] + self._S_GRID[None, None, :, None] * d[:, None, None, :]
            self._terms = (spectrum if np.array_equal(use, held) else None, np.log(var).sum(axis=3), 1.0 / var)
        _key, log_sum, inverse = self._terms  # (the grids' terms of one table's spectrum, kept while it is in use)
        nll = (log_sum + inverse @ second[use]).reshape(len(spectrum), -1).min(axis=1)
        return float(self.LENGTH_FACTORS[int(np.argmin(nll))])
