"""Argument checks shared by the modules: one message format for bad numbers."""

from __future__ import annotations

import math


def check_positive(value, name: str, error: type[Exception] = ValueError) -> float:
    """``value`` as a float if it is a finite number > 0, else ``error`` naming ``name`` and the value."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise error(f"{name} must be a positive number, got {value!r}") from None
    if not (math.isfinite(number) and number > 0):
        raise error(f"{name} must be a positive number, got {value!r}")
    return number
