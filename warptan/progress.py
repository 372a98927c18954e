"""A progress bar: tqdm's where it is installed, else a stand-in that shows nothing (a machine with only the core,
numpy and warp)."""

from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager


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

    def set_postfix_str(self, *_, **__):
        pass

    @staticmethod
    def write(text: str) -> None:
        print(text, file=sys.stderr)


def progress_bar(total: int, unit: str, disable: bool = False):
    """tqdm over ``total`` ``unit`` s on stderr (resizing with the terminal), or :class:`NoProgress`."""
    try:
        from tqdm import tqdm
    except ModuleNotFoundError:
        return NoProgress()
    return tqdm(total=total, unit=unit, disable=disable, dynamic_ncols=True)


@contextmanager
def compile_notice(write, after_s: float = 0.5):
    """While active, a compilation of Warp kernels that lasts longer than ``after_s`` is announced once through
    ``write`` ("compiling kernels (first run only) …": a first run on a CPU compiles for about a minute, and a progress
    bar's first step would otherwise sit at ``1/600 [01:00<10:01:10]`` without a word), and when the block ends the
    time it took. Kernels loaded from Warp's cache (every later run) say nothing. Yields a dict: ``compiled_s``, the
    seconds spent compiling. Relies on Warp's ``Module._compile`` (private: where a Warp version lacks it, nothing
    is announced and nothing else changes)."""
    state = {"compiled_s": 0.0, "said": False}
    try:
        from warp._src.context import Module

        original = Module._compile
    except (ImportError, AttributeError):
        yield state
        return
    lock = threading.Lock()

    def announce():
        with lock:
            if not state["said"]:
                state["said"] = True
                write("compiling kernels (first run only; cached for the next runs) ...")

    def compile_watched(self, *args, **kwargs):
        timer = threading.Timer(after_s, announce)
        timer.daemon = True
        t0 = time.perf_counter()
        timer.start()
        try:
            return original(self, *args, **kwargs)
        finally:
            timer.cancel()
            with lock:
                state["compiled_s"] += time.perf_counter() - t0

    Module._compile = compile_watched
    try:
        yield state
    finally:
        Module._compile = original
        if state["said"]:
            write(f"kernels compiled in {state['compiled_s']:.0f} s")
