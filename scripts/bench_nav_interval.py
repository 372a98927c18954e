#!/usr/bin/env python3
"""Device time of the nav interval kernel alone (:mod:`warptan.kernels.nav`: nominal INS, Riccati, the interval's Φ
and chol S) for K IMU samples and B filters, in both forms: ``tiled`` (one CUDA block per filter, what the filter
launches on CUDA) and ``thread`` (one thread per filter, the CPU's form). Each timing is one launch captured in a
graph and replayed 20 times between two events (the device's time, not the host's launch), the median of 20 such.

    python scripts/bench_nav_interval.py --device cuda:0 --json nav_interval.json
"""

from __future__ import annotations

import argparse
import json
import statistics

import numpy as np
import warp as wp

import warptan as wt
from warptan.kernels import nav as knav
from warptan.meta import run_meta


def _arrays(b: int, k: int, device):
    """Inputs and outputs of one launch: a level flight at 100 m/s, 1 km up, a slow turn, a diagonal P."""
    p0 = np.diag(np.r_[np.full(3, 0.01), np.full(3, 1e-6), np.full(3, 1e-4), np.full(3, 1e-8)])
    imu = np.zeros((b, max(k, 1), 3, 3))
    imu[:, :, 0] = [0.1, 0.2, -9.8]
    imu[:, :, 1] = [0.01, -0.02, 0.03]
    imu[:, :, 2, 0] = 0.01
    d = device
    inputs = [0, 1, 1, 0, wp.zeros((b, 2), dtype=wp.float64, device=d),
              wp.array(np.full((b, knav.N_INTS), k, dtype=np.int32), dtype=wp.int32, device=d), 0.01,
              wp.full(b, 0.0025, dtype=wp.float64, device=d), 0.0, wp.vec4d(1e-6, 1e-10, 1e-10, 1e-14),
              wp.zeros(b, dtype=wp.float64, device=d), wp.array(imu, dtype=wp.vec3d, device=d),
              wp.array(np.tile([0.0, 0.0, -1000.0], (b, 1)), dtype=wp.vec3d, device=d),
              wp.array(np.tile([100.0, 0.0, 0.0], (b, 1)), dtype=wp.vec3d, device=d),
              wp.array(np.tile([1.0, 0.0, 0.0, 0.0], (b, 1)), dtype=wp.vec4d, device=d),
              wp.zeros(b, dtype=wp.vec3d, device=d), wp.zeros(b, dtype=wp.vec3d, device=d),
              wp.array(np.stack([p0] * b).reshape(b, 4, 3, 4, 3).transpose(0, 1, 3, 2, 4).copy(), dtype=wp.mat33d,
                       device=d),
              wp.empty((b, 5, 5), dtype=wp.mat33d, device=d), wp.empty((b, 5, 5), dtype=wp.mat33d, device=d),
              wp.empty((b, 15, 15), dtype=wp.float64, device=d)]
    outputs = [wp.empty((b, 5, 5), dtype=wp.mat33, device=d), wp.empty((b, 5, 5), dtype=wp.mat33, device=d),
               wp.empty((b, 7), dtype=wp.float64, device=d), wp.empty(b, dtype=wp.mat33, device=d),
               wp.empty((b, 4), dtype=wp.mat33, device=d)]
    return inputs, outputs


def time_launch(b: int, k: int, tiled: bool, device) -> float:
    inputs, outputs = _arrays(b, k, device)

    def go():
        if tiled:
            wp.launch_tiled(knav.nav_interval_kernels[True], dim=[b], inputs=inputs, outputs=outputs,
                            block_dim=knav.NAV_BLOCK_DIM, device=device)
        else:
            wp.launch(knav.nav_interval_kernels[False], dim=b, inputs=inputs, outputs=outputs, device=device)

    for _ in range(3):
        go()
    wp.synchronize_device(device)
    wp.capture_begin(device=device)
    go()
    graph = wp.capture_end(device=device)
    stream = wp.get_stream(device)
    times = []
    for _ in range(20):
        start, stop = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
        stream.record_event(start)
        for _ in range(20):
            wp.capture_launch(graph)
        stream.record_event(stop)
        wp.synchronize_event(stop)
        times.append(wp.get_event_elapsed_time(start, stop) / 20)
    return statistics.median(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda:0", help="a CUDA device (the tiled form needs one)")
    parser.add_argument("--json", dest="json_out", default=None)
    args = parser.parse_args(argv)
    device = wt.resolve_device(args.device)
    if not device.is_cuda:
        parser.error(f"--device {args.device}: the nav interval's tiled form runs on a CUDA device")
    rows = []
    for b, k in ((1, 0), (1, 1), (1, 10), (100, 10)):
        for tiled in (True, False):
            ms = time_launch(b, k, tiled, device)
            rows.append({"B": b, "K": k, "form": "tiled" if tiled else "thread", "device_ms": ms})
            print(f"B={b:4d} K={k:3d} {rows[-1]['form']:7s} {ms:.4f} ms")
    if args.json_out:
        meta = run_meta(args.device, what="device ms of one nav_interval_kernel launch (K IMU samples, B filters): "
                        "median of 20 x (20 graph replays between two events)")
        with open(args.json_out, "w") as fh:
            json.dump({"meta": meta, "results": rows}, fh, indent=1)
        print(f"wrote {args.json_out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
