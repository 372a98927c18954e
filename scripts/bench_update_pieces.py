"""Device time of each piece of one filter's measurement update on CUDA, warm, as the update's graph runs it: the head
(interval, moves, poses), the model (a ray-casting model's two kernels also apart), a tempering stage with its
resampling (one block per filter: candidates' partials, exponent, weights, resampling, poses), the tail (integrity,
record, slot), and the whole update graph. Each piece is captured ``--reps`` times in a row in one graph, replayed
``--repeats`` times between events; the median per piece is reported (µs). A piece repeated on its own output does the
same work as in an update (stage 0 is always active; a resampling copies the particles whether or not it draws).

    python scripts/bench_update_pieces.py --scenario S8 S7 --json pieces.json     (a CUDA device)
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

import numpy as np
import warp as wp

from warptan.cli import count_arg
from warptan.device import quiet_warp
from warptan.meta import run_meta


def _filter(sid: str, device: str):
    import bench_filter_step as bfs

    mpf, f, w, setup = bfs.scenario_filter(sid, device)
    truth = setup["truth"]
    ipm, rng = setup["imu_per_meas"], np.random.default_rng(1)
    scan = None
    for it in range(30):
        k = it * ipm
        scan = setup["sensor"].measure(setup["world"], truth.pos_n[k + ipm], truth.quat_nb[k + ipm], rng)
        mpf.predict_many(f[k:k + ipm], w[k:k + ipm])
        mpf.update(scan, sync=False)
    wp.synchronize_device(device)
    mpf.predict_many(f[30 * ipm:31 * ipm], w[30 * ipm:31 * ipm])
    mpf._stage_interval()
    mpf._early = False
    return mpf, mpf.model.stage(scan, mpf._pos, mpf._quat)


def _time(fn, device, reps: int, repeats: int) -> float:
    """Median µs per call of ``fn`` captured ``reps`` times in one graph."""
    fn()
    wp.capture_begin(device=device)
    try:
        for _ in range(reps):
            fn()
    finally:
        graph = wp.capture_end(device=device)
    stream = wp.get_stream(device)
    times = []
    for _ in range(repeats):
        start, end = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
        stream.record_event(start)
        wp.capture_launch(graph)
        stream.record_event(end)
        wp.synchronize_event(end)
        times.append(1e3 * wp.get_event_elapsed_time(start, end) / reps)
    return statistics.median(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", nargs="+", default=["S8", "S7"])
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--reps", type=count_arg, default=50)
    parser.add_argument("--repeats", type=count_arg, default=20)
    parser.add_argument("--json", dest="json_out")
    args = parser.parse_args(argv)
    quiet_warp()
    if not wp.get_device(args.device).is_cuda:
        print("bench_update_pieces: error: needs a CUDA device", file=sys.stderr)
        return 2
    rows = []
    for sid in args.scenario:
        mpf, out = _filter(sid, args.device)
        pieces = {
            "head (interval, moves, poses)": mpf._launch_lean_head,
            "poses": mpf._launch_poses,
            "model": lambda m=mpf: m.model.launch(m._pos, m._quat),
            "tempering stage and resampling (one block)": lambda m=mpf, o=out: (m._launch_stage(o, 0),
                                                                                 m._launch_resample(0)),
            "tail (integrity, record, slot)": mpf._launch_tail,
            "whole update (device program)": lambda m=mpf, o=out: m._device_update(o),
        }
        if hasattr(mpf.model, "_launch_residuals"):  # a ray-casting model: its two kernels apart
            dev = wp.get_device(args.device)
            pieces["model: the ray casts"] = lambda m=mpf, o=out, d=dev: m.model._launch_residuals(m._pos, m._quat,
                                                                                                      o, d)
            pieces["model: the per-particle reduction"] = lambda m=mpf, o=out, d=dev: m.model._launch_reduce(m._quat,
                                                                                                            o, d)
        row = {"scenario": sid, "B": 1, "N": mpf.n, "M": int(out.residual_m.shape[1]), "lean": mpf._lean,
               "pieces_us": {name: _time(fn, args.device, args.reps, args.repeats) for name, fn in pieces.items()}}
        rows.append(row)
        print(sid, json.dumps({k: round(v, 1) for k, v in row["pieces_us"].items()}))
    if args.json_out:
        with open(args.json_out, "w") as fh:
            json.dump({"meta": run_meta([args.device], command=" ".join(["bench_update_pieces.py", *sys.argv[1:]]),
                                        what=__doc__.split("\n\n")[0]), "rows": rows}, fh, indent=1)
        print(f"wrote {args.json_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
