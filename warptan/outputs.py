"""Output folders written as a whole, and strictly valid JSON.

A run's outputs are written into a temporary folder beside the target (``.NAME.warptan-partial-*``, same file
system) and swapped into place when complete, so the target holds one whole run: the previous one or the new
one, never a mix, whenever the process is interrupted.

* The target may be missing, empty, or a previous warptan run (a ``.warptan-run`` manifest lists its files; a
  folder from before the manifest is recognised by its ``results.json``). Anything else (a file, a folder of
  other things, an unwritable parent) is refused by :meth:`OutputFolder.check` before any work starts.
* Files in the target that the previous run did not write (the user's notes, a sub-folder) are carried into the
  new folder as hard links (copies where links are impossible) before the swap: they are never deleted.
* The swap is one atomic ``renameat2(RENAME_EXCHANGE)`` on Linux; elsewhere (or where the file system refuses
  it) two renames with Ctrl-C held back between them, and a target left missing by a crash between them is
  restored from ``.NAME.warptan-old-*`` by the next run.
* JSON: NaN and ±inf become ``null`` (:func:`json_ready`), and :func:`write_json` refuses anything else that is not
  JSON (``allow_nan=False``).
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import math
import os
import shutil
import signal
import tempfile
import threading
import uuid
from pathlib import Path

import numpy as np

MANIFEST = ".warptan-run"
"""The file in an output folder listing what the run wrote (JSON: ``{"files": [...]}``)."""
_LEGACY_FILES = ("results.json", "results.md")


class OutputError(ValueError):
    """An output folder that cannot be used; the message names it and what to do."""


def json_ready(value):
    """``value`` with NumPy scalars and arrays made Python, and non-finite floats made None (JSON null)."""
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    return value


def write_json(path: str | os.PathLike, data, indent: int = 1) -> None:
    """Write ``data`` as strictly valid JSON (NaN/inf as null)."""
    Path(path).write_text(json.dumps(json_ready(data), indent=indent, allow_nan=False) + "\n")


def _previous_run_files(folder: Path) -> set[str] | None:
    """The files (relative paths) a previous warptan run wrote into ``folder``; None when it is not one."""
    manifest = folder / MANIFEST
    if manifest.is_file():
        try:
            return {*json.loads(manifest.read_text())["files"], MANIFEST}
        except (ValueError, KeyError, TypeError, OSError):
            raise OutputError(f"{folder}: its {MANIFEST} is corrupt; remove the folder or choose another "
                              "--out") from None
    results = folder / "results.json"
    if results.is_file():  # a run written before the manifest existed
        try:
            data = json.loads(results.read_text())
        except (ValueError, OSError):
            return None
        if isinstance(data, dict) and {"meta", "scenarios", "runs"} <= set(data):
            plots = {p.name for p in folder.glob("*_seed*_*.png")}
            return {*_LEGACY_FILES, *plots}
    return None


def _user_entries(folder: Path, run_files: set[str]) -> list[str]:
    """Top-level entries of ``folder`` that its run did not write (a listed file inside a sub-folder keeps that
    sub-folder a run entry)."""
    run_tops = {f.split("/", 1)[0] for f in run_files}
    return sorted(e.name for e in folder.iterdir() if e.name not in run_tops)


def _rename_exchange(a: Path, b: Path) -> bool:
    """Atomically exchange two paths (Linux renameat2 RENAME_EXCHANGE); False where unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    return renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


@contextlib.contextmanager
def _interrupts_held():
    """Hold SIGINT until the block ends (main thread only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = signal.signal(signal.SIGINT, lambda *a: caught.append(a))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught and callable(previous):
            previous(*caught[0])


class OutputFolder:
    """The output folder of one run, written as a whole.

    Use::

        out = OutputFolder("results")      # checks the target; nothing is created yet
        with out as tmp:                   # tmp: the temporary folder beside it
            (tmp / "results.json").write_text(...)
        # leaving the block without an exception swaps tmp into place; with one, tmp is removed
    """

    def __init__(self, path: str | os.PathLike):
        text = os.fspath(path)
        if not text or not text.strip():
            raise OutputError("the output folder name is empty")
        self.path = Path(os.path.realpath(text))
        self._tmp: Path | None = None
        self.check()

    def _siblings(self, kind: str) -> list[Path]:
        return sorted(self.path.parent.glob(f".{self.path.name}.warptan-{kind}-*"))

    def check(self) -> None:
        """Refuse a target that is a file, a folder of other things, or in an unwritable parent (OutputError)."""
        target, parent = self.path, self.path.parent
        if not target.exists():
            stale = [p for p in self._siblings("old") if p.is_dir()]
            if stale:  # a crash between the two renames of a fallback swap: the previous run is there
                os.rename(stale[-1], target)
        if target.exists() and not target.is_dir():
            raise OutputError(f"--out {target} is a file, not a folder; choose a folder name")
        if not parent.is_dir():
            raise OutputError(f"--out {target}: its parent folder {parent} does not exist")
        try:  # the real test (permissions, read-only or full file systems): make and remove a folder there
            os.rmdir(tempfile.mkdtemp(prefix=f".{target.name}.warptan-probe-", dir=parent))
        except OSError as err:
            raise OutputError(f"--out {target}: cannot create a folder in {parent} ({err.strerror or err})") from None
        if target.is_dir():
            if not os.access(target, os.R_OK | os.X_OK):
                raise OutputError(f"--out {target}: cannot read the folder (permission denied)")
            if any(target.iterdir()) and _previous_run_files(target) is None:
                first = sorted(e.name for e in target.iterdir())[:3]
                raise OutputError(f"--out {target} holds files that are not a warptan run ({', '.join(first)} ...); "
                                  "choose a new or empty folder (nothing there is replaced)")

    def __enter__(self) -> Path:
        self.check()
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.warptan-partial-", dir=self.path.parent))
        return self._tmp

    def __exit__(self, exc_type, exc, tb) -> bool:
        tmp, self._tmp = self._tmp, None
        if exc_type is None:
            try:
                self._commit(tmp)
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
        else:
            shutil.rmtree(tmp, ignore_errors=True)
        return False

    def _commit(self, tmp: Path) -> None:
        written = sorted(str(p.relative_to(tmp)) for p in tmp.rglob("*") if p.is_file())
        (tmp / MANIFEST).write_text(json.dumps({"files": written}, indent=1) + "\n")
        os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp makes 0700; an output folder is an ordinary folder
        target = self.path
        if not target.exists():
            os.rename(tmp, target)
            return
        self.check()
        previous = _previous_run_files(target) or set()
        for name in _user_entries(target, previous):
            if name not in written and not (tmp / name).exists():
                _link_tree(target / name, tmp / name)
        if _rename_exchange(tmp, target):
            shutil.rmtree(tmp, ignore_errors=True)  # tmp now holds the previous run
            return
        old = target.parent / f".{target.name}.warptan-old-{uuid.uuid4().hex[:8]}"
        with _interrupts_held():
            os.rename(target, old)
            os.rename(tmp, target)
        shutil.rmtree(old, ignore_errors=True)


def current_umask() -> int:
    """The process's umask (read without changing it for longer than a call)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _link_tree(src: Path, dst: Path) -> None:
    """Hard-link (else copy) ``src`` (a file or a folder) to ``dst``."""
    def link(a, b):
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)

    if src.is_dir() and not src.is_symlink():
        shutil.copytree(src, dst, copy_function=link, symlinks=True)
    elif src.is_symlink():
        os.symlink(os.readlink(src), dst)
    else:
        link(src, dst)
