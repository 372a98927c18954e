"""Device resolution: a device is chosen once (``None`` = Warp's default) and then follows the data; host-device
copies that do not hold the host (pinned staging, :class:`HostEcho`)."""

from __future__ import annotations

import os

import numpy as np
import warp as wp

AUTO = "auto"
"""The device the CLI and the API default to: a CUDA GPU when Warp sees one, else the CPU (:func:`auto_device`)."""


def auto_device(device=AUTO, cluster: bool = False):
    """``device`` with :data:`AUTO` decided: ``"cuda:0"`` when Warp sees a CUDA device (``"cuda"`` for a Ray
    campaign, ``cluster``: each of its tasks gets one GPU), else ``"cpu"``. Any other value is returned as given
    (``"cpu"`` keeps the CPU where a GPU is present)."""
    if isinstance(device, str) and device == AUTO:
        if wp.is_cuda_available():
            return "cuda" if cluster else "cuda:0"
        return "cpu"
    return device


def device_words(given, chosen) -> str:
    """How a run names its device in its first line: ``cuda:0 (auto: a CUDA GPU was found)``, ``cpu (auto: no CUDA
    GPU)``, or the device as given."""
    if given != AUTO:
        return str(chosen)
    return f"{chosen} (auto: " + ("a CUDA GPU was found; --device cpu forces the CPU)" if str(chosen).startswith(
        "cuda") else "no CUDA GPU)")


def resolve_device(device=None) -> wp.Device:
    """Return the Warp device for ``device`` ("cpu", "cuda", "cuda:0", :data:`AUTO`, a Device, or None).

    Raises:
        ValueError: the name is not a device Warp knows, or names a CUDA device that is not present.
    """
    device = auto_device(device)
    if isinstance(device, wp.Device):
        return device
    if device is not None and not isinstance(device, str):
        raise ValueError(f"device must be a name such as 'cpu' or 'cuda:0', got {device!r}")
    try:
        return wp.get_device(device)
    except (RuntimeError, ValueError) as err:
        present = ", ".join(d.alias for d in wp.get_devices())
        raise ValueError(f"unknown or absent device {device!r} (present: {present}): {err}") from None


def upload(array: wp.array, values) -> None:
    """``array.assign(values)``; on the CPU written through the array's own memory (``assign`` makes a temporary
    array and copies: ~10 µs, several times a filter step). ``values`` has the array's shape (NumPy casts its dtype)."""
    if array.device.is_cpu:
        array.numpy()[...] = values
    else:
        array.assign(values)


class Uploads:
    """Small host-to-device copies that do not hold the host (a measurement's ranges each step): on CUDA each name has
    two pinned host buffers used in turn; the values are written into one and its copy is queued on the stream (an
    asynchronous copy, behind the device work already queued, which a pageable ``assign`` would wait for), and a buffer
    is written again only once its last copy is done (an event recorded after it). On the CPU :func:`upload`."""

    def __init__(self):
        self._slots: dict = {}
        self._held: list | None = None
        self._buffers: dict | None = None

    def hold(self, buffers: dict) -> None:
        """Until :meth:`release`, on CUDA: each put writes a pinned buffer kept in ``buffers`` (the caller's dict, one
        per use of them: a filter's staging set) and holds its copy, and :meth:`later` holds other device work, for
        the caller to queue (in its graph, whose copy nodes read these buffers when replayed). The caller owns the
        buffers and writes them again only once the work queued from them is done."""
        self._held, self._buffers = [], buffers

    def later(self, fn) -> bool:
        """Hold ``fn`` (device work after the held copies) while holding; False (the caller runs it now) if not."""
        if self._held is None:
            return False
        self._held.append(fn)
        return True

    def release(self) -> list:
        """The held copies and work, in order (callables), and stop holding."""
        held, self._held, self._buffers = self._held or [], None, None
        return held

    def put(self, name: str, array: wp.array, values) -> None:
        """Copy ``values`` (the array's shape; NumPy casts the dtype) into ``array`` through the buffers of ``name``."""
        if array.device.is_cpu:
            upload(array, values)
            return
        if self._held is not None:
            # a buffer per (name, shape), kept: a graph that copies from it holds it (a new shape is a new buffer,
            # and the caller's arrays of that shape are new too: its graphs are re-captured anyway)
            key = (name, array.shape, array.dtype, array.device.alias)
            kept = self._buffers.get(key)
            if kept is None:
                buf = wp.empty(array.shape, dtype=array.dtype, device="cpu", pinned=True)
                kept = self._buffers[key] = (buf, buf.numpy())
            buf, view = kept
            view[...] = values
            self._held.append(lambda: wp.copy(array, buf))
            return
        slot = self._slots.get(name)
        if slot is None or slot["key"] != (array.shape, array.dtype, array.device):
            bufs = [wp.empty(array.shape, dtype=array.dtype, device="cpu", pinned=True) for _ in range(2)]
            slot = self._slots[name] = {"key": (array.shape, array.dtype, array.device), "bufs": bufs,
                                        "views": [b.numpy() for b in bufs], "next": 0,
                                        "events": [wp.Event(array.device), wp.Event(array.device)],
                                        "used": [False, False]}
        k = slot["next"]
        if slot["used"][k]:
            wp.synchronize_event(slot["events"][k])  # the copy two puts ago has read this buffer
        slot["views"][k][...] = values
        wp.copy(array, slot["bufs"][k])
        wp.get_stream(array.device).record_event(slot["events"][k])
        slot["used"][k] = True
        slot["next"] = k ^ 1


WARP_OUTPUT_ENV = "WARPTAN_WARP_OUTPUT"
"""Set to 1 to keep Warp's own output (its start-up banner, "Module … load" lines) when warptan is imported."""


_BLAS = None  # (one_blas_thread's controller, made on first use)


def one_blas_thread():
    """A context in which NumPy's BLAS/LAPACK runs on one thread (``threadpoolctl``), for the small dense
    problems the host solves behind a filter's updates (the map-error modes' eigendecomposition of a scan's few
    hundred points, their sharing along the track). A multi-threaded OpenBLAS wakes its pool for a 100 × 100
    ``eigh`` and, beside the threads that launch the device's work, spins: measured on the 2-core VM with another
    process running, 130 ms for S8's first table against 0.5 ms on one thread (the same matrix,
    ``OPENBLAS_NUM_THREADS=1``); S8 learned over a 5 m / 1 km world (120 s, CPU) waited 0.27 s a run for its tables,
    0.001 s on one thread. On an H200 host (``scripts/profile_update_host.py``, before this) the scan's staging, where
    the wait shows, took 117–280 µs an update against 22 µs over the map. The limit is process-wide while the context
    is open (BLAS has no per-thread setting); the calls inside give the same results at any thread count up to
    rounding."""
    global _BLAS
    if _BLAS is None:
        from threadpoolctl import ThreadpoolController

        _BLAS = ThreadpoolController()
    return _BLAS.limit(limits=1, user_api="blas")


def quiet_warp() -> None:
    """Silence Warp's start-up banner and per-module load messages (done when warptan's device layer is imported,
    unless ``$WARPTAN_WARP_OUTPUT`` is 1: the API prints nothing of its own on stdout)."""
    wp.config.quiet = True
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)


if os.environ.get(WARP_OUTPUT_ENV, "") != "1":
    quiet_warp()


class HostEcho:
    """Device arrays copied to the host behind the device's work, for host decisions that may lag (CUDA): each
    :meth:`queue` copies them into one of two pinned buffers in turn and records an event; :meth:`read` returns the
    copy queued before the last one (waiting for its event, long past in a pipelined filter), so the host never
    waits for the work it just queued. Before two copies, and on the CPU (where the arrays are current and reading
    them costs nothing), it reads the arrays themselves. A ``tag`` given to :meth:`queue` (host values that go with
    the copy, e.g. the table it was computed with) is :attr:`tag` after the :meth:`read` that returns that copy."""

    def __init__(self, arrays: list[wp.array]):
        self.arrays = arrays
        self.device = arrays[0].device
        self._queued = 0
        self._tags = [None, None]
        self.tag = None
        """The tag queued with the copy the last :meth:`read` returned."""
        if self.device.is_cuda:
            self._host = [[wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=True) for a in arrays]
                          for _ in range(2)]
            self._events = [wp.Event(self.device), wp.Event(self.device)]

    def queue(self, tag=None) -> None:
        slot = self._queued % 2
        self._tags[slot] = tag
        if not self.device.is_cuda:
            self._queued += 1
            return
        for host, a in zip(self._host[slot], self.arrays, strict=True):
            wp.copy(host, a)
        wp.get_stream(self.device).record_event(self._events[slot])
        self._queued += 1

    def read(self) -> list[np.ndarray]:
        if not self.device.is_cuda or self._queued < 2:
            self.tag = self._tags[(self._queued - 1) % 2]  # (the last queued: the arrays are its values)
            return [a.numpy() for a in self.arrays]
        slot = self._queued % 2  # the copy before the last one
        self.tag = self._tags[slot]
        wp.synchronize_event(self._events[slot])
        return [h.numpy().copy() for h in self._host[slot]]
