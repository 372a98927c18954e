"""The host's reading of the filter: :class:`Readout`, a base of :class:`~warptan.filter.mpf.MarginalizedParticleFilter`
(``P``, ``nominal``, ``moments`` and ``estimate``; it holds no state of its own: the filter's constructor makes the
arrays it reads)."""

from __future__ import annotations

import numpy as np
import warp as wp

from warptan.filter.records import Estimate, _from_blocks
from warptan.kernels import mpf as kmpf
from warptan.nav.frames import quat_exp, quat_mul
from warptan.nav.ins import NavState
from warptan.parallel import launch


class Readout:
    """What the host reads of the filter (see :class:`~warptan.filter.mpf.MarginalizedParticleFilter`, whose attributes
    it reads)."""

    @property
    def P(self) -> np.ndarray:
        """The shared Kalman covariance (12, 12) of [dv, dth, dba, dbg] ((B, 12, 12) for a batch)."""
        p = _covariances(self._read_out())
        return p if self.batched else p[0]

    def nominal(self, b: int = 0) -> NavState:
        """The nominal INS state of filter b (after the buffered IMU samples)."""
        pos, vel, quat, ba, bg = _nominals(self._read_out())
        return NavState(pos[b], vel[b], quat[b], ba[b], bg[b])

    def moments(self) -> np.ndarray:
        """Weighted moments of the particles of each filter (host float64, (B, 169)):
        [Σw, Σw dp (3), Σw dp dpᵀ (9), Σw l (12), Σw l lᵀ (144)] at offsets :data:`warptan.kernels.mpf.MOM_W` …
        ``MOM_LL``."""
        return self._read_out()[:, :kmpf.N_MOMENTS]

    def _read_out(self) -> np.ndarray:
        """(B, :data:`~warptan.kernels.mpf.N_READOUT`) host float64, what :meth:`moments`, :attr:`P`,
        :meth:`nominal` and :meth:`estimate` read: the particles' moments, P's blocks and the nominal INS (after the
        buffered IMU samples), packed by one kernel and copied to the host at once; on CUDA into pinned memory, the
        launches and the copy replayed as one graph from the second call on. An estimate's reads were two launches
        and seven synchronous copies: on an H100's host (S7, B = 1) an estimate took 1.11 ms, 0.36–0.57 ms now
        (``estimate_ms`` of ``benchmarks/issue32/scenario_step_h100.json`` at 32fe1d2 and d777296), and the
        synchronised step after one was 19 µs slower than after none, now 2 µs
        (``benchmarks/issue32/ab_estimate_before_h100.json``, ``ab_estimate_h100.json``)."""
        self.flush()
        key = self._record_key()
        graph = self._readout_graph
        if self.graph and self.device.is_cuda and graph is not None:
            if graph[0] != key:  # (the first call ran eagerly: modules are loaded)
                wp.capture_begin(device=self.device)
                try:
                    self._launch_readout()
                finally:
                    graph = self._readout_graph = (key, wp.capture_end(device=self.device))
            wp.capture_launch(graph[1])
        else:
            self._launch_readout()
            self._readout_graph = (None, None)
        if self.device.is_cuda:
            wp.synchronize_stream(wp.get_stream(self.device))
        return self._readout_host.numpy().copy()

    def _launch_readout(self) -> None:
        d, b, nav = self.device, self.n_filters, self._nav
        launch(kmpf.moment_partials_kernel, dim=(b, kmpf.N_MOMENT_CHUNKS),
               inputs=[self.n, self.state.logw, self.state.dp, self.state.lin], outputs=[self._moments_partial],
               device=d)
        launch(kmpf.readout_kernel, dim=(b, kmpf.N_READOUT),
               inputs=[self._moments_partial, nav["cov"], nav["pos"], nav["vel"], nav["quat"], nav["ba"], nav["bg"]],
               outputs=[self._readout], device=d)
        if d.is_cuda:
            wp.copy(self._readout_host, self._readout)

    def estimate(self):
        """The corrected navigation solution, with the mixture covariance (a list of B for a batch)."""
        packed = self._read_out()
        moments, P = packed[:, :kmpf.N_MOMENTS], _covariances(packed)
        pos, vel, quat, ba, bg = _nominals(packed)  # (the filter's own: the estimate's NavState checks the sums)
        out = []
        for b, m in enumerate(moments):
            total = m[kmpf.MOM_W]
            if not (np.isfinite(m).all() and total > 0):
                raise FloatingPointError(f"particle moments of filter {b} are not finite (Σw = {total}); this is a bug")
            dp = m[kmpf.MOM_DP:kmpf.MOM_DP + 3] / total
            cov_pos = m[kmpf.MOM_DPDP:kmpf.MOM_DPDP + 9].reshape(3, 3) / total - np.outer(dp, dp)
            cov_pos[2, 2] += self.map_offset_var
            lin = m[kmpf.MOM_L:kmpf.MOM_L + 12] / total
            spread = m[kmpf.MOM_LL:kmpf.MOM_LL + 144].reshape(12, 12) / total - np.outer(lin, lin)
            q = quat_mul(quat[b], quat_exp(lin[3:6]))
            nav = NavState(pos[b] + dp, vel[b] + lin[0:3], q / np.linalg.norm(q), ba[b] + lin[6:9], bg[b] + lin[9:12])
            out.append(Estimate(nav=nav, dp=dp, lin=lin, cov_pos=0.5 * (cov_pos + cov_pos.T),
                                cov_lin=P[b] + 0.5 * (spread + spread.T)))
        return out if self.batched else out[0]


def _covariances(packed: np.ndarray) -> np.ndarray:
    """(B, 12, 12) P of each filter from :meth:`Readout._read_out`'s rows."""
    return _from_blocks(packed[:, kmpf.RO_COV:kmpf.RO_NOMINAL].reshape(-1, 4, 4, 3, 3))


def _nominals(packed: np.ndarray) -> tuple[np.ndarray, ...]:
    """(B, ·) position, velocity, attitude quaternion, accelerometer and gyro biases of each filter's nominal INS from
    :meth:`Readout._read_out`'s rows."""
    nom = packed[:, kmpf.RO_NOMINAL:]
    return (nom[:, kmpf.NOM_POS:kmpf.NOM_POS + 3], nom[:, kmpf.NOM_VEL:kmpf.NOM_VEL + 3],
            nom[:, kmpf.NOM_QUAT:kmpf.NOM_QUAT + 4], nom[:, kmpf.NOM_BA:kmpf.NOM_BA + 3],
            nom[:, kmpf.NOM_BG:kmpf.NOM_BG + 3])
