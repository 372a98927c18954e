# Over 500 lines on purpose: the update's device program is one ordered sequence (move, tempering stages, model,
# resampling, modes, integrity, record) issued in three forms (eager, recorded for replay on the CPU, captured in CUDA
# graphs with conditional stages) that must stay the same launches in the same order.
"""The device program of a measurement update: :class:`UpdateProgram`, the base of
:class:`~warptan.filter.mpf.MarginalizedParticleFilter` that launches it (it holds no state of its own: the filter's
constructor makes the arrays it launches on).

Per IMU sample (``predict``) the host only buffers the sample (into one of two pinned staging sets on CUDA,
alternating per interval, so that the host fills one while the device's graph copies the other; an event per set
says when it is free again). Per measurement (``update``), all on the device, no host decision, captured as one
graph on CUDA:

1. one kernel (:mod:`warptan.kernels.nav`, float64; one thread per filter on the CPU, one 32-thread block per filter
   on CUDA whose lanes share the 3×3 blocks in shared memory): the buffered samples run through the nominal INS and
   the Riccati recursion (``N_k``, ``L_k``, ``P``), and the K steps a particle would take are composed into one
   affine map with Gaussian noise (``Φ``, ``chol S``) — the same distribution as K separate moves;
2. every particle moves, the model scores its pose, and the log-likelihood is
   applied in tempering stages (progressive correction, Oudjane & Musso 2000; design notes §6b): each stage applies
   the largest exponent ``γ`` of what remains that keeps ESS ≥ ``temper_ess · n`` (chosen on the device from
   20 geometric candidates by streaming log-sum-exp reductions), normalises per filter, and resamples when
   exponent remains or ESS < ``resample_threshold · n``; the next stage re-evaluates the model at the moved
   particles. Every resampling is regularised (Musso, Oudjane & Le Gland 2001) with partial kernel shrinkage
   (Liu & West 2001): ``dp_i = a dp_anc + (1 - a) m + h chol(Σ̂) z_i``, ``a = sqrt(1 - s h²)``, Σ̂ and m the
   weighted covariance and mean of dp before resampling, ``h`` Silverman's bandwidth for d = 3 times
   ``regularize``, ``s`` = ``shrinkage``: the cloud's covariance grows by ``1 + (1 - s) h²`` per resampling.
   A model that cannot fix the position with one reading (the altimeter: ``fixes_per_scan`` False; it returns each
   particle's position information ``g gᵀ/σ²``) keeps the jitter within what one reading resolves: ``h`` is scaled by
   ``f = min(1, sqrt(JITTER_NIS / tr(h² Σ̂ Ī_p)))`` (:data:`warptan.kernels.mpf.JITTER_NIS`), and each particle is
   scored for that kernel ``(h f)² Σ̂`` (the map's height mean and variance over it,
   :func:`warptan.kernels.sliding.kernel_height`; ``h · chol(P0)`` before the first reading and after a re-spread).
   Measured on S9 over the 30 m tile (CPU, 60 seeds): seeds over 5 m 9 → 3, 3σ coverage N/E 90/90 → 95.5/97 %.
   Measured (8 seeds, 120 s, per-point likelihood): s = 0 lets the covariance grow by 1 + h² per resampling and
   over flat terrain, where nothing contracts it, the altimeter run S12 drifted 2–3 km; s = 1 keeps the
   covariance exactly and the flat point-cloud run S11 became overconfident (3σ coverage 62/47 %, RMSE
   4.0/6.4 m); s = 0.5 gave S11 2.1/2.0 m at 97/98 % and S12 20/18 m at 99/100 %. Then the integrity monitor,
   the update's record, P's measurement update and (closed loop) the injection.

Steps 1–2 are a fixed sequence of copies and launches on persistent buffers (``max_stages`` stages; a filter that is
done ignores the later ones), so it is captured as a graph (one per staging set) and replayed (CUDA; ``graph=True`` on
the CPU, where Warp replays it on one thread). The CPU default is eager: stages no filter needs are not launched (the
host reads the flags, free on the CPU), with the same result, and the fixed pieces between those decisions replay
launches recorded once with their arguments packed (:class:`warptan.parallel.Recorder`: packing cost ~40 µs per
launch, a third of a small step; the row splits over cores are kept, which a CPU graph loses). Measured A/B on this
2-core VM (N = 500, M = 100, gaussian, 4 × 40 steps interleaved): sliding 2.29 vs 3.50 ms, dda 6.05 vs 7.41 ms per
step; N = 5000 sliding 14.1 vs 14.4 ms. Host work per step does not depend on the number of particles; a batch of B
filters (independent seeds, same model) shares every launch. Measured on an H100 (N = 500, M = 400, gaussian,
``benchmarks/filter_step_device_h100.json``): sliding 0.77 ms, dda 0.95 ms per synchronised step, 0.52 / 0.70 ms
pipelined; with the nav interval on the host and P's update read back per update it was 2.16 / 1.67 ms.

On CUDA a tempering stage's per-filter pieces after the candidates' partials (ESS, selection, log-likelihood partials,
maximum, exp partials, weight statistics, normalisation, Kalman update) run as one block per filter
(:data:`warptan.kernels.mpf.stage_block_kernel`) together with the stage's resampling, the particles' poses and the next
stage's flag: the same functions on the same values with barriers between them, the same bits as the separate kernels (a
graph node costs ~2 µs whatever its work: 16 nodes a stage became 2). The CPU runs the same block kernel as one thread
per filter, which searches the candidates in order itself (no partials launched): one launch a stage instead of 13, the
same bits (S8 / S7, N = 500, 10 × 10 rays, updates alternated in one process on this 2-core VM: 2.81 → 2.71 / 4.67 →
4.57 ms per update; none of the separate launches was split over cores). ``_lean`` (CUDA, where it measured faster;
slower on a 2-core CPU) fuses the head (moves, poses, statistics reset) and the tail (integrity + re-spread; record +
P's update + reset) likewise, nests the stages' conditionals and queues the head (the interval, the particles' moves and
poses: a graph of its own) as soon as the measurement passed the model's ``check``, so that the device runs it while the
host stages the scan; the same bits on the CPU (``tests/test_mpf.py``).
"""

from __future__ import annotations

import warp as wp

from warptan.filter.records import step_seed, step_seed_int
from warptan.kernels import likelihood as klik
from warptan.kernels import mpf as kmpf
from warptan.kernels import nav as knav
from warptan.parallel import launch, launch_rows, rows_of

_STREAM_INIT, _STREAM_MOVE, _STREAM_RESAMPLE = 0, 1, 2
"""The counter-based random streams of the initial draw, the particle moves and the resamplings."""


class UpdateProgram:
    """The launches of an interval and of a measurement update, their CPU recordings and CUDA graphs (see the module
    docstring). A base class of :class:`~warptan.filter.mpf.MarginalizedParticleFilter`, whose attributes it reads."""

    def _stage_interval(self) -> None:
        """Host part of an interval (O(B)): the sample count and the interval's seeds next to the buffered samples."""
        ints = self._ints_np[self._set]
        if ints.shape[0] == 1:  # one filter: Python integers, one row written (5.9 -> 1.5 µs a step on the CPU)
            row = [0] * knav.N_INTS
            seed = int(self.seeds[0])
            row[knav.INT_STEPS] = self._k
            row[knav.INT_MOVE_SEED] = step_seed_int(seed, self.n_imu_steps, _STREAM_MOVE)
            row[knav.INT_RESAMPLE_SEED] = step_seed_int(seed, self.n_updates + 1, _STREAM_RESAMPLE)
            ints[0] = row
        else:
            ints[:, knav.INT_STEPS] = self._k
            ints[:, knav.INT_MOVE_SEED] = step_seed(self.seeds, self.n_imu_steps, _STREAM_MOVE)
            ints[:, knav.INT_RESAMPLE_SEED] = step_seed(self.seeds, self.n_updates + 1, _STREAM_RESAMPLE)
        self._interval_k = self._k
        self._k = 0

    def _copy_interval(self, samples: bool = True) -> None:
        """CUDA: the staged count and seeds, and (``samples``) the samples, to the device (copies from pinned memory,
        the count first: a sample it counts was written before it)."""
        if self.device.is_cuda:
            wp.copy(self._ints, self._ints_host[self._set])
            if samples:
                wp.copy(self._imu, self._imu_host[self._set])

    def _launch_interval(self, keep: bool = False) -> None:
        """Device part of an interval: the staged samples and seeds to the device, then one kernel runs the samples
        not yet run through the nominal INS and the Riccati and composes the interval's Φ and chol(S) as it stands
        (:mod:`warptan.kernels.nav`, float64); ``keep``: the interval may go on (:meth:`_advance`)."""
        self._copy_interval()
        nav, out = self._nav, self._dev
        phi, noise, scratch = self._scratch
        tiled = self.device.is_cuda
        begin = int(self._ahead == 0)
        launch_rows(knav.nav_interval_kernels[tiled], self.n_filters,
                    lambda a, b: ([a or 0, begin, 1, int(keep), self._nav_progress, self._ints, self.dt,
                                   self._q_dev[0], self.q_rough, self._q_lin, self._q_dev[1], self._imu, nav["pos"],
                                   nav["vel"], nav["quat"], nav["ba"], nav["bg"], nav["cov"], phi, noise, scratch],
                                  [out["phi"], out["chol"], out["pose"], out["att_cov"], out["p_col"]]),
                    self.device, row_cost=4000 * max(self._interval_k, 1),
                    block_dim=knav.NAV_BLOCK_DIM if tiled else None)

    def _end_interval(self) -> None:
        """The interval's end on the device: its outputs (Φ, chol S, the pose) as the samples so far left them: what
        :meth:`_advance` already wrote when no sample came after it (then only the seeds go up), else the launch."""
        if self._ahead_state() == 2:
            self._copy_interval(samples=False)  # (no kernel reads the samples again: a batch's are ~0.5 MB)
        else:
            self._launch_interval()

    def _ahead_state(self) -> int:
        """0: none of the interval's samples ran ahead (:meth:`_advance`); 1: some did, more came after; 2: all did
        (after :meth:`_stage_interval`, which fixes the interval's count). Graphs are kept per state."""
        if self._ahead == 0:
            return 0
        return 2 if self._k == 0 and self._ahead == self._interval_k else 1

    def _head_first(self) -> bool:
        """The lean update queues its head before the scan is staged (and, with graphs, :meth:`predict_many` runs
        the interval's samples ahead), not for a model without ``check``. (Under map-error modes the scan geometry
        and the revisit memory read the platform's pose from a copy behind the device's work, not the interval.)"""
        return self._lean and self._interval_first and callable(getattr(self.model, "check", None))

    def _stage_scan(self, measurement, attitude) -> tuple:
        """The model's ``stage`` of the scan (validating first: nothing moves), and the device work it held. With
        graphs on CUDA and an early head the scan's copies and launches go into the update's graph, from pinned
        buffers of this filter's staging set, instead of being issued one by one from Python. A scan refused after
        the head (interval, moves) went to the device leaves the filter as after ``flush()``."""
        extra = {} if attitude is None else {"attitude": attitude}  # a model of the user's may not take it
        held = (self._early and self.graph and self.device.is_cuda
                and callable(getattr(self.model, "hold_device_work", None)))
        if held:
            self.model.hold_device_work(self._staging_buffers[self._set])
        try:
            out = self.model.stage(measurement, self._pos, self._quat, **extra)
        except BaseException:
            if held:
                self.model.release_device_work()
            if self._early:
                self._next_set()
            raise
        return out, (self.model.release_device_work() if held else ())

    def _advance(self) -> None:
        """``_run_ahead`` (the default with CUDA graphs) and a lean head-first update: run the samples buffered so far
        through the nominal INS and the Riccati now and write the interval's outputs as it stands (one graph), so
        that the update which ends the interval finds that work done or under way instead of queuing it after the
        scan's check; a sample buffered after this one runs at the update. The same bits as one launch for the
        interval (:data:`warptan.kernels.nav.nav_interval_kernels`); the particles still move once, at the update."""
        if not (self._k and self._run_ahead and self._head_first()):
            return
        self._ints_np[self._set][:, knav.INT_STEPS] = self._k  # (the count so far: its copy is queued first)
        if not self.graph or self._graph_key is None:  # (the first update runs eagerly)
            self._launch_interval(keep=True)
        else:
            self._replay("advance", self._launch_interval, True)
        self._ahead = self._k

    def _next_set(self) -> None:
        """After the device work that reads the current staging set is queued: switch sets (CUDA), first waiting
        until the work queued on the other set, two intervals ago, is done."""
        self._ahead = 0
        if not self.device.is_cuda:
            return
        wp.get_stream(self.device).record_event(self._events[self._set])
        self._set ^= 1
        wp.synchronize_event(self._events[self._set])  # returns at once if never recorded

    def _launch_time_update(self) -> None:
        dv, n, st = self._dev, self.n, self.state
        launch_rows(kmpf.time_update_kernel, self.n_filters * n,
                    lambda a, b: ([a or 0, n, dv["seeds"], dv["phi"], dv["chol"]],
                                  [rows_of(st.dp, a, b), rows_of(st.lin, a, b)]), self.device, row_cost=30)

    def _launch_move(self) -> None:
        self._end_interval()
        self._launch_time_update()

    def _piece(self, key, fn, *args) -> None:
        """A fixed piece of the device work: replayed from its recorded launches on the CPU, else launched."""
        if self._recorder is None:
            fn(*args)
        else:
            self._recorder.run(key, lambda: fn(*args))

    def _launch_poses(self) -> None:
        launch(kmpf.particle_poses_kernel, dim=self.n_filters * self.n,
                  inputs=[self.n, self._dev["pose"], self.state.dp, self.state.lin],
                  outputs=[self._pos, self._quat], device=self.device)

    def _launch_stage(self, out, stage: int) -> None:
        """One tempering stage: choose the exponent, weight, normalise and decide to resample (device)."""
        d, b, n, st = self.device, self.n_filters, self.n, self.state
        lam, info = self._attitude_info(out)
        if d.is_cpu and not self._block_stages:  # candidates in order until one is taken (same bits, usually 1 of
            # 20; the CPU's block form searches them itself)
            launch(kmpf.temper_search_kernel, dim=b,
                   inputs=[n, stage, self.params, out.loglik, out.n_valid, out.meta, st.logw, self._stats],
                   outputs=[self._temper_partials, self._unpred_partials, self._temper_ess], device=d)
        elif not d.is_cpu:  # every candidate in parallel
            launch(kmpf.temper_partials_kernel, dim=(b, kmpf.N_CHUNKS, kmpf.N_TEMPER),
                   inputs=[n, stage, out.loglik, out.n_valid, out.meta, st.logw, self._stats],
                   outputs=[self._temper_partials, self._unpred_partials], device=d,
                   spread=kmpf.TEMPER_BLOCK_DIM)
        if self._block_stages:  # CUDA: the stage's other pieces and its resampling in one block per filter
            seeds, sp = self._dev["resample_seeds"], self._spare
            launch(kmpf.stage_block_kernel, dim=[b],
                   inputs=[n, stage, int(stage == self.max_stages - 1), self.params, out.loglik, out.n_valid, out.meta,
                           out.nis, lam, info, *self._position_info(out), int(self.measurement_update),
                           self._feedback, self._dev["p_col"], seeds, self.scheme, self._dev["pose"]],
                   outputs=[self._temper_partials, self._unpred_partials, self._temper_ess, self._chunk_max,
                            self._chunk_counts, self._chunk_min_nis, self._chunk_sums, self._stats,
                            self._kernel_chol, self._cdf_sums, self._cdf, self._ancestors, st.dp, st.lin, st.logw,
                            sp.dp, sp.lin, sp.logw, self._pos, self._quat, *self._mode_arrays(), self._more_stages],
                   block_dim=kmpf.STAGE_BLOCK_DIM, device=d)
            return
        if not d.is_cpu:
            launch(kmpf.temper_ess_kernel, dim=(b, kmpf.N_TEMPER), inputs=[self._temper_partials],
                   outputs=[self._temper_ess], block_dim=kmpf.WARP_LANES, device=d)
        launch(kmpf.temper_select_kernel, dim=b,
                  inputs=[n, stage, int(stage == self.max_stages - 1), self.params, out.meta, self._temper_ess,
                          self._unpred_partials], outputs=[self._stats], device=d)
        launch(kmpf.add_loglik_partials_kernel, dim=(b, kmpf.N_CHUNKS),
                  inputs=[n, out.loglik, out.n_valid, out.meta, self._stats, out.nis],
                  outputs=[st.logw, self._chunk_max, self._chunk_counts, self._chunk_min_nis], device=d)
        launch(kmpf.max_of_partials_kernel, dim=[b], inputs=[self._chunk_max, self._chunk_counts,
               self._chunk_min_nis], outputs=[self._stats], block_dim=kmpf.WARP_LANES, device=d)
        launch(kmpf.exp_partials_kernel, dim=(b, kmpf.N_CHUNKS),
                  inputs=[n, st.logw, st.dp, out.nis, lam, *self._position_info(out), self._stats],
                  outputs=[self._chunk_sums], device=d)
        launch(kmpf.weight_stats_kernel, dim=[b], inputs=[n, self.params, self._chunk_sums],
                        outputs=[self._stats, self._kernel_chol], block_dim=kmpf.N_CHUNKS, device=d)
        launch(kmpf.normalize_weights_kernel, dim=b * n, inputs=[n, self._stats], outputs=[st.logw], device=d)
        if self.measurement_update:
            launch(kmpf.kalman_update_kernel, dim=b * n,
                   inputs=[n, self.params, self._stats, self._feedback, self._dev["p_col"], lam, info],
                   outputs=[st.lin], device=d)

    def _position_info(self, out) -> tuple[int, wp.array]:
        """(1, the particles' horizontal position information) when the model gives it (one that cannot fix the
        position with one measurement: it then bounds the regularisation jitter,
        :data:`warptan.kernels.mpf.JITTER_NIS`), else (0, a one-element placeholder)."""
        info = getattr(out, "info_pos", None)
        if info is not None:
            return 1, info
        if self._no_pos_info is None:
            self._no_pos_info = wp.zeros(1, dtype=wp.vec3, device=self.device)
        return 0, self._no_pos_info

    def _attitude_info(self, out) -> tuple[wp.array, wp.array]:
        """The model's per-particle attitude information (Λ_i, b_i); zeros for a model that gives none."""
        if out.lam is not None and out.info is not None:
            return out.lam, out.info
        if self._no_info is None:
            nt = self.n_filters * self.n
            self._no_info = (wp.zeros(nt, dtype=wp.mat33, device=self.device),
                             wp.zeros(nt, dtype=wp.vec3, device=self.device))
        return self._no_info

    def _launch_resample(self, stage: int) -> None:
        """Resample and regularise the filters whose flags say so (device decisions; others are copied). The block
        form resampled in the stage's block (:data:`~warptan.kernels.mpf.stage_block_kernel`): only the map-error
        modes' gather is left then."""
        d, b, n, st, sp = self.device, self.n_filters, self.n, self.state, self._spare
        seeds = self._dev["resample_seeds"]
        if not self._block_stages:
            launch(kmpf.cdf_partials_kernel, dim=(b, kmpf.N_CHUNKS), inputs=[n, st.logw, self._stats],
                   outputs=[self._cdf_sums], device=d)
            launch(kmpf.cdf_kernel, dim=(b, kmpf.N_CHUNKS), inputs=[n, st.logw, self._stats, self._cdf_sums],
                   outputs=[self._cdf], device=d)
            launch(kmpf.ancestors_kernel, dim=b * n, inputs=[n, stage, seeds, self.scheme, self._stats, self._cdf],
                   outputs=[self._ancestors], device=d)
            launch(kmpf.gather_kernel, dim=b * n, inputs=[n, stage, seeds, self.params, self._stats, self._ancestors,
                   st.dp, st.lin, st.logw], outputs=[sp.dp, sp.lin, sp.logw], device=d)
            launch(kmpf.copy_particles_kernel, dim=b * n, inputs=[sp.dp, sp.lin, sp.logw],
                   outputs=[st.dp, st.lin, st.logw], device=d)
        if self._mode_table() is not None and not self._block_stages:
            post, spare = self._out.mode_post, self._mode_spare
            launch(kmpf.gather_modes_kernel, dim=b * n, inputs=[self._ancestors, self._mode_mean, post],
                   outputs=list(spare), device=d)
            launch(kmpf.copy_modes_kernel, dim=b * n, inputs=list(spare), outputs=[self._mode_mean, post], device=d)

    def _mode_table(self) -> wp.array | None:
        """The model's map-error mode table when its likelihood states a map error (else None: no mode state)."""
        table = getattr(self.model, "mode_table", None)
        return table if table is not None and self.model.likelihood.models_map_error else None

    def _mode_arrays(self) -> tuple:
        """The block kernels' map-error mode arguments: (1, the particles' stored means, the model's posteriors, their
        two spare arrays) when the model states a map error, else (0, four one-element placeholders)."""
        if self._mode_table() is not None:
            return 1, self._mode_mean, self._out.mode_post, *self._mode_spare
        return 0, *self._no_modes()

    def _no_modes(self) -> tuple[wp.array, ...]:
        """Four one-element placeholders for a block kernel's mode arrays (no map error stated: unread)."""
        if self._no_mode_arrays is None:
            self._no_mode_arrays = wp.zeros(1, dtype=klik.modes_vec, device=self.device)
        return (self._no_mode_arrays,) * 4

    def _launch_modes(self) -> None:
        """The particles' map-error mode prior for the next scan (after the integrity monitor's re-spread)."""
        table = self._mode_table()
        if table is None:
            return
        d, b, m = self.device, self.n_filters, table.shape[0] - klik.MODE_EXTRA_ROWS
        launch(kmpf.modes_finalize_kernel, dim=b * self.n,
               inputs=[self.n, m, table, self._stats, self._out.mode_post, self._mode_var], outputs=[self._mode_mean],
               device=d)
        launch(kmpf.modes_variance_kernel, dim=b, inputs=[m, table, self._stats], outputs=[self._mode_var], device=d)

    def _launch_integrity(self) -> None:
        d, b, n, st = self.device, self.n_filters, self.n, self.state
        launch(kmpf.integrity_kernel, dim=b, inputs=[self.params, self._stats, self._integrity],
               outputs=[self._kernel_chol], device=d)
        launch(kmpf.respread_kernel, dim=b * n,
                  inputs=[n, 2 * n * self.max_stages, self._dev["resample_seeds"], self.params, self._stats,
                          st.dp, st.logw], device=d)

    def _launch_record(self) -> None:
        d, b, st = self.device, self.n_filters, self.state
        launch(kmpf.summary_partials_kernel, dim=(b, kmpf.N_CHUNKS), inputs=[self.n, st.logw, st.dp, st.lin],
                  outputs=[self._summary_sums], device=d)
        launch(kmpf.summary_kernel, dim=[b],
                        inputs=[self.params, self._summary_sums, self._stats, self._integrity, self._slot],
                        outputs=[self._history, self._feedback], block_dim=kmpf.N_CHUNKS, device=d)
        self._launch_feedback()
        launch(kmpf.advance_slot_kernel, dim=1, inputs=[self._slot], outputs=[self._more_stages], device=d)

    def _launch_feedback(self) -> None:
        """What the update feeds back, on the device: the nominal's record, the Kalman measurement update of P, and
        in closed loop the injection into the nominal INS with the particles' reset."""
        d, b, st, nav = self.device, self.n_filters, self.state, self._nav
        launch(kmpf.covariance_update_kernel, dim=b,
                  inputs=[int(self.measurement_update), int(self.closed_loop), self._feedback, self._slot],
                  outputs=[nav["cov"], nav["pos"], nav["vel"], nav["quat"], nav["ba"], nav["bg"], self._injections,
                           self._nominal_hist, self._p_hist], device=d)
        if self.closed_loop:
            launch(kmpf.reset_kernel, dim=b * self.n, inputs=[self.n, self._feedback],
                      outputs=[st.dp, st.lin], device=d)

    def _device_update(self, out, read_flags: bool = False) -> None:
        """The device part of an update: move, then up to ``max_stages`` tempering stages (each after the first
        re-evaluates the model at the moved particles), the integrity monitor, the record. A stage after the
        first runs only when some filter still has exponent left: decided on the host when ``read_flags`` (free
        on the CPU, which runs launches in order), else by a device flag and a conditional node
        (``wp.capture_if``: no host sync, and in a captured graph a converged update costs one stage). Filters
        that are done ignore a stage that runs for the others, so both paths give the same result. The pieces
        between host decisions are fixed sequences (:meth:`_piece`)."""
        self._piece(("move", self._ahead_state()), self._launch_head)  # (the interval's launch differs by state)
        self._launch_model("model0")
        self._piece("weigh0", self._launch_weigh, out, 0)
        self._resample_if(stage=0, read_flags=read_flags)
        for stage in range(1, self.max_stages):
            if read_flags:
                if not (self._stats.numpy()[:, kmpf.ST_REMAIN] > 0).any():
                    break
                if not self._block_stages:  # (the block form's resampling wrote them)
                    self._piece(("poses", stage), self._launch_poses)
                self._launch_later_model(("model", stage))
                self._piece(("weigh", stage), self._launch_stage, out, stage)
                self._resample_if(stage=stage, read_flags=True)
            elif self._lean:
                self._stages_if(out, stage)
                break
            else:
                flag = self._stage_flags[stage]
                launch(kmpf.more_stages_kernel, dim=1, inputs=[self._stats], outputs=[flag], device=self.device)
                wp.capture_if(flag, on_true=self._extra_stage, out=out, stage=stage)
        self._piece("tail", self._launch_tail)

    def _stages_if(self, out, stage: int) -> None:
        """Stage ``stage`` and the later ones as nested conditionals: a later stage's test only runs when this one
        ran (a converged update pays one test, not ``max_stages - 1``)."""
        if stage >= self.max_stages:
            return
        flag = self._stage_flags[stage]
        if not self._block_stages:  # (the block form set it: :data:`~warptan.kernels.mpf.stage_block_kernel`)
            launch(kmpf.more_stages_kernel, dim=1, inputs=[self._stats], outputs=[flag], device=self.device)
        wp.capture_if(flag, on_true=self._stage_then_more, out=out, stage=stage)

    def _stage_then_more(self, out, stage: int) -> None:
        self._extra_stage(out, stage)
        self._stages_if(out, stage + 1)

    def _launch_head(self) -> None:
        if not self._lean:
            self._launch_move()
            self._launch_poses()
        elif not self._early:  # (early: queued before the scan was staged, :meth:`_queue_head`)
            self._launch_lean_head()

    def _launch_lean_head(self) -> None:
        """The interval, then the particles' moves, poses and the statistics' reset in one launch (none of which
        reads the scan)."""
        self._end_interval()
        dv, n, st = self._dev, self.n, self.state
        launch(kmpf.move_pose_kernel, dim=self.n_filters * n,
               inputs=[n, dv["seeds"], dv["phi"], dv["chol"], dv["pose"], self._exponent],
               outputs=[st.dp, st.lin, self._pos, self._quat, self._stats], device=self.device,
               spread=kmpf.MOVE_BLOCK_DIM)

    def _launch_model(self, key) -> None:
        """The model at the particles' poses: a recorded piece for a model that launches only through
        :mod:`warptan.parallel` (``recordable``), else launched anew."""
        if getattr(self.model, "recordable", False):
            self._piece(key, self.model.launch, self._pos, self._quat)
        else:
            self.model.launch(self._pos, self._quat)

    def _launch_later_model(self, key) -> None:
        """The model at a later tempering stage (``key``: its recorded piece, None: launched anew). It evaluates
        every filter of a batch; those already done keep their map-error mode posteriors from before it
        (:func:`~warptan.kernels.mpf.keep_done_modes_kernel`), as each would alone."""
        held = self._mode_spare[1] if self._mode_table() is not None and self.n_filters > 1 else None
        post = self._out.mode_post
        if held is not None:
            wp.copy(held, post)
        if key is None:
            self.model.launch(self._pos, self._quat)
        else:
            self._launch_model(key)
        if held is not None:
            launch(kmpf.keep_done_modes_kernel, dim=held.shape[0], inputs=[self.n, self._stats, held],
                   outputs=[post], device=self.device)

    def _launch_weigh(self, out, stage: int) -> None:
        if not self._lean:  # (lean: the head reset the statistics)
            launch(kmpf.begin_update_kernel, dim=self.n_filters, inputs=[self._exponent], outputs=[self._stats],
                   device=self.device)
        self._launch_stage(out, stage)

    def _extra_stage(self, out, stage: int) -> None:
        """A tempering stage after the first (graph path): poses (which the block form of the last resampling
        wrote) and model at the moved particles, weights, resampling."""
        if not self._block_stages:
            self._launch_poses()
        self._launch_later_model(None)
        self._launch_stage(out, stage)
        self._launch_resample(stage)

    def _resample_if(self, stage: int, read_flags: bool) -> None:
        """Resampling after a stage (skipped when ``read_flags`` shows no filter needs it)."""
        if not read_flags or self._stats.numpy()[:, kmpf.ST_RESAMPLE].any():
            self._piece(("resample", stage), self._launch_resample, stage)

    def _launch_tail(self) -> None:
        if not self._lean:
            self._launch_integrity()
            self._launch_modes()
            self._launch_record()
            return
        d, b, n, st, nav = self.device, self.n_filters, self.n, self.state, self._nav
        offset, seeds = 2 * n * self.max_stages, self._dev["resample_seeds"]
        table = self._mode_table()  # (the modes run in the block between the integrity monitor and the record)
        modes = (0, 0, *self._no_modes()) if table is None else (
            1, table.shape[0] - klik.MODE_EXTRA_ROWS, table, self._out.mode_post, self._mode_var, self._mode_mean)
        one = int(b == 1)  # (one filter: its block ends the update, no launch of its own)
        launch(kmpf.record_block_kernel, dim=[b],
               inputs=[n, self.params, int(self.measurement_update), int(self.closed_loop), offset, one, seeds,
                       self._kernel_chol, st.logw, self._stats, self._integrity, self._slot],
               outputs=[self._summary_sums, self._history, self._feedback, nav["cov"], nav["pos"], nav["vel"],
                        nav["quat"], nav["ba"], nav["bg"], self._injections, self._nominal_hist, self._p_hist, st.dp,
                        st.lin, *modes, self._more_stages], block_dim=kmpf.RECORD_BLOCK_DIM, device=d)
        if not one:
            launch(kmpf.advance_slot_kernel, dim=1, inputs=[self._slot], outputs=[self._more_stages], device=d)

    def _queue_update(self, out, staged=()) -> None:
        """The device work of an update: eager launches (the CPU replaying its recorded pieces) or the graph;
        ``staged``: the scan's copies and launches the model held (:meth:`MeasurementModel.hold_device_work`), queued
        first (in the graph: replayed from the same pinned buffers)."""
        if self._recorder is not None:
            key = self._record_key()
            if key != self._graph_key:  # re-record when an array the recorded launches hold was replaced
                self._recorder.clear()
                self._graph_key = key
        if not self.graph:
            self._staged_update(staged, out, read_flags=self.device.is_cpu)
            return
        if self._graph_key is None:  # the first update runs eagerly: modules load, buffers settle
            self._graph_key = ()
            self._staged_update(staged, out)
            return
        self._replay("update", self._staged_update, staged, out)

    def _staged_update(self, staged, out, read_flags: bool = False) -> None:
        """The scan's held device work (in order), then the update's."""
        for work in staged:
            work()
        self._device_update(out, read_flags=read_flags)

    def _queue_head(self) -> None:
        """The update's head alone (the lean update queues it before the scan is staged: the interval, the moves,
        the poses): launched, or its graph."""
        if not self.graph or self._graph_key is None:  # (the first update runs eagerly)
            self._launch_lean_head()
        else:
            self._replay("head", self._launch_lean_head)

    def _replay(self, name: str, fn, *args) -> None:
        """Launch the graph of ``fn(*args)`` for the current staging set (one per set: its copies read that set),
        captured at its first use; all graphs are dropped when a buffer they hold was replaced."""
        key = self._record_key()
        if key != self._graph_key:
            self._graphs.clear()
            self._graph_key = key
        slot = (name, self._set, self._ahead_state())  # (the interval's launch differs when samples ran ahead)
        graph = self._graphs.get(slot)
        if graph is None:
            wp.capture_begin(device=self.device)
            try:
                fn(*args)
            finally:
                graph = self._graphs[slot] = wp.capture_end(device=self.device)
        wp.capture_launch(graph)

    def _record_key(self) -> tuple:
        """The generation of everything the recorded launches (graphs or CPU recordings) hold: the filter's own
        arrays (replaced when the history grows), the model's buffers, likelihood struct and attitude covariance
        (``model.generation``, bumped by the model whenever it replaces one of them) and the update's switches. A
        recording of another key is stale and is dropped (identities of freed arrays could be reused: no ``id()``)."""
        return (self._generation, getattr(self.model, "generation", 0), self.measurement_update, self.closed_loop,
                self._early)
