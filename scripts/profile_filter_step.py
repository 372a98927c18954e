#!/usr/bin/env python3
"""Per-kernel device time of a whole filter step (eager launches, Warp's CUDA activity timer): which kernels bound
the step. CUDA only (the timer records CUDA kernels).

    python scripts/profile_filter_step.py --model dda --likelihood gaussian paper --m-side 20 --json OUT.json
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import warp as wp

import warptan as wt
from warptan.meta import run_meta
from warptan.outputs import write_json

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_filter_step import MODELS, bench


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--model", default="dda", choices=MODELS)
    parser.add_argument("--likelihood", nargs="+", default=["gaussian"], choices=["paper", "gaussian", "student_t"])
    parser.add_argument("--n", type=int, default=500)
    parser.add_argument("--batch", type=int, default=1, help="filters per batch B")
    parser.add_argument("--m-side", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=300)
    parser.add_argument("--top", type=int, default=15)
    parser.add_argument("--json", dest="json_out")
    args = parser.parse_args(argv)
    if not wt.resolve_device(args.device).is_cuda:
        print("profile_filter_step: error: needs a CUDA device (the timer records CUDA kernels)", file=sys.stderr)
        return 2
    terrain = wt.Terrain.synthetic("rugged")
    rows = []
    for lik in args.likelihood:
        bench(terrain, args.model, args.n, args.m_side, args.device, 3, args.warmup, graph=False, likelihood=lik,
              batch=args.batch)
        with wp.ScopedTimer("step", cuda_filter=wp.TIMING_KERNEL, print=False, synchronize=True) as timer:
            r = bench(terrain, args.model, args.n, args.m_side, args.device, args.repeats, args.warmup, graph=False,
                      likelihood=lik, batch=args.batch)
        steps = 2 * (args.repeats + args.warmup)  # bench runs every interval twice: latency, then throughput
        total, calls = collections.defaultdict(float), collections.Counter()
        for res in timer.timing_results:  # elapsed in ms
            name = res.name.replace("forward kernel ", "").rsplit("_", 1)[0]
            total[name] += res.elapsed
            calls[name] += 1
        kernels = [{"kernel": k, "us_per_step": 1e3 * v / steps, "calls_per_step": calls[k] / steps}
                   for k, v in sorted(total.items(), key=lambda kv: -kv[1])]
        rows.append({"likelihood": lik, "eager_step_ms": r["step_ms"], "stages": r["tempering_stages_mean"],
                     "kernels": kernels})
        print(f"{lik}: eager step {r['step_ms']:.3f} ms, {r['tempering_stages_mean']:.2f} stages per update")
        for k in kernels[: args.top]:
            print(f"  {k['kernel']:32s} {k['us_per_step']:9.1f} µs/step  {k['calls_per_step']:4.1f} calls")
    if args.json_out:
        meta = run_meta(args.device, model=args.model, B=args.batch, N=args.n, M=args.m_side**2,
                        what="device time per kernel per step (all steps incl. warm-up; estimate() kernels included)")
        write_json(args.json_out, {"meta": meta, "results": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
