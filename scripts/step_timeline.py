#!/usr/bin/env python3
"""Where a synchronised filter step of a scenario goes on CUDA, B = 1: host time stamps and device events along the
step (``predict_many`` of the interval's samples, then ``update``), medians over traced steps.

Every other step is traced: the filter's methods are wrapped to stamp the host clock (``time.perf_counter``) and to
record CUDA events around the run-ahead of the interval's samples (``_advance``, in ``predict_many``: the nav
interval's graph), around the update's head (``_queue_head``) and around the update's graph (``_queue_update``), and
host stamps around the measurement's ``check`` and the scan's staging (``model.stage``); device times are event times
after an event recorded at the step's start on an idle device (an event ``*_end`` is when the device finished what was
queued before it), host times are from that start. The untraced steps between give ``untraced_step`` (what the tracing
costs is the difference to ``sync_return``). All values in µs.

    python scripts/step_timeline.py --device cuda:0 --scenario S8 S7 --json step_timeline.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np
import warp as wp

import warptan as wt
from warptan.meta import run_meta


def timeline(sid: str, device: str, steps: int, n: int, scan_side: int) -> dict:
    import bench_filter_step as bfs  # (this folder: the scenario's own filter, as the step benchmark builds it)

    mpf, f, w, setup = bfs.scenario_filter(sid, device, n=n, scan_side=scan_side)
    truth, ipm = setup["truth"], setup["imu_per_meas"]
    rng = np.random.default_rng(1)
    warm = 100
    if len(truth.f_b) < (warm + steps + 1) * ipm + 1:
        raise SystemExit(f"step_timeline: error: the flight of {sid} is too short for {steps} steps")
    scans = [setup["sensor"].measure(setup["world"], truth.pos_n[(it + 1) * ipm], truth.quat_nb[(it + 1) * ipm], rng)
             for it in range(warm + steps)]
    stream = wp.get_stream(device)
    marks: dict = {}

    def stamp(name, event=False):
        e = None
        if event:
            e = wp.Event(device, enable_timing=True)
            stream.record_event(e)
        marks[name] = (time.perf_counter(), e)

    cls, model_cls = type(mpf), type(mpf.model)
    plain = (cls._queue_head, cls._queue_update, model_cls.stage, cls._advance, model_cls.check)

    def queue_head(self):
        stamp("head_start", True)
        plain[0](self)
        stamp("head_end", True)

    def queue_update(self, *args):
        stamp("main_start", True)
        plain[1](self, *args)
        stamp("main_end", True)

    def stage(self, *args, **kwargs):
        stamp("stage_start")
        out = plain[2](self, *args, **kwargs)
        stamp("stage_end")
        return out

    def advance(self):
        stamp("advance_start", True)
        plain[3](self)
        stamp("advance_end", True)

    def check(self, *args, **kwargs):
        stamp("check_start")
        plain[4](self, *args, **kwargs)
        stamp("check_end")

    wrapped = (queue_head, queue_update, stage, advance, check)

    def use(fns):
        cls._queue_head, cls._queue_update, model_cls.stage, cls._advance, model_cls.check = fns

    rows, untraced = [], []
    try:
        for it in range(warm + steps):
            k = it * ipm
            traced = it >= warm and it % 2 == 0
            use(wrapped if traced else plain)
            wp.synchronize_device(device)
            marks.clear()
            t0 = time.perf_counter()
            if traced:
                stamp("start", True)
            mpf.predict_many(f[k:k + ipm], w[k:k + ipm])
            t1 = time.perf_counter()
            mpf.update(scans[it], sync=False)
            t2 = time.perf_counter()
            wp.synchronize_device(device)
            t3 = time.perf_counter()
            if it < warm:
                continue
            if not traced:
                untraced.append(t3 - t0)
                continue
            row = {"host_predict_done": t1 - t0, "host_update_done": t2 - t0, "host_sync_return": t3 - t0}
            e0 = marks["start"][1]
            for name, (th, e) in marks.items():
                if name == "start":
                    continue
                row["host_" + name] = th - t0
                if e is not None:
                    row["device_" + name] = 1e-3 * wp.get_event_elapsed_time(e0, e)
            rows.append(row)
    finally:
        use(plain)
    keys = sorted({k for r in rows for k in r})
    med = {k: 1e6 * statistics.median([r[k] for r in rows if k in r]) for k in keys}
    med["untraced_step"] = 1e6 * statistics.median(untraced)
    return dict(sorted(med.items(), key=lambda kv: kv[1]))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda:0", help="a CUDA device (the timeline reads CUDA events)")
    parser.add_argument("--scenario", nargs="+", default=["S8", "S7"])
    parser.add_argument("--steps", type=int, default=300, help="steps after 100 warm-up steps (half traced)")
    parser.add_argument("--n", type=int, default=500)
    parser.add_argument("--scan-side", type=int, default=20)
    parser.add_argument("--json", dest="json_out")
    args = parser.parse_args(argv)
    device = wt.resolve_device(args.device)
    if not device.is_cuda:
        parser.error(f"--device {args.device}: the timeline records CUDA events; give a CUDA device")
    if args.steps < 2:
        parser.error(f"--steps must be at least 2, got {args.steps}")
    out = {}
    for sid in args.scenario:
        out[sid] = timeline(sid, args.device, args.steps, args.n, args.scan_side)
        print(sid, " ".join(f"{k}={v:.1f}" for k, v in out[sid].items()))
    if args.json_out:
        meta = run_meta(args.device, command=" ".join(["step_timeline.py", *(argv or sys.argv[1:])]),
                        what="median µs from a synchronised step's start (an idle device): host stamps and device "
                             "events of every other step; untraced_step: the steps between, untraced")
        with open(args.json_out, "w") as fh:
            json.dump({"meta": meta, "results": out}, fh, indent=1)
        print(f"wrote {args.json_out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
