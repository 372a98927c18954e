"""Device resolution: a device is chosen once (``None`` = Warp's default) and then follows the data."""

from __future__ import annotations

import warp as wp


def resolve_device(device=None) -> wp.Device:
    """Return the Warp device for ``device`` ("cpu", "cuda", "cuda:0", a Device, or None).

    Raises:
        ValueError: the name is not a device Warp knows, or names a CUDA device that is not present.
    """
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


def quiet_warp() -> None:
    """Silence Warp's start-up banner and per-module load messages (for the CLI, scripts and tests)."""
    wp.config.quiet = True
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
