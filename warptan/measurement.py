"""Measurement models: one log-likelihood per particle from its hypothetical pose (paper eqs. 14–17, SPEC §5).

Each model takes the particles' poses on the device — positions (N,) vec3 NED in m and attitudes (N,)
vec4 [w, x, y, z] — and the received measurement, fills an (N, M) residual array with N×M threads, and
reduces it per particle with one kernel (N threads): no Python loop over particles or points.

* :class:`RaycastModel` — predicted ranges by ray casting (any backend), paper error of eq. 15;
* :class:`SlidingModel` — the sliding grid, no ray cast, paper error of eq. 16;
* :class:`AltimeterModel` — radar altimeter with barometric altitude, eq. 17.

The likelihood is the paper's Gaussian on the scalar error, or a per-point Gaussian / Student-t over
all valid residuals (:class:`Likelihood`, :mod:`warptan.kernels.likelihood` for the exact formulas).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warptan.kernels import likelihood as klik
from warptan.kernels import raycast as kray
from warptan.kernels import sliding as kslide
from warptan.parallel import launch_rows, rows_of
from warptan.raycast import RayCaster, check_same_device
from warptan.sensors import AltimeterReading, PointCloud

LIKELIHOODS = {"paper": klik.LIK_PAPER, "gaussian": klik.LIK_GAUSS, "student_t": klik.LIK_STUDENT}


@dataclass(frozen=True)
class Likelihood:
    """How residuals become a log-likelihood.

    Attributes:
        kind: "paper" (Gaussian on the scalar error), "gaussian" or "student_t" (per point).
        r_err: Variance of the paper's scalar error, m².
        sigma_m: Per-point residual scale σ, m.
        nu: Student-t degrees of freedom.
        outlier_sigmas: A point the particle cannot predict (off the map, nodata, no hit) scores as a
            residual of this many σ; a particle with no valid point gets ``-0.5 outlier_sigmas²`` (paper).
    """

    kind: str = "paper"
    r_err: float = 1.0
    sigma_m: float = 1.0
    nu: float = 4.0
    outlier_sigmas: float = 4.0

    def __post_init__(self):
        if self.kind not in LIKELIHOODS:
            raise ValueError(f"unknown likelihood {self.kind!r}; choose one of {', '.join(LIKELIHOODS)}")
        for name in ("r_err", "sigma_m", "nu", "outlier_sigmas"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"likelihood {name} must be a positive number, got {value!r}")


@dataclass
class ModelOutput:
    """Per-particle results of one measurement update (device arrays, reused between calls)."""

    loglik: wp.array
    """(N,) float32 log-likelihood (finite for every particle)."""
    error_m: wp.array
    """(N,) float32 paper error in m (NaN for a particle with no valid point)."""
    n_valid: wp.array
    """(N,) int32 number of points the particle could predict."""
    residual_m: wp.array
    """(N, M) float32 residuals in m (NaN = invalid)."""
    n_received: int
    """Number of valid received points (host knows it without a sync)."""

    @property
    def all_points_invalid(self) -> bool:
        """Warning flag: no received point was valid, every particle got the same (no-information) score."""
        return self.n_received == 0


class MeasurementModel:
    """Base class: buffers, validation and the reduction; subclasses fill the residuals."""

    name = "base"
    err_kind = klik.ERR_MEAN_ABS

    def __init__(self, terrain, likelihood: Likelihood | None = None):
        self.terrain = terrain
        self.likelihood = likelihood or Likelihood()
        self._buffers: dict = {}

    def _outputs(self, device, n: int, m: int) -> ModelOutput:
        key = (str(device), n, m)
        if key not in self._buffers:
            self._buffers = {key: ModelOutput(
                loglik=wp.empty(n, dtype=wp.float32, device=device),
                error_m=wp.empty(n, dtype=wp.float32, device=device),
                n_valid=wp.empty(n, dtype=wp.int32, device=device),
                residual_m=wp.empty((n, m), dtype=wp.float32, device=device),
                n_received=0,
            )}
        return self._buffers[key]

    def _reduce(self, out: ModelOutput, point_ok: wp.array, axis_w: wp.array, device) -> ModelOutput:
        lk = self.likelihood
        consts = [self.err_kind, LIKELIHOODS[lk.kind], float(lk.r_err), float(lk.sigma_m), float(lk.nu),
                  float(lk.outlier_sigmas)]
        launch_rows(klik.reduce_loglik_kernel, out.loglik.shape[0],
                    lambda a, b: ([rows_of(out.residual_m, a, b), point_ok, axis_w, *consts],
                                  [rows_of(out.error_m, a, b), rows_of(out.loglik, a, b),
                                   rows_of(out.n_valid, a, b)]), device,
                    row_cost=out.residual_m.shape[1])
        return out

    @staticmethod
    def _check_poses(pos_n: wp.array, quat_nb: wp.array):
        device = check_same_device(pos_n=pos_n, quat_nb=quat_nb)
        if pos_n.dtype != wp.vec3 or quat_nb.dtype != wp.vec4:
            raise ValueError(f"poses must be vec3 positions and vec4 quaternions, got {pos_n.dtype}, {quat_nb.dtype}")
        if pos_n.shape != quat_nb.shape:
            raise ValueError(f"pos_n has shape {pos_n.shape} but quat_nb {quat_nb.shape}")
        return device


class _PointCloudModel(MeasurementModel):
    def evaluate(self, pos_n: wp.array, quat_nb: wp.array, cloud: PointCloud) -> ModelOutput:
        """Log-likelihood of the received ``cloud`` for each particle pose."""
        if not isinstance(cloud, PointCloud):
            raise ValueError(f"{self.name} model needs a PointCloud, got {type(cloud).__name__}")
        device = self._check_poses(pos_n, quat_nb)
        dev = cloud.on_device(device)
        out = self._outputs(device, pos_n.shape[0], len(cloud.ranges_m))
        out.n_received = int(cloud.valid.sum())
        self._residuals(pos_n, quat_nb, dev, out.residual_m, device)
        return self._reduce(out, dev["point_ok"], dev["axis_w"], device)


class RaycastModel(_PointCloudModel):
    """Predict each point by casting the pattern ray from the particle's pose (paper eq. 6, 15).

    Args:
        terrain: The map DEM.
        likelihood: See :class:`Likelihood`.
        caster: Backend ("dda", "mesh", "bisection") and its parameters.
    """

    name = "raycast"
    err_kind = klik.ERR_AXES

    def __init__(self, terrain, likelihood: Likelihood | None = None, caster: RayCaster | None = None):
        super().__init__(terrain, likelihood)
        self.caster = caster or RayCaster("dda")

    def _residuals(self, pos_n, quat_nb, dev, residual_out, device):
        lead = self.caster.launch_args(self.terrain, device)
        launch_rows(kray.raycast_residual_kernel, residual_out.shape[0],
                    lambda a, b: ([*lead, rows_of(pos_n, a, b), rows_of(quat_nb, a, b), dev["dirs"], dev["ranges"]],
                                  [rows_of(residual_out, a, b)]),
                    device, cols=residual_out.shape[1], row_cost=20)


class SlidingModel(_PointCloudModel):
    """The sliding grid: read the map under each received point placed with the particle's pose (eq. 14, 16).

    Args:
        terrain: The map DEM.
        likelihood: See :class:`Likelihood`.
        surface: Sample the triangulated surface instead of the bilinear height (the surface ray casts see).
    """

    name = "sliding"
    err_kind = klik.ERR_MEAN_ABS

    def __init__(self, terrain, likelihood: Likelihood | None = None, surface: bool = False):
        super().__init__(terrain, likelihood)
        self.surface = bool(surface)

    def _residuals(self, pos_n, quat_nb, dev, residual_out, device):
        grid = self.terrain.grid(device)
        surface = int(self.surface)
        launch_rows(kslide.sliding_residual_kernel, residual_out.shape[0],
                    lambda a, b: ([grid, surface, rows_of(pos_n, a, b), rows_of(quat_nb, a, b), dev["points"]],
                                  [rows_of(residual_out, a, b)]),
                    device, cols=residual_out.shape[1], row_cost=2)


class AltimeterModel(MeasurementModel):
    """Radar altimeter with barometric altitude: ``a^_i = h_baro - h(p_i)`` (paper eq. 8, 17).

    With a barometer the altimeter residual does not depend on a particle's altitude, so the barometer is
    also used as what it is, a measurement of altitude: each particle's log-likelihood gets
    ``-0.5 (h_baro + p_i,z)² / baro_sigma_m²`` (without it the vertical error would be unobservable).

    Args:
        terrain: The map DEM.
        likelihood: See :class:`Likelihood`.
        surface: Sample the triangulated surface instead of the bilinear height.
        use_baro: False predicts with each particle's own altitude ``-p_i,z`` (no barometer).
        baro_sigma_m: Barometer noise σ for its altitude term, m.
    """

    name = "altimeter"
    err_kind = klik.ERR_SIGNED

    def __init__(self, terrain, likelihood: Likelihood | None = None, surface: bool = False, use_baro: bool = True,
                 baro_sigma_m: float = 1.0):
        super().__init__(terrain, likelihood)
        if not (np.isfinite(baro_sigma_m) and baro_sigma_m > 0):
            raise ValueError(f"baro_sigma_m must be a positive number of metres, got {baro_sigma_m!r}")
        self.surface = bool(surface)
        self.use_baro = bool(use_baro)
        self.baro_sigma_m = float(baro_sigma_m)
        self._consts: dict[str, tuple[wp.array, wp.array, wp.array]] = {}

    def evaluate(self, pos_n: wp.array, quat_nb: wp.array, reading: AltimeterReading) -> ModelOutput:
        """Log-likelihood of the altimeter ``reading`` for each particle (attitudes are not used)."""
        if not isinstance(reading, AltimeterReading):
            raise ValueError(f"altimeter model needs an AltimeterReading, got {type(reading).__name__}")
        device = self._check_poses(pos_n, quat_nb)
        key = str(device)
        if key not in self._consts:
            self._consts[key] = (wp.array([0], dtype=wp.int32, device=device),
                                 wp.array([1], dtype=wp.int32, device=device),
                                 wp.array([wp.vec3(1.0, 1.0, 1.0)], dtype=wp.vec3, device=device))
        axis_w = self._consts[key][2]
        out = self._outputs(device, pos_n.shape[0], 1)
        valid = reading.valid and (not self.use_baro or bool(np.isfinite(reading.baro_alt_m)))
        point_ok = self._consts[key][int(valid)]
        out.n_received = int(valid)
        if valid:
            wp.launch(kslide.altimeter_residual_kernel, dim=pos_n.shape[0],
                      inputs=[self.terrain.grid(device), int(self.surface), int(self.use_baro), pos_n,
                              float(reading.range_m), float(reading.baro_alt_m)], outputs=[out.residual_m],
                      device=device)
        else:
            out.residual_m.fill_(float("nan"))
        self._reduce(out, point_ok, axis_w, device)
        if self.use_baro and np.isfinite(reading.baro_alt_m):
            wp.launch(kslide.add_baro_loglik_kernel, dim=pos_n.shape[0],
                      inputs=[pos_n, float(reading.baro_alt_m), 1.0 / self.baro_sigma_m**2], outputs=[out.loglik],
                      device=device)
        return out


MODELS = {"raycast": RaycastModel, "sliding": SlidingModel, "altimeter": AltimeterModel}


def make_model(name: str, terrain, likelihood: Likelihood | None = None, backend: str = "dda",
               **kwargs) -> MeasurementModel:
    """Build a model by name ("raycast", "sliding", "altimeter"); ``backend`` applies to raycast."""
    if name not in MODELS:
        raise ValueError(f"unknown measurement model {name!r}; choose one of {', '.join(MODELS)}")
    if name == "raycast":
        kwargs.setdefault("caster", RayCaster(backend))
    return MODELS[name](terrain, likelihood, **kwargs)
