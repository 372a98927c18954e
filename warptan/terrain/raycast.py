"""Ray casting launchers: ``wt.raycast`` for arbitrary rays and the per-pose pattern form (design notes §5, §9).

Backends (see :mod:`warptan.kernels.raycast` for what each does and when it returns NaN):

* ``"mesh"`` — ``wp.mesh_query_ray`` on the terrain's SAH-built ``wp.Mesh`` (the paper's ray–triangle cast);
* ``"dda"`` — exact heightfield traversal, same triangles, the fastest;
* ``"bisection"`` — the paper's CPU variant (march, then bisection).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warptan.checks import FLOAT32_MAX, FilterError
from warptan.device import resolve_device
from warptan.kernels import raycast as kray

BACKENDS = {"mesh": kray.BACKEND_MESH, "dda": kray.BACKEND_DDA, "bisection": kray.BACKEND_BISECTION}


@dataclass(frozen=True)
class RayCaster:
    """A backend choice with its parameters.

    Attributes:
        backend: "mesh", "dda" or "bisection".
        step_m: Bisection march step, horizontal metres; None = half the smaller post spacing.
        n_bisect: Bisection halvings after the march (resolution ``step / 2**n_bisect``).
    """

    backend: str = "dda"
    step_m: float | None = None
    n_bisect: int = 16

    def __post_init__(self):
        check_backend(self.backend)
        if self.step_m is not None and not (np.isfinite(self.step_m) and self.step_m > 0):
            raise FilterError(f"bisection step_m must be a positive number of metres, got {self.step_m!r}")
        if not (isinstance(self.n_bisect, (int, np.integer)) and 0 <= self.n_bisect <= 40):
            raise FilterError(f"n_bisect must be an integer in [0, 40], got {self.n_bisect!r}")

    def launch_args(self, terrain, device) -> list:
        """The leading kernel arguments (grid, mesh id, backend code, step, halvings) for ``device``."""
        mesh_id = terrain.mesh(device).id if self.backend == "mesh" else wp.uint64(0)
        step = self.step_m if self.step_m is not None else 0.5 * min(terrain.dn, terrain.de)
        return [terrain.grid(device), mesh_id, BACKENDS[self.backend], float(step), int(self.n_bisect)]


def check_backend(backend: str) -> str:
    """Return ``backend`` if it names a ray-cast backend, else raise a ValueError listing the valid ones."""
    if backend not in BACKENDS:
        raise FilterError(f"unknown ray-cast backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    return backend


def _as_vec3_array(name: str, value, device) -> wp.array:
    if isinstance(value, wp.array):
        if value.dtype == wp.vec3 and value.ndim == 1:
            return value
        if value.dtype == wp.float32 and value.ndim == 2 and value.shape[1] == 3:
            return wp.array(ptr=value.ptr, dtype=wp.vec3, shape=value.shape[0], device=value.device, copy=False)
        raise FilterError(f"{name} must be a (K, 3) array of float32 or (K,) of vec3, got {value.dtype} {value.shape}")
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise FilterError(f"{name} must have shape (K, 3), got {arr.shape}")
    return wp.array(arr.astype(np.float32), dtype=wp.vec3, device=device)


def _check_rays(origins, dirs) -> None:
    """Validate host copies of the rays (done once per public call, not in the filter's hot path)."""
    o = origins.numpy() if isinstance(origins, wp.array) else np.asarray(origins, dtype=np.float64)
    d = dirs.numpy() if isinstance(dirs, wp.array) else np.asarray(dirs, dtype=np.float64)
    for name, a in (("origins_n", o), ("dirs_n", d)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise FilterError(f"{name} must have shape (K, 3), got {a.shape}")
    if len(o) != len(d):
        raise FilterError(f"origins and dirs must have the same number of rays, got {len(o)} and {len(d)}")
    with np.errstate(invalid="ignore"):
        bad = ~(np.abs(o) <= FLOAT32_MAX).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise FilterError(f"{bad.sum()} ray origins are not finite in float32 (the device's precision; first at index "
                         f"{k}: {o[k].tolist()})")
    norm = np.linalg.norm(d, axis=1)
    bad = ~np.isfinite(norm) | (norm < 1e-6)
    if bad.any():
        raise FilterError(
            f"{bad.sum()} ray directions are zero-length or not finite (first at index {int(np.argmax(bad))})"
        )


def raycast(terrain, origins_n, dirs_n, backend: str = "dda", device=None, *, step_m: float | None = None,
            n_bisect: int = 16, out: wp.array | None = None):
    """Cast K rays against the terrain.

    Args:
        terrain: A :class:`~warptan.terrain.grid.Terrain`.
        origins_n: (K, 3) NED origins in m (NumPy, or a Warp array of vec3 / (K, 3) float32).
        dirs_n: (K, 3) directions in the NED frame (normalised here; zero-length is an error).
        backend: "dda", "mesh" or "bisection".
        device: Warp device for NumPy inputs (default: Warp's default); Warp inputs run on their device.
        step_m, n_bisect: Bisection parameters (see :class:`RayCaster`).
        out: Optional (K,) float32 Warp output.

    Returns:
        (K,) ranges in m, NaN = no hit: a NumPy float64 array for NumPy inputs, else a Warp array.
    """
    caster = RayCaster(backend, step_m, n_bisect)
    warp_in = isinstance(origins_n, wp.array) or isinstance(dirs_n, wp.array)
    if warp_in:
        if not (isinstance(origins_n, wp.array) and isinstance(dirs_n, wp.array)):
            raise FilterError("origins_n and dirs_n must both be Warp arrays or both NumPy arrays")
        if origins_n.device != dirs_n.device:
            raise FilterError(f"origins_n is on {origins_n.device} but dirs_n on {dirs_n.device}")
        device = origins_n.device
    else:
        device = resolve_device(device)
    _check_rays(origins_n, dirs_n)
    o = _as_vec3_array("origins_n", origins_n, device)
    d = _as_vec3_array("dirs_n", dirs_n, device)
    if out is None:
        out = wp.empty(o.shape[0], dtype=wp.float32, device=device)
    elif out.shape != (o.shape[0],) or out.device != device or out.dtype != wp.float32:
        raise FilterError(f"out must be a ({o.shape[0]},) float32 array on {device}")
    if o.shape[0]:
        wp.launch(kray.raycast_kernel, dim=o.shape[0], inputs=[*caster.launch_args(terrain, device), o, d],
                  outputs=[out], device=device)
    return out if warp_in else out.numpy().astype(np.float64)


def raycast_pattern(terrain, pos_n: wp.array, quat_nb: wp.array, dirs_s: wp.array, caster: RayCaster,
                    out: wp.array | None = None, record: bool = False):
    """Cast the M sensor-frame directions from each of N poses: (N, M) ranges in m (NaN = no hit).

    Args:
        terrain: The map.
        pos_n: (N,) vec3 NED positions, m.
        quat_nb: (N,) vec4 attitudes [w, x, y, z].
        dirs_s: (M,) vec3 unit directions in the sensor frame (FRD).
        caster: Backend and parameters.
        out: Optional (N, M) float32 output.
        record: Return the launch as a ``warp.Launch`` (run once here) to be replayed on the same arrays.
    """
    device = pos_n.device
    check_same_device(pos_n=pos_n, quat_nb=quat_nb, dirs_s=dirs_s)
    if quat_nb.shape[0] != pos_n.shape[0]:
        raise FilterError(f"pos_n has {pos_n.shape[0]} poses but quat_nb {quat_nb.shape[0]}")
    shape = (pos_n.shape[0], dirs_s.shape[0])
    if out is None:
        out = wp.empty(shape, dtype=wp.float32, device=device)
    cmd = wp.launch(kray.raycast_pattern_kernel, dim=shape, inputs=[*caster.launch_args(terrain, device), pos_n,
                    quat_nb, dirs_s], outputs=[out], device=device, record_cmd=record)
    if record:
        cmd.launch()
        return cmd
    return out


def check_same_device(**arrays: wp.array) -> wp.Device:
    """Raise a ValueError naming the arrays when they are not all on one device; return that device."""
    devices = {name: a.device for name, a in arrays.items()}
    first = next(iter(devices.values()))
    if any(d is not first for d in devices.values()) and len({str(d) for d in devices.values()}) > 1:
        listing = ", ".join(f"{name} on {d}" for name, d in devices.items())
        raise FilterError(f"arrays must be on one device, got {listing}")
    return first
