"""Provenance of a measured artifact: what code, machine and command produced a JSON under benchmarks/ or results/.

Every script that writes a benchmark or results file puts :func:`run_meta` under the file's ``meta`` key, so a
number quoted in the README can be traced to a commit, a CPU or GPU, the thread count and the exact command.
"""

from __future__ import annotations

import datetime
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

REQUIRED = ("git_commit", "date_utc", "cpu_model", "cpu_cores", "cpu_threads", "warp_version", "python", "command",
            "devices")
"""Keys every artifact's ``meta`` carries (``gpu`` as well when a CUDA device was used)."""


def git_commit(path: str | os.PathLike | None = None) -> str:
    """The commit of the checkout that holds ``path`` (default: this package), with ``+dirty`` when tracked files
    differ from it. Outside a git checkout: the commit an installed package was built from (``BUILD_COMMIT``, which
    the build writes into the wheel: ``"<commit> (installed)"``), else ``unknown (…)`` (a copy on a GPU machine,
    where ``WARPTAN_GIT_COMMIT`` may name the commit the copy was made from)."""
    if os.environ.get("WARPTAN_GIT_COMMIT"):
        return os.environ["WARPTAN_GIT_COMMIT"]
    where = Path(path or Path(__file__).resolve().parent)
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return _built_commit(where) or "unknown (not a git checkout)"
        # (--no-optional-locks: a plain `git status` refreshes the checkout's index, writing .git/index.lock; under
        # a file size limit that write was cut and a stale lock blocked the user's next git command)
        dirty = subprocess.run(["git", "--no-optional-locks", "status", "--porcelain", "--untracked-files=no"],
                               cwd=where, capture_output=True, text=True, timeout=10).stdout.strip()
        return head.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return _built_commit(where) or "unknown (git not available)"


def _built_commit(where: Path) -> str | None:
    """The commit a non-editable install was built from (``setup.py`` writes ``BUILD_COMMIT`` beside this module),
    None when there is none (a copy, a build outside a clone)."""
    try:
        text = (Path(__file__).resolve().parent / "BUILD_COMMIT").read_text().strip()
    except OSError:
        return None
    return f"{text} (installed)" if text and where == Path(__file__).resolve().parent else None


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux, else the platform's processor string)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run_meta(devices=("cpu",), command: list[str] | str | None = None, **extra) -> dict:
    """The ``meta`` block of an artifact: git commit, UTC date, CPU model, cores and the threads warptan's CPU
    launches use, Warp / Python / NumPy versions, the Warp devices used (and GPU name and driver where CUDA was
    used), the exact command (default: this process's command line), and ``extra`` keys."""
    import numpy as np
    import warp as wp

    from warptan import __version__
    from warptan.parallel import cpu_threads

    if isinstance(devices, str):
        devices = (devices,)
    names = {}
    gpu = []
    for d in devices:
        dev = wp.get_device(d)
        names[str(dev)] = dev.name if dev.is_cuda else "CPU"
        if dev.is_cuda:
            gpu.append(dev.name)
    if command is None:
        command = [Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python", *sys.argv[1:]]
    meta = {
        "git_commit": git_commit(),
        "warptan_version": __version__,
        "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "cpu_model": cpu_model(),
        "cpu_cores": os.cpu_count(),
        "cpu_threads": cpu_threads(),
        "warp_version": wp.config.version,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "devices": names,
        "command": command if isinstance(command, str) else shlex.join(command),
    }
    if gpu:
        driver = wp.get_cuda_driver_version()
        meta["gpu"] = {"names": gpu, "driver_cuda_version": ".".join(map(str, driver)) if driver else "unknown"}
        meta["gpu"]["driver"] = _nvidia_driver()
    meta.update(extra)
    return meta


def _nvidia_driver() -> str:
    """The NVIDIA kernel driver version (nvidia-smi or /proc), or "unknown"."""
    try:
        text = Path("/proc/driver/nvidia/version").read_text()
        for word in text.split():
            if word.count(".") >= 1 and word.replace(".", "").isdigit():
                return word
    except OSError:
        pass
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=10)
        if out.returncode == 0 and out.stdout.strip():
            return out.stdout.strip().splitlines()[0]
    except (OSError, subprocess.SubprocessError):
        pass
    return "unknown"
