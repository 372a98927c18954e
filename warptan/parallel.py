"""Multi-core CPU launches: the particle (row) dimension of a kernel split into chunks, one per core.

Warp runs one CPU launch on one thread, but launches release the GIL, so chunks launched from a thread
pool run in parallel. Every chunk computes disjoint rows with the same code, so the result is bit-identical
to a single launch. On CUDA, or for small work, it is one ordinary launch.

``WARPTAN_CPU_THREADS`` sets the number of threads (default: the number of cores; 1 disables splitting).

Replayed launches (:class:`Recorder`): ``wp.launch`` packs every argument into C structs on every call (tens of
microseconds per launch on the CPU, the larger part of a small filter step). A fixed sequence of launches through
:func:`launch` and :func:`launch_rows` is recorded once as ``warp.Launch`` commands (arguments packed once) and then
replayed, the row splits kept (chunks replayed on the thread pool), so unlike a captured CPU graph, which runs on
one thread, a large step keeps its cores. The same kernels on the same arguments: the results are bit-identical.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import warp as wp

MIN_ROWS_PER_CHUNK = 64
MIN_WORK_PER_CHUNK = 16_384
"""Below this many thread-items (rows × cols × row_cost) per chunk, splitting costs more than it saves."""
_POOL: ThreadPoolExecutor | None = None
_POOL_SIZE = 0
_LOADED: set = set()
_CORES = max(1, os.cpu_count() or 1)
_RECORDING: list | None = None
"""The sequence being recorded by a :class:`Recorder`, else None."""


def cpu_threads() -> int:
    """Threads used for CPU launches."""
    env = os.environ.get("WARPTAN_CPU_THREADS")
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise ValueError(f"WARPTAN_CPU_THREADS must be a positive integer, got {env!r}") from None
    return _CORES


def _pool(size: int) -> ThreadPoolExecutor:
    global _POOL, _POOL_SIZE
    if _POOL is None or _POOL_SIZE != size:
        if _POOL is not None:
            _POOL.shutdown(wait=True)
        _POOL = ThreadPoolExecutor(max_workers=size, thread_name_prefix="warptan-cpu")
        _POOL_SIZE = size
    return _POOL


def rows_of(array, a: int | None, b: int | None):
    """Rows ``a:b`` of ``array`` as a view, or the array itself for the whole range (``a is None``): making a
    view costs tens of microseconds, which a single launch should not pay."""
    return array if a is None else array[a:b]


def _issue(kernel, dim, block_dim: int | None, inputs, outputs, device, record: bool, spread: int | None = None):
    """One launch (``wp.launch_tiled`` with ``block_dim``; ``spread``: a plain launch in CUDA blocks of that many
    threads); with ``record`` it is made as a ``warp.Launch``, run now and returned."""
    if block_dim is not None:
        dims = list(dim) if isinstance(dim, (list, tuple)) else [dim]
        cmd = wp.launch_tiled(kernel, dim=dims, inputs=list(inputs), outputs=list(outputs), block_dim=block_dim,
                              device=device, record_cmd=record)
    else:
        cmd = wp.launch(kernel, dim=dim, inputs=list(inputs), outputs=list(outputs), device=device, record_cmd=record,
                        block_dim=spread or 256)
    if record:
        cmd.launch()
    return cmd


def launch(kernel, dim, inputs=(), outputs=(), device=None, block_dim: int | None = None,
           spread: int | None = None) -> None:
    """``wp.launch`` (``wp.launch_tiled`` over ``dim`` with ``block_dim``), recorded while a :class:`Recorder`
    records. ``spread``: CUDA blocks of this many threads instead of 256, for a launch of few threads with long
    chains each (more multiprocessors, fewer warps sharing a scheduler)."""
    cmd = _issue(kernel, dim, block_dim, inputs, outputs, device, _RECORDING is not None, spread)
    if _RECORDING is not None:
        _RECORDING.append(cmd)


def launch_rows(kernel, rows: int, args: Callable[[int, int], tuple[list, list]], device, cols: int | None = None,
                threads: int | None = None, row_cost: int = 1, block_dim: int | None = None) -> None:
    """Launch ``kernel`` over ``rows`` (× ``cols``) threads, split by rows across CPU threads.

    Args:
        kernel: A Warp kernel whose first launch dimension indexes rows (particles).
        rows: Number of rows.
        args: ``args(a, b) -> (inputs, outputs)`` for rows ``a:b``, row arrays taken with :func:`rows_of`
            (``a = b = None`` means all rows; ``a`` is otherwise the first row's global index).
        device: The Warp device.
        cols: Second launch dimension, if the kernel is 2-D.
        threads: Override of :func:`cpu_threads`.
        row_cost: Work of one (row, col) item relative to a simple one (e.g. the number of steps it loops).
        block_dim: A tiled kernel (one block of ``block_dim`` threads per row, ``wp.launch_tiled``; a block is one
            thread on the CPU).
    """
    if rows == 0:
        return
    n_threads = threads or cpu_threads()
    work = rows * (cols or 1) * row_cost
    chunks = 1
    if device.is_cpu and not device.is_capturing:  # a captured graph replays on one thread, in order
        chunks = min(n_threads, rows // MIN_ROWS_PER_CHUNK, work // MIN_WORK_PER_CHUNK)
    if chunks <= 1:
        inputs, outputs = args(None, None)
        launch(kernel, rows if cols is None else (rows, cols), inputs, outputs, device, block_dim)
        return
    record = _RECORDING is not None
    key = (kernel.module.name, device.alias)
    if key not in _LOADED:
        wp.load_module(kernel.module, device=device)  # compile once, before the threads
        _LOADED.add(key)
    bounds = [rows * k // chunks for k in range(chunks + 1)]

    def run(k: int):
        a, b = bounds[k], bounds[k + 1]
        inputs, outputs = args(a, b)
        return _issue(kernel, b - a if cols is None else (b - a, cols), block_dim, inputs, outputs, device, record)

    futures = [_pool(n_threads).submit(run, k) for k in range(1, chunks)]
    cmds = [run(0)] + [f.result() for f in futures]
    if record:
        _RECORDING.append(tuple(cmds))


def _replay_chunks(cmds: tuple) -> None:
    pool = _POOL if _POOL is not None and _POOL_SIZE >= len(cmds) else _pool(len(cmds))
    futures = [pool.submit(c.launch) for c in cmds[1:]]
    cmds[0].launch()
    for f in futures:
        f.result()


class Recorder:
    """Sequences of launches recorded once and replayed (see the module docstring), keyed by the caller.

    ``run(key, fn)`` calls ``fn()`` the first time (recording every launch it makes through :func:`launch` and
    :func:`launch_rows`) and replays the recording afterwards. ``fn`` must make the same launches on the same
    arrays every time (no host decision inside it, no launch around these helpers); :meth:`clear` drops the
    recordings, e.g. when an array they hold was replaced."""

    def __init__(self):
        self._seqs: dict = {}

    def clear(self) -> None:
        self._seqs.clear()

    def __len__(self) -> int:
        return len(self._seqs)

    def run(self, key, fn) -> None:
        global _RECORDING
        seq = self._seqs.get(key)
        if seq is not None:
            for cmd in seq:
                if isinstance(cmd, tuple):
                    _replay_chunks(cmd)
                else:
                    cmd.launch()
            return
        if _RECORDING is not None:
            raise RuntimeError("Recorder.run: already recording (nested recordings are not supported)")
        _RECORDING = []
        try:
            fn()
            self._seqs[key] = _RECORDING
        finally:
            _RECORDING = None
