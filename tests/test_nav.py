"""The host navigation kernel (nominal INS + Riccati + interval composition) against the float64 Python path."""

import numpy as np
import pytest
import warp as wp

from warptan.filter.prior import InitialErrors, initial_nominal, prior_linear_cov
from warptan.kernels import nav as knav
from warptan.nav.imu import ImuModel
from warptan.nav.ins import error_transition, mechanize, process_noise
from warptan.nav.trajectory import Straight, Trajectory, Turn


def _python_interval(nominal, f, w, dt, P, q_n, q_l, steps=None):
    """Reference: the MPF Riccati of design notes §6 step by step, and Φ, S composed from the 15×15 transitions
    (``steps``: each sample's own step, the noise scaled by ``step / dt``)."""
    state = nominal.copy()
    steps = np.full(len(f), dt) if steps is None else steps
    phi, S = np.eye(15), np.zeros((15, 15))
    for k in range(len(f)):
        h = steps[k]
        F = error_transition(state, f[k], w[k], h)
        a_n, a_l = F[0:3, 3:15], F[3:15, 3:15]
        pa = P @ a_n.T
        n_k = a_n @ pa + q_n * (h / dt)
        gain = np.linalg.solve(n_k, (a_l @ pa).T).T
        P = a_l @ P @ a_l.T + q_l * (h / dt) - gain @ n_k @ gain.T
        P = 0.5 * (P + P.T)
        T = np.eye(15)
        T[0:3, 3:15] = a_n
        T[3:15, 3:15] = a_l
        G = np.vstack([np.eye(3), gain])
        phi = T @ phi
        S = T @ S @ T.T + G @ n_k @ G.T
        state = mechanize(state, f[k], w[k], h)
    return state, P, phi, S


def _blocks(a):
    """(B, 5, 5, 3, 3) blocks -> (B, 15, 15)."""
    b = a.shape[0]
    return a.transpose(0, 1, 3, 2, 4).reshape(b, a.shape[1] * 3, a.shape[2] * 3)


def test_nav_kernel_split_interval_same_bits(device):
    """An interval run as several launches (the samples buffered so far, then the rest; ``begin``/``keep``, as
    ``predict_many`` runs them ahead on CUDA), each writing the outputs as the interval stands (``finish``) or not,
    gives the bits of one launch: nominal, P, Φ, chol S and the outputs the update reads, in both forms (one thread
    per filter; on CUDA also the block of lanes)."""
    forms = (False, True) if wp.get_device(device).is_cuda else (False,)
    rate, k_steps, d, B = 100.0, 10, device, 2
    dt = 1.0 / rate
    truth = Trajectory.build([Straight(0.05), Turn(20, bank_deg=30)], rate, [0, 0, -1000.0])
    imu = ImuModel("tactical", rate, seed=3)
    f, w, _ = imu.corrupt(truth.f_b[:2 * k_steps], truth.w_b[:2 * k_steps])
    samples = np.zeros((B, k_steps, 3, 3))
    samples[:, :, 0] = np.stack([f[:k_steps], f[k_steps:]])
    samples[:, :, 1] = np.stack([w[:k_steps], w[k_steps:]])
    samples[:, :, 2, 0] = dt * (1.0 + 0.4 * np.sin(np.arange(k_steps)))
    initial = InitialErrors()
    P0 = prior_linear_cov(initial, imu)
    nominals = [initial_nominal(truth.state(0), initial, np.random.default_rng(b)) for b in range(B)]
    q_l = np.diag(process_noise(imu.grade, dt)[3:15, 3:15])
    for tiled in forms:
        results = []
        for splits, ahead in (((k_steps,), 0), ((4, k_steps), 0), ((0, 3, 7, 7, k_steps), 0),
                              ((4, k_steps), 1), ((0, 3, 7, 7, k_steps), 1)):
            nav = [wp.array([n.pos_n for n in nominals], dtype=wp.vec3d, device=d),
                   wp.array([n.vel_n for n in nominals], dtype=wp.vec3d, device=d),
                   wp.array([n.quat_nb for n in nominals], dtype=wp.vec4d, device=d),
                   wp.zeros(B, dtype=wp.vec3d, device=d), wp.zeros(B, dtype=wp.vec3d, device=d),
                   wp.array(np.stack([P0] * B).reshape(B, 4, 3, 4, 3).transpose(0, 1, 3, 2, 4).copy(),
                            dtype=wp.mat33d, device=d),
                   wp.empty((B, 5, 5), dtype=wp.mat33d, device=d), wp.empty((B, 5, 5), dtype=wp.mat33d, device=d),
                   wp.empty((B, 15, 15), dtype=wp.float64, device=d)]
            outs = [wp.zeros((B, 5, 5), dtype=wp.mat33, device=d), wp.zeros((B, 5, 5), dtype=wp.mat33, device=d),
                    wp.zeros((B, 7), dtype=wp.float64, device=d), wp.zeros(B, dtype=wp.mat33, device=d),
                    wp.zeros((B, 4), dtype=wp.mat33, device=d)]
            progress = wp.zeros((B, 2), dtype=wp.float64, device=d)
            for i, upto in enumerate(splits):
                counts = wp.array(np.full((B, 3), upto, dtype=np.int32), dtype=wp.int32, device=d)
                last = i == len(splits) - 1
                inputs = [0, int(i == 0), int(last or ahead), int(not last), progress, counts, dt,
                          wp.full(B, 0.25 * dt, dtype=wp.float64, device=d), 1e-4, wp.vec4d(*q_l[[0, 3, 6, 9]]),
                          wp.zeros(B, dtype=wp.float64, device=d), wp.array(samples, dtype=wp.vec3d, device=d), *nav]
                if tiled:
                    wp.launch_tiled(knav.nav_interval_kernels[True], dim=[B], inputs=inputs, outputs=outs,
                                    block_dim=knav.NAV_BLOCK_DIM, device=d)
                else:
                    wp.launch(knav.nav_interval_kernels[False], dim=B, inputs=inputs, outputs=outs, device=d)
            results.append([a.numpy() for a in (*nav[:6], *outs)])
        for other in results[1:]:
            for one, split in zip(results[0], other, strict=True):
                np.testing.assert_array_equal(one, split)


@pytest.mark.parametrize("uneven", [False, True])
def test_nav_kernel_matches_python(device, uneven):
    """The interval kernel (nominal INS, Riccati, interval composition; float64 on the filter's device) against
    the Python INS and a NumPy Riccati, on the CPU and on CUDA (one thread per filter, and the block of lanes per
    filter the filter launches there); evenly spaced samples and samples with their own steps (a recorded flight's
    jitter, ±40 %)."""
    for tiled in (False, True) if wp.get_device(device).is_cuda else (False,):
        _check_nav_kernel(device, uneven, tiled)


def _check_nav_kernel(device, uneven, tiled):
    rate, k_steps = 100.0, 10
    dt = 1.0 / rate
    truth = Trajectory.build([Straight(0.05), Turn(20, bank_deg=30)], rate, [0, 0, -1000.0])
    imu = ImuModel("tactical", rate, seed=3)
    initial = InitialErrors()
    rng = np.random.default_rng(0)
    nominals = [initial_nominal(truth.state(0), initial, rng) for _ in range(2)]
    f, w, _ = imu.corrupt(truth.f_b[:2 * k_steps], truth.w_b[:2 * k_steps])
    fb = np.stack([f[:k_steps], f[k_steps:]])
    wb = np.stack([w[:k_steps], w[k_steps:]])
    P0 = prior_linear_cov(initial, imu)
    q_n = 0.25 * dt * np.eye(3)
    q_l = process_noise(imu.grade, dt)[3:15, 3:15]
    q_vel_down = 0.1  # a map-error offset's vertical-velocity noise, m²/s³ (added to Q^l's down velocity)
    d = device
    B = 2
    pos = wp.array([n.pos_n for n in nominals], dtype=wp.vec3d, device=d)
    vel = wp.array([n.vel_n for n in nominals], dtype=wp.vec3d, device=d)
    quat = wp.array([n.quat_nb for n in nominals], dtype=wp.vec4d, device=d)
    ba = wp.zeros(B, dtype=wp.vec3d, device=d)
    bg = wp.zeros(B, dtype=wp.vec3d, device=d)
    cov = wp.array(np.stack([P0, P0]).reshape(B, 4, 3, 4, 3).transpose(0, 1, 3, 2, 4).copy(), dtype=wp.mat33d,
                   device=d)
    phi = wp.empty((B, 5, 5), dtype=wp.mat33d, device=d)
    noise = wp.empty((B, 5, 5), dtype=wp.mat33d, device=d)
    scratch = wp.empty((B, 15, 15), dtype=wp.float64, device=d)
    phi_out = wp.empty((B, 5, 5), dtype=wp.mat33, device=d)
    chol_out = wp.empty((B, 5, 5), dtype=wp.mat33, device=d)
    pose_out = wp.empty((B, 7), dtype=wp.float64, device=d)
    att_cov = wp.empty(B, dtype=wp.mat33, device=d)
    p_col = wp.empty((B, 4), dtype=wp.mat33, device=d)
    qd = np.diag(q_l)
    steps = dt * (1.0 + 0.4 * np.sin(np.arange(2 * k_steps))) if uneven else np.full(2 * k_steps, dt)
    step_col = np.zeros((B, k_steps, 3))
    step_col[:, :, 0] = steps.reshape(B, k_steps)
    counts = wp.array(np.full((B, 3), k_steps, dtype=np.int32), dtype=wp.int32, device=d)
    kernel = knav.nav_interval_kernels[tiled]
    launch = wp.launch_tiled if tiled else wp.launch
    extra = {"block_dim": knav.NAV_BLOCK_DIM} if tiled else {}
    launch(kernel, dim=[B], **extra,
           inputs=[0, 1, 1, 0, wp.zeros((B, 2), dtype=wp.float64, device=d), counts, dt,
                   wp.full(B, 0.25 * dt, dtype=wp.float64, device=d), 0.0,
                   wp.vec4d(qd[0], qd[3], qd[6], qd[9]), wp.full(B, q_vel_down * dt, dtype=wp.float64, device=d),
                   wp.array(np.stack([fb, wb, step_col], axis=2), dtype=wp.vec3d, device=d),
                   pos, vel, quat, ba, bg, cov, phi, noise, scratch],
           outputs=[phi_out, chol_out, pose_out, att_cov, p_col], device=d)
    covs = _blocks(cov.numpy())
    phis = _blocks(phi_out.numpy().astype(np.float64))
    chols = _blocks(chol_out.numpy().astype(np.float64))
    for b in range(B):
        state, P, phi_ref, S_ref = _python_interval(nominals[b], fb[b], wb[b], dt, P0.copy(), q_n,
                                                    q_l + np.diag(np.r_[0.0, 0.0, q_vel_down * dt, np.zeros(9)]),
                                                    steps[b * k_steps:(b + 1) * k_steps])
        np.testing.assert_allclose(pos.numpy()[b], state.pos_n, rtol=0, atol=1e-9)
        np.testing.assert_allclose(vel.numpy()[b], state.vel_n, rtol=0, atol=1e-11)
        np.testing.assert_allclose(quat.numpy()[b], state.quat_nb, rtol=0, atol=1e-13)
        np.testing.assert_allclose(pose_out.numpy()[b], np.r_[state.pos_n, state.quat_nb], atol=1e-9)
        np.testing.assert_allclose(covs[b], P, rtol=1e-9, atol=1e-18)
        np.testing.assert_allclose(phis[b], phi_ref, rtol=1e-6, atol=1e-7)
        S_got = chols[b] @ chols[b].T
        scale = np.sqrt(np.outer(np.diag(S_ref), np.diag(S_ref)))
        assert np.all(np.abs(S_got - S_ref) <= 2e-3 * scale + 1e-30), np.max(np.abs(S_got - S_ref) / (scale + 1e-30))
        assert np.allclose(np.triu(chols[b], 1), 0.0)
        np.testing.assert_allclose(att_cov.numpy()[b], P[3:6, 3:6], rtol=1e-6, atol=1e-30)
        np.testing.assert_allclose(np.concatenate(list(p_col.numpy()[b])), P[:, 3:6], rtol=1e-6, atol=1e-30)
