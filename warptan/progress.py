"""A progress bar: tqdm's where it is installed, else a stand-in that shows nothing (a machine with only the core,
numpy and warp)."""

from __future__ import annotations


class NoProgress:
    """Stands in for tqdm where it is not installed."""

    def __init__(self, *_, **__):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *_):
        return False

    def update(self, *_):
        pass

    def set_description(self, *_):
        pass


def progress_bar(total: int, unit: str, disable: bool = False):
    """tqdm over ``total`` ``unit`` s on stderr (resizing with the terminal), or :class:`NoProgress`."""
    try:
        from tqdm import tqdm
    except ModuleNotFoundError:
        return NoProgress()
    return tqdm(total=total, unit=unit, disable=disable, dynamic_ncols=True)
