"""Output folders written as a whole, by one writer at a time, holding outputs only; and strictly valid JSON.

A run's outputs are written into a temporary folder beside the target (``.NAME.warptan-partial-*``, same file
system) and swapped into place when complete, so the target holds one whole run: the previous one or the new
one, never a mix, whenever the process is interrupted (Ctrl-C or SIGTERM) or a write fails (a full disk: the
error names the file, and the previous run stays).

* **One writer per folder**: an advisory lock (``flock`` on ``.NAME.warptan-lock`` beside the target; the kernel
  releases it on any exit, SIGKILL included) is held from the check to the swap. A second run on the same folder
  is refused at once, naming the process that holds it. Partial folders a killed writer left are removed by the
  next holder of the lock.
* **Kinds**: the ``.warptan-run`` manifest names what wrote the folder (``run``, ``replay``, ``campaign`` or
  ``flight-logs``) and lists its files. A folder is replaced only by the same kind of output: flight logs written
  by ``--export-log`` are the inputs of a later replay, never a previous run that ``--out`` may replace.
* **Outputs only**: :meth:`OutputFolder.refuse_inputs` refuses a target that is, contains or lies inside any input
  of the run (log, bag, DEM, map, scenario or campaign file).
* The target may be missing, empty, or a previous output of the same kind (its manifest says so). Anything else (a
  file, a folder of other things, a folder holding a ``results.json`` without a manifest — a user's copy, or a run
  from before the manifest: which files warptan wrote there cannot be told, and the rule that guessed them from
  their names deleted a user's ``*_seed*_*.png`` —, a read-only or immutable folder, an unwritable parent) is
  refused by :meth:`OutputFolder.check` before any work starts.
* Replacing a previous output removes only the files its manifest lists: anything else in the folder (the user's
  notes, a file added inside a sub-folder) is carried into the new folder as hard links (copies where links are
  impossible) before the swap. A user's file with the name of a new output is never overwritten: the new output
  is then kept beside the folder and the error says where.
* The swap is one atomic ``renameat2(RENAME_EXCHANGE)`` on Linux; elsewhere (or where the file system refuses
  it) two renames with Ctrl-C and SIGTERM held back between them, and a target left missing by a crash between
  them is restored from ``.NAME.warptan-old-*`` by the next run.
* JSON: NaN and ±inf become ``null`` (:func:`json_ready`), and :func:`write_json` refuses anything else that is not
  JSON (``allow_nan=False``).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import json
import math
import os
import shutil
import signal
import stat
import sys
import tempfile
import threading
import uuid
import weakref
from pathlib import Path

import numpy as np

MAX_NAME_BYTES = 200
"""Longest output folder name (bytes): the lock, partial and previous folders beside it add up to 30 (the file
system's limit is 255; a 300-character name was a raw "[Errno 36]")."""
MANIFEST = ".warptan-run"
"""The file in an output folder naming its kind and listing what was written (JSON: ``{"kind": .., "files": [..]}``)."""
KINDS = ("run", "replay", "campaign", "flight-logs")
"""What writes output folders: ``warptan run``, ``warptan replay``, ``warptan campaign`` and ``--export-log``."""
_KIND_WORDS = {"run": "a warptan run's results", "replay": "a warptan replay's results",
               "campaign": "a warptan campaign's results",
               "flight-logs": "flight logs written by --export-log (inputs of a replay, not a run)"}


class OutputError(ValueError):
    """An output folder that cannot be used; the message names it and what to do."""


def write_failure(err: OSError) -> str:
    """Why a write failed, in words (a full disk or a file size limit said so)."""
    why = err.strerror or str(err)
    if err.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT):
        why += " (the disk is full or a file size limit was reached)"
    return why


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


def _previous_output(folder: Path) -> tuple[str, set[str]] | None:
    """(kind, files) of a previous warptan output in ``folder`` (files: relative paths it wrote, manifest
    included); None when it is not one. A manifest without a kind (written before kinds) is read from its files."""
    manifest = folder / MANIFEST
    if manifest.is_file():
        try:
            data = json.loads(manifest.read_text())
            files = {*data["files"], MANIFEST}
            kind = data.get("kind")
        except (ValueError, KeyError, TypeError, AttributeError, OSError):
            raise OutputError(f"{folder}: its {MANIFEST} is corrupt; remove the folder or choose another "
                              "folder") from None
        if kind not in KINDS:
            if any(f.endswith(".h5") or "_bag/" in f for f in files):
                kind = "flight-logs"
            elif "campaign.json" in files:
                kind = "campaign"
            else:
                kind = "results"  # a run or a replay of an earlier version: either may replace it
        return kind, files
    return None


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


HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""Signals held back between the two renames of the fallback swap."""


@contextlib.contextmanager
def _interrupts_held():
    """Hold SIGINT and SIGTERM until the block ends (main thread only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = {s: signal.signal(s, lambda *a: caught.append(a)) for s in HELD_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        if caught:
            handler = previous.get(caught[0][0])
            if callable(handler):
                handler(*caught[0])
            elif handler == signal.SIG_DFL:
                signal.raise_signal(caught[0][0])


_HELD_LOCKS: weakref.WeakSet = weakref.WeakSet()


def release_locks() -> None:
    """Release every output-folder lock this process holds (the command line calls it on the way out)."""
    for folder in list(_HELD_LOCKS):
        folder.release()


class OutputFolder:
    """The output folder of one run, written as a whole by one writer.

    Use::

        out = OutputFolder("results", kind="run")   # checks the target and locks it; nothing is created yet
        out.refuse_inputs([dem_path, log_path])       # an --out that is, holds or lies in an input is refused
        with out as tmp:                              # tmp: the temporary folder beside it
            (tmp / "results.json").write_text(...)
        # leaving the block without an exception swaps tmp into place and releases the lock; with one, tmp is
        # removed and the target is as it was

    Args:
        path: The target folder.
        kind: What writes it (one of :data:`KINDS`); a previous output of another kind is not replaced.
        option: How messages name the target (the command-line option: ``--out``, ``--export-log``).
    """

    def __init__(self, path: str | os.PathLike, kind: str = "run", option: str = "--out"):
        text = os.fspath(path)
        if not text or not text.strip():
            raise OutputError(f"{option}: the output folder name is empty")
        if kind not in KINDS:
            raise OutputError(f"output kind must be one of {', '.join(KINDS)}, got {kind!r}")
        self.path = Path(os.path.realpath(text))
        self.kind, self.option = kind, option
        self._tmp: Path | None = None
        self._lock_fd: int | None = None
        if len(self.path.name.encode()) > MAX_NAME_BYTES:
            raise OutputError(f"{option} {text[:60]}…: the folder name is {len(self.path.name.encode())} bytes long; "
                              f"at most {MAX_NAME_BYTES} (the files written beside it have longer names)")
        self.check()

    def _siblings(self, kind: str) -> list[Path]:
        return sorted(self.path.parent.glob(f".{self.path.name}.warptan-{kind}-*"))

    @property
    def lock_path(self) -> Path:
        return self.path.parent / f".{self.path.name}.warptan-lock"

    def _name(self) -> str:
        return f"{self.option} {self.path}"

    # ------------------------------------------------------------------ lock
    def _acquire(self) -> None:
        """Take the folder's advisory lock (refused at once when another process holds it)."""
        if self._lock_fd is not None:
            return
        import fcntl

        lock = self.lock_path
        for _ in range(20):  # a holder may remove the file between our open and our lock: take the new one
            try:
                fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as err:
                raise OutputError(f"{self._name()}: cannot create its lock file {lock} ({err.strerror})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                holder = _read_holder(fd)
                os.close(fd)
                if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    raise OutputError(f"{self._name()} is being written by another warptan process ({holder}); "
                                      "wait for it to finish or choose another folder") from None
                raise OutputError(f"{self._name()}: cannot lock {lock} ({err.strerror})") from None
            try:
                same = os.fstat(fd).st_ino == os.stat(lock).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        else:
            raise OutputError(f"{self._name()}: could not take its lock {lock}")
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()}: {' '.join([Path(sys.argv[0]).name, *sys.argv[1:]])[:300]}\n".encode())
        self._lock_fd = fd
        _HELD_LOCKS.add(self)
        for stale in self._siblings("partial") + self._siblings("probe"):  # left by a killed writer
            shutil.rmtree(stale, ignore_errors=True)

    def release(self) -> None:
        """Release the lock (idempotent; also on garbage collection and, by the kernel, on any exit)."""
        fd, self._lock_fd = self._lock_fd, None
        if fd is None:
            return
        _HELD_LOCKS.discard(self)
        with contextlib.suppress(OSError):
            os.unlink(self.lock_path)  # unlinked while held: a waiting opener sees another inode and retries
        os.close(fd)

    def __del__(self):
        with contextlib.suppress(Exception):
            self.release()

    # ------------------------------------------------------------------ checks
    def check(self) -> None:
        """Refuse a target that is a file, a folder of other things or of another kind of output, a read-only
        folder, in an unwritable parent, or locked by another process (OutputError)."""
        target, parent = self.path, self.path.parent
        if os.path.lexists(target) and not os.path.exists(target):
            raise OutputError(f"{self._name()} is a symbolic link that leads nowhere (a loop, or to a folder whose "
                              "parent is missing); choose another folder")
        if target.exists() and not target.is_dir():
            raise OutputError(f"{self._name()} is a file, not a folder; choose a folder name")
        if os.path.ismount(target):
            raise OutputError(f"{self._name()} is a mount point; an output folder is replaced as a whole (a rename, "
                              "which a mount point refuses): choose a folder inside it")
        if not parent.is_dir():
            raise OutputError(f"{self._name()}: its parent folder {parent} does not exist")
        try:  # the real test (permissions, read-only or full file systems): make and remove a folder there
            os.rmdir(tempfile.mkdtemp(prefix=f".{target.name}.warptan-probe-", dir=parent))
        except OSError as err:
            raise OutputError(f"{self._name()}: cannot create a folder in {parent} ({err.strerror or err})") from None
        self._acquire()
        if not target.exists():
            stale = [p for p in self._siblings("old") if p.is_dir()]
            if stale:  # a crash between the two renames of a fallback swap: the previous run is there
                os.rename(stale[-1], target)
        if target.is_dir():
            if not os.access(target, os.R_OK | os.X_OK):
                raise OutputError(f"{self._name()}: cannot read the folder (permission denied)")
            if not os.access(target, os.W_OK):
                raise OutputError(f"{self._name()}: the folder is read-only or immutable, so it cannot be replaced; "
                                  "choose another folder")
            if any(target.iterdir()):
                previous = _previous_output(target)
                if previous is None:
                    first = sorted(e.name for e in target.iterdir())[:3]
                    why = "files that are not a warptan run"
                    if (target / "results.json").exists():  # a copy, or a run from before the manifest
                        why = (f"a results.json but no {MANIFEST} manifest (a copy, or a run from before the "
                               "manifest: which files warptan wrote cannot be told)")
                    raise OutputError(f"{self._name()} holds {why} ({', '.join(first)} ...); choose a new or empty "
                                      "folder (nothing there is replaced)")
                kind = previous[0]
                if kind != self.kind and not (kind == "results" and self.kind in ("run", "replay")):
                    raise OutputError(f"{self._name()} holds {_KIND_WORDS.get(kind, kind)}; a {self.kind} does not "
                                      "replace them: choose another folder")

    def refuse_inputs(self, inputs) -> None:
        """Refuse (OutputError) a target that is, contains or lies inside one of ``inputs`` (paths; None and names
        that are not files are ignored): a run never writes over, or beside and then replaces, what it reads."""
        for item in inputs:
            if item is None:
                continue
            try:
                real = Path(os.path.realpath(os.fspath(item)))
            except TypeError:
                continue
            if not real.exists():
                continue
            if real == self.path:
                what = "is"
            elif self.path in real.parents:
                what = "contains"
            elif real in self.path.parents:
                what = "lies inside"
            else:
                continue
            raise OutputError(f"{self._name()} {what} the input {real}; an output folder holds outputs only: "
                              "choose another folder")

    # ------------------------------------------------------------------ writing
    def __enter__(self) -> Path:
        self.check()
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.warptan-partial-", dir=self.path.parent))
        _watch_writes(self._tmp)
        return self._tmp

    def __exit__(self, exc_type, exc, tb) -> bool:
        tmp, self._tmp = self._tmp, None
        try:
            if exc_type is None:
                try:
                    self._commit(tmp)
                except OSError as err:  # the manifest's write, the swap: nothing of the new run is kept
                    shutil.rmtree(tmp, ignore_errors=True)
                    where = err.filename if err.filename and str(tmp) not in str(err.filename) else self.path
                    raise OutputError(f"writing {where} failed: {write_failure(err)}; {self.path} is as it was "
                                      "before this run") from None
                except BaseException:
                    shutil.rmtree(tmp, ignore_errors=True)
                    raise
            else:
                failed = _failed_file(tmp, exc) if isinstance(exc, OSError) else None
                shutil.rmtree(tmp, ignore_errors=True)
                if failed is not None:
                    raise OutputError(f"writing {self.path / failed} failed: {write_failure(exc)}; {self.path} is "
                                      "as it was before this run") from None
        finally:
            _OPENED.pop(os.path.abspath(tmp), None)
            self.release()
        return False

    def _commit(self, tmp: Path) -> None:
        written = sorted(str(p.relative_to(tmp)) for p in tmp.rglob("*") if p.is_file())
        (tmp / MANIFEST).write_text(json.dumps({"kind": self.kind, "files": written}, indent=1) + "\n")
        target = self.path
        if not target.exists():
            os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp makes 0700; an output folder is an ordinary folder
            os.rename(tmp, target)
            return
        self.check()
        previous = _previous_output(target)
        clash = _carry_user_files(target, tmp, previous[1] if previous else set())
        if clash is not None:
            kept = target.parent / f"{target.name}.new-{uuid.uuid4().hex[:6]}"
            os.rename(tmp, kept)
            raise OutputError(f"{target / clash} was not written by the previous run and the new one writes a file "
                              f"of that name: nothing in {target} was replaced; the new outputs are in {kept}")
        os.chmod(tmp, stat.S_IMODE(target.stat().st_mode))  # the replaced folder's mode (a 555 one came back 0755)
        if _rename_exchange(tmp, target):
            _remove_folder(tmp)  # tmp now holds the previous run
            return
        old = target.parent / f".{target.name}.warptan-old-{uuid.uuid4().hex[:8]}"
        with _interrupts_held():
            os.rename(target, old)
            os.rename(tmp, target)
        _remove_folder(old)


def _remove_folder(path: Path) -> None:
    """Remove a replaced output folder (made writable first: it kept its own mode, which may be read-only)."""
    with contextlib.suppress(OSError):
        os.chmod(path, 0o700)
    shutil.rmtree(path, ignore_errors=True)


def _read_holder(fd: int) -> str:
    """What the lock file says about its holder (``pid N: command``), or a neutral phrase."""
    with contextlib.suppress(OSError):
        text = os.pread(fd, 400, 0).decode(errors="replace").strip()
        if text:
            return text
    return "its process id is not recorded yet"


_OPENED: dict[str, str | None] = {}
"""Per output folder being written (its partial folder): the last file opened for writing in it."""
_HOOK: list = []


def _audit(event: str, args) -> None:
    if event != "open" or not _OPENED or not isinstance(args[0], (str, bytes, os.PathLike)):
        return
    mode, flags = args[1], args[2]
    if (any(c in mode for c in "wax+") if isinstance(mode, str) else bool(flags & (os.O_WRONLY | os.O_RDWR))):
        path = os.path.abspath(os.fsdecode(args[0]))
        for tmp in _OPENED:
            if path.startswith(tmp + os.sep):
                _OPENED[tmp] = path


def _watch_writes(tmp: Path) -> None:
    """Record the last file opened for writing in ``tmp`` (a Python audit hook, installed once): a write that fails
    without naming its file (a full disk, a file size limit) is named by it. (The newest file by modification time
    was a guess: files written within one clock tick tie, and ``ulimit -f`` named results.md for a plot.)"""
    if not _HOOK:
        _HOOK.append(_audit)
        sys.addaudithook(_audit)
    _OPENED[os.path.abspath(tmp)] = None


def _failed_file(tmp: Path | None, err: OSError) -> str | None:
    """The file (relative to the output folder) whose write raised ``err``: the error's own file name when it lies
    in ``tmp``, else (an error that names no file, as a full disk's) the last file opened for writing there
    (:func:`_watch_writes`; writes are sequential). None when ``tmp`` is gone or the error is about a file
    elsewhere (not a failed write)."""
    if tmp is None or not tmp.is_dir():
        return None
    name = os.fsdecode(err.filename) if err.filename else _OPENED.get(os.path.abspath(tmp))
    if name is None:
        return "(its first file)"
    try:
        return str(Path(os.path.realpath(name)).relative_to(os.path.realpath(tmp)))
    except ValueError:
        return None


def _carry_user_files(target: Path, tmp: Path, listed: set[str]) -> str | None:
    """Link every entry of ``target`` that the previous output did not write (not in ``listed``, at any depth)
    into ``tmp`` at the same place. Returns the first such file whose name the new output also wrote (nothing is
    then carried further), else None."""
    listed_dirs = {str(Path(f).parent) for f in listed if "/" in f}
    listed_dirs |= {str(p) for f in listed_dirs for p in Path(f).parents if str(p) != "."}
    for root, dirs, files in os.walk(target):
        rel_root = Path(root).relative_to(target)
        for name in sorted(dirs):
            rel = str(rel_root / name)  # Path(".") / name is name
            if rel in listed_dirs:
                continue  # a folder the previous run wrote into: walk it
            dirs.remove(name)  # a folder of the user's (or a symlink): carried whole
            if (tmp / rel).exists():
                return rel
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            _link_tree(target / rel, tmp / rel)
        for name in sorted(files):
            rel = str(rel_root / name)
            if rel in listed:
                continue
            if (tmp / rel).exists() or (tmp / rel).is_symlink():
                return rel
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            _link_tree(target / rel, tmp / rel)
    return None


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
