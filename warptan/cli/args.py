"""Argument types and defaults the command line and the benchmark scripts share (a bad value: one line, exit 2)."""

from __future__ import annotations

import argparse
import math
import sys

DEFAULT_TERRAIN = "synthetic:rugged"


def count_arg(text: str) -> int:
    """argparse type: a whole number ≥ 1 (the command line's and the scripts' counts)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number ≥ 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be ≥ 1, got {value}")
    return value


def text_arg(text: str) -> str:
    """argparse type: a name or path that is not empty or blank (an empty ``--terrain ""`` silently meant the
    scenario's own DEM; ``--out`` has the output folder's own check)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"must not be empty, got {text!r}")
    if "\0" in text:
        raise argparse.ArgumentTypeError(f"must not hold a NUL character, got {text!r}")
    return text


def seed_arg(text: str) -> int:
    """argparse type: a seed, a whole number in [0, 2**63)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number ≥ 0, got {text!r}") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**63), got {value}")
    return value


def number_arg(minimum: float, strict: bool):
    """argparse type: a finite number > minimum (strict) or ≥ minimum."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
        if not math.isfinite(value) or value < minimum or (strict and value == minimum):
            raise argparse.ArgumentTypeError(f"must be a finite number {'>' if strict else '≥'} {minimum:g}, "
                                             f"got {text!r}")
        return value
    return parse


def _relief_arg(text: str):
    """argparse type: 'auto' or a finite number (checked with the scenario)."""
    return "auto" if text.strip().lower() == "auto" else _finite(text)


def _finite(text: str) -> float:
    """argparse type: any finite number."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")  # (it said "≥ -inf")
    return value


def heading_arg(text: str) -> float:
    """argparse type: a heading in degrees from north, within ±360 (1e300 was taken, its sine meaningless)."""
    value = _finite(text)
    if abs(value) > 360.0:
        raise argparse.ArgumentTypeError(f"must be a heading in degrees within ±360, got {text!r}")
    return value


def script_inputs(prog: str, devices: list[str], terrain_spec: str):
    """For the benchmark scripts: silence Warp, check the device names and load the terrain; a bad name or
    terrain prints one line and exits with status 2 (no traceback)."""
    from warptan.device import quiet_warp, resolve_device
    from warptan.terrain.grid import Terrain

    quiet_warp()
    try:
        for d in devices:
            resolve_device(d)
        return Terrain.load(terrain_spec)
    except (ValueError, FileNotFoundError) as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
