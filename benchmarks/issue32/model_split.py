"""The scenario model's device time on CUDA split into its launches (S7: the ray casts, ``_launch_residuals``, and
their per-particle reduction, ``_launch_reduce``; S8: the fused sliding kernel), for one filter (B = 1, N = 500,
20 x 20 scan) at the poses of its 120th update: each piece captured 20 times in a graph, replayed between events;
medians over 30 replays of the time per piece (µs).

    python3 benchmarks/issue32/model_split.py scripts OUT.json S7 S8   (from a folder outside the checkout)
"""
import json
import statistics
import sys

import warp as wp

sys.path.insert(0, sys.argv[1])  # scripts/: bench_filter_step's scenario setup
import bench_filter_step as bfs

from warptan.device import quiet_warp


def piece_us(fn, device, reps: int = 20, replays: int = 30) -> float:
    fn()
    wp.synchronize_device(device)
    wp.capture_begin(device=device)
    for _ in range(reps):
        fn()
    graph = wp.capture_end(device=device)
    times = []
    for _ in range(replays):
        e0, e1 = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
        wp.get_stream(device).record_event(e0)
        wp.capture_launch(graph)
        wp.get_stream(device).record_event(e1)
        wp.synchronize_device(device)
        times.append(1e3 * wp.get_event_elapsed_time(e0, e1) / reps)
    return statistics.median(times)


def split(sid: str) -> dict:
    mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
    for _ in bfs.synchronised_steps(mpf, f, w, setup, 120):
        pass
    model, device, out = mpf.model, mpf.device, mpf.model._out
    pieces = {"model.launch": lambda: model.launch(mpf._pos, mpf._quat)}
    if hasattr(model, "_launch_residuals"):
        pieces["residuals"] = lambda: model._launch_residuals(mpf._pos, mpf._quat, out, device)
        pieces["reduce"] = lambda: model._launch_reduce(mpf._quat, out, device)
    return {name: piece_us(fn, device) for name, fn in pieces.items()}


def main():
    quiet_warp()
    res = {}
    for sid in sys.argv[3:]:
        res[sid] = split(sid)
        print(sid, json.dumps({k: round(v, 2) for k, v in res[sid].items()}))
    bfs.write_cuda_results(sys.argv[2], sys.argv, __doc__, res)


if __name__ == "__main__":
    main()
