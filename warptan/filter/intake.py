"""The host side of the time update: :class:`ImuIntake`, a base of
:class:`~warptan.filter.mpf.MarginalizedParticleFilter` (IMU samples checked, held or refused, buffered into the
staging set of the interval; the device moves the particles through them at the next update or :meth:`flush`)."""

from __future__ import annotations

import time

import numpy as np

from warptan.checks import FilterError
from warptan.filter.program import UpdateProgram
from warptan.filter.records import _imu_arrays

MAX_STEPS_PER_INTERVAL = 64
"""IMU samples buffered between measurements before the particles are moved anyway."""
MAX_STEP_S = 1.0
"""Longest IMU step :meth:`ImuIntake.predict` integrates, s."""


class ImuIntake(UpdateProgram):
    """``predict``, ``predict_many`` and ``flush`` of the filter (see :class:`~warptan.filter.mpf.
    MarginalizedParticleFilter`, whose attributes it reads)."""

    def predict(self, f_b, w_b, dt: float | None = None) -> None:
        """One IMU sample, (3,) or (B, 3) for a batch: specific force (m/s²) and body rate (rad/s), held over the
        next ``dt`` seconds (default: the nominal step, 1 / ``rate_hz``). Buffered on the host; the nominal INS, the
        Riccati recursion and the particle moves of all samples since the last measurement run in one launch each. A
        sample that is not finite or beyond the grade's range is refused or held (``bad_imu``)."""
        t_enter = time.perf_counter()
        b = self.n_filters
        f, w = _imu_arrays(f_b, w_b)
        if f.size != 3 * b or w.size != 3 * b:
            raise FilterError(f"IMU sample must be {'(3,)' if b == 1 else f'({b}, 3)'}, got {f.shape} and {w.shape}")
        self._buffer(f.reshape(1, b, 3), w.reshape(1, b, 3), self._steps(dt, 1), t_enter)

    def predict_many(self, f_b, w_b, dt=None) -> None:
        """K IMU samples at once, (K, 3) each or (K, B, 3) for a batch: the same as K calls of :meth:`predict` (same
        buffering, flushes, ``bad_imu`` handling and results), with the checks done on the whole block — the host
        cost of an interval is then one call instead of K (20 µs each). ``dt``: each sample's step in s, (K,) or one
        number (all filters of a batch share it; default the nominal step). On CUDA with graphs the samples buffered
        so far then run through the nominal INS and the Riccati at once (the same bits as at the update), so that the
        update which ends the interval does not wait for them; the particles move at the update, as before."""
        t_enter = time.perf_counter()
        b = self.n_filters
        f, w = _imu_arrays(f_b, w_b)
        shape = (f.shape[0], 3) if b == 1 and f.ndim == 2 else (f.shape[0] if f.ndim else 0, b, 3)
        if f.ndim not in (2, 3) or f.shape != shape or w.shape != shape or (b > 1 and f.ndim != 3):
            want = "(K, 3)" if b == 1 else f"(K, {b}, 3)"
            raise FilterError(f"IMU samples must be {want} arrays, got {f.shape} and {w.shape}")
        self._buffer(f.reshape(-1, b, 3), w.reshape(-1, b, 3), self._steps(dt, f.shape[0]), t_enter, advance=True)

    def _steps(self, dt, k: int) -> np.ndarray:
        """(K,) step lengths in s: ``dt`` (a number or K of them) or the nominal step; each in (0, MAX_STEP_S]."""
        if dt is None:
            if k > len(self._nominal_steps):
                return np.full(k, self.dt)
            return self._nominal_steps[:k]  # (read only)
        try:
            steps = np.broadcast_to(np.asarray(dt, dtype=np.float64), (k,))
        except (TypeError, ValueError):
            raise FilterError(f"IMU step dt must be a number or {k} numbers (s), got {dt!r}") from None
        with np.errstate(invalid="ignore"):
            bad = ~((steps > 0.0) & (steps <= MAX_STEP_S))
        if bad.any():
            i = int(np.argmax(bad))
            raise FilterError(f"IMU step dt[{i}] = {float(steps[i])!r} s: each step must be in (0, {MAX_STEP_S:g}] s "
                              "(a longer gap is lost data, not a step)")
        return steps

    def _buffer(self, f: np.ndarray, w: np.ndarray, steps: np.ndarray, t_enter: float, advance: bool = False) -> None:
        """Buffer (K, B, 3) samples with their (K,) steps: checked as one block; a block with a sample that is not
        finite or beyond the grade's range is refused or held sample by sample (``bad_imu``); the buffer flushes
        itself when full. ``advance``: then :meth:`_advance` (``predict_many``), before the bookkeeping that nothing
        on the device waits for (the last good sample, the timer): on CUDA the graph that runs the samples is issued
        as early as the host can, since the update's device work waits for it."""
        k, n = self._k, f.shape[0]
        # one test for the usual block (a NaN fails it too: NaN <= x is False); the sample-wise test only after it
        plausible = (np.abs(f).max(initial=0.0) <= self.grade.accel_range
                     and np.abs(w).max(initial=0.0) <= self.grade.gyro_range)
        if plausible and 0 < n <= MAX_STEPS_PER_INTERVAL - k:  # the usual block: it fits, one write of each column
            imu = self._imu_rows[self._set]
            imu[k:k + n, :, 0] = f
            imu[k:k + n, :, 1] = w
            imu[k:k + n, :, 2, 0] = steps[:, None]
            self._k = k + n
            self.n_imu_steps += n
        else:
            self._buffer_each(f, w, steps, None if plausible else self._bad_samples(f, w))
        if advance:
            self._advance()
        if n:
            self._last_imu[:] = self._imu_rows[self._set][self._k - 1, :, :2]
        if self.timer is not None:
            self.timer._predict_s += time.perf_counter() - t_enter

    def _bad_samples(self, f: np.ndarray, w: np.ndarray) -> np.ndarray:
        """(K, B) samples not finite or beyond the grade's range."""
        return ~((np.abs(f) <= self.grade.accel_range).all(axis=2) & (np.abs(w) <= self.grade.gyro_range).all(axis=2))

    def _buffer_each(self, f: np.ndarray, w: np.ndarray, steps: np.ndarray, bad: np.ndarray | None) -> None:
        """:meth:`_buffer`'s general case: samples held or refused one by one (``bad``), the buffer flushed when full
        (the particles moved through what it holds) and filled on."""
        if bad is not None:
            f, w = f.copy(), w.copy()
            for k in range(f.shape[0]):
                if bad[k].any():
                    self._hold(f[k], w[k], bad[k], self.n_imu_steps + k)
                self._last_imu[:, 0], self._last_imu[:, 1] = f[k], w[k]
        k0, n = 0, f.shape[0]
        while k0 < n:
            if self._k == MAX_STEPS_PER_INTERVAL:
                self.flush()
            take = min(n - k0, MAX_STEPS_PER_INTERVAL - self._k)
            imu = self._imu_rows[self._set]
            imu[self._k:self._k + take, :, 0] = f[k0:k0 + take]
            imu[self._k:self._k + take, :, 1] = w[k0:k0 + take]
            imu[self._k:self._k + take, :, 2, 0] = steps[k0:k0 + take, None]
            self._k += take
            self.n_imu_steps += take
            k0 += take

    def _hold(self, f: np.ndarray, w: np.ndarray, bad: np.ndarray, sample: int) -> None:
        """Sample ``sample`` (B, 3), bad in the filters ``bad``: replaced in place by the last good one (``bad_imu =
        "hold"``), else a FilterError naming it."""
        b = self.n_filters
        k = int(np.argmax(bad))
        if not (self.bad_imu == "hold" and np.isfinite(self._last_imu[bad]).all()):
            where = f" (filter {k})" if b > 1 else ""
            what = "implausible" if np.isfinite(f[k]).all() and np.isfinite(w[k]).all() else "non-finite"
            raise FilterError(
                f"{what} IMU sample {sample}{where}: specific force {f[k].tolist()} m/s², body "
                f"rate {w[k].tolist()} rad/s (grade {self.grade.name}: |f| ≤ {self.grade.accel_range:g} m/s², "
                f"|ω| ≤ {self.grade.gyro_range:g} rad/s per axis, finite)"
                + ("" if self.bad_imu == "hold" else
                   "; bad_imu='hold' integrates such samples as the last good one"))
        f[bad], w[bad] = self._last_imu[bad, 0], self._last_imu[bad, 1]
        self.n_imu_held += bad

    def flush(self) -> None:
        """Move the particles through the buffered IMU samples now (before an estimate, or a full buffer)."""
        if self._k == 0:
            return
        self._stage_interval()
        self._piece(("flush", self._ahead_state()), self._launch_move)
        self._next_set()
