"""One campaign file on several engine / GPU configurations: are the rows identical, how long does each take, how
many batches ran at once. Each configuration is a ``warptan campaign`` process of its own (with
``CUDA_VISIBLE_DEVICES`` set when it names GPUs), after one unmeasured warm-up that compiles the kernels.

    python scripts/campaign_engines.py campaigns/example_quick.toml --json results/campaign_engines_cpu.json
    python scripts/campaign_engines.py campaigns/example.toml --device cuda --configs local:0 ray:0 ray:0,1 \
        --json results/campaign_engines_2gpu.json

A configuration is ``ENGINE`` or ``ENGINE:GPUS`` (``ray:0,1``: a local Ray cluster that sees GPUs 0 and 1). With
``--device cuda`` the local engine runs on ``cuda:0`` of what it sees and Ray gives each task one GPU.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from warptan.cli import count_arg
from warptan.device import quiet_warp
from warptan.outputs import write_json
from warptan.sim.campaign import Campaign

CLI = "import sys; sys.path.pop(0); from warptan.cli import main; sys.exit(main())"
"""``warptan`` with the current directory off the import path (as the installed console script runs)."""
WARMUP = """
import sys; sys.path.pop(0)
from warptan.sim.campaign import Campaign
from warptan.sim.campaign_run import run_batch
from warptan.device import quiet_warp
quiet_warp()
c = Campaign.load(sys.argv[1]); c.check("cpu")
for b in c.batches:  # every kernel each batch uses, compiled once (2 s flights, one seed)
    run_batch({**b.spec(), "seeds": [b.seeds[0]], "overrides": {**b.overrides, "duration_s": 2.0},
               "batched": True}, sys.argv[2])
"""


def max_concurrent(tasks: list[dict]) -> int:
    """Most tasks running at one instant (from their start and end times)."""
    events = sorted([(t["start_unix"], 1) for t in tasks] + [(t["end_unix"], -1) for t in tasks],
                    key=lambda e: (e[0], e[1]))
    now = best = 0
    for _, step in events:
        now += step
        best = max(best, now)
    return best


def run_config(config: str, campaign: Path, device: str, folder: Path, cpus_per_task: int) -> dict:
    engine, _, gpus = config.partition(":")
    env = dict(os.environ)
    if gpus:
        env["CUDA_VISIBLE_DEVICES"] = gpus
    dev = ("cuda:0" if engine == "local" else "cuda") if device == "cuda" else device
    out = folder / config.replace(":", "_").replace(",", "-")
    cmd = [sys.executable, "-c", CLI, "campaign", str(campaign), "--engine", engine, "--device", dev, "--out",
           str(out), "--quiet", "--no-plots", "--cpus-per-task", str(cpus_per_task)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    process_s = time.perf_counter() - t0
    result = {"config": config, "engine": engine, "cuda_visible_devices": gpus or None, "device": dev,
              "exit_code": proc.returncode, "process_s": process_s}
    if not (out / "campaign.json").exists():
        result["error"] = proc.stderr.strip()[-2000:]
        return result
    data = json.loads((out / "campaign.json").read_text())
    tasks = data["meta"]["tasks"]
    first = min((t["start_unix"] for t in tasks), default=0.0)
    span = max((t["end_unix"] for t in tasks), default=0.0) - first
    result.update({
        "wall_s": data["meta"]["wall_s"], "batches": data["meta"]["batches"], "failures": data["failures"],
        "max_concurrent_batches": max_concurrent(tasks),
        "tasks_span_s": span, "batch_s_sum": sum(t["wall_s"] for t in tasks),
        "timeline": [{"batch": t["batch"], "device": t["device"], "pid": t["pid"],
                      "start_s": t["start_unix"] - first, "end_s": t["end_unix"] - first} for t in tasks],
        "devices": sorted({f"{t['host']} {t['device']} CUDA_VISIBLE_DEVICES={t.get('cuda_visible_devices')} "
                           f"({t['device_name']})" for t in tasks}),
        "batch_wall_s": sorted(t["wall_s"] for t in tasks), "rows": data["rows"],
    })
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("campaign", type=Path)
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--configs", nargs="+", default=["local", "ray"])
    parser.add_argument("--cpus-per-task", type=count_arg, default=1)
    parser.add_argument("--no-warmup", action="store_true")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    quiet_warp()
    Campaign.load(args.campaign)  # a bad file: one error before anything runs
    with tempfile.TemporaryDirectory() as tmp:
        if not args.no_warmup:
            t0 = time.perf_counter()
            env = dict(os.environ)
            first_gpus = args.configs[0].partition(":")[2]
            if first_gpus:
                env["CUDA_VISIBLE_DEVICES"] = first_gpus
            dev = "cuda:0" if args.device == "cuda" else "cpu"
            subprocess.run([sys.executable, "-c", WARMUP, str(args.campaign), dev], env=env, check=True)
            print(f"warm-up (kernels compiled or loaded): {time.perf_counter() - t0:.1f} s", flush=True)
        runs = []
        for config in args.configs:
            r = run_config(config, args.campaign, args.device, Path(tmp), args.cpus_per_task)
            runs.append(r)
            if args.json:  # what is measured so far survives an interrupted run
                write_json(args.json, {"partial": True, "configs": runs})
            if "wall_s" in r:
                line = (f"wall {r['wall_s']:.1f} s (process {r['process_s']:.1f} s; first batch start to last end "
                        f"{r['tasks_span_s']:.1f} s), {r['batches']['done']} batches, at most "
                        f"{r['max_concurrent_batches']} at once")
            else:
                line = f"failed: {r['error']}"
            print(f"{config:>10}: {line}", flush=True)
    done = [r for r in runs if "rows" in r]
    reference = json.dumps(done[0]["rows"], sort_keys=True) if done else None
    identical = [r["config"] for r in done if json.dumps(r["rows"], sort_keys=True) == reference]
    summary = {"rows_identical_in": identical, "rows_differ_in": [r["config"] for r in done
                                                                   if r["config"] not in identical],
               "failed": [r["config"] for r in runs if "rows" not in r or r["failures"]]}
    if len(done) > 1:
        summary["wall_s_ratio_to_first"] = {r["config"]: r["wall_s"] / done[0]["wall_s"] for r in done}
    print(f"rows identical in {identical}" + (f"; DIFFER in {summary['rows_differ_in']}"
                                               if summary["rows_differ_in"] else ""))
    if args.json:
        from warptan.meta import run_meta

        rows = done[0]["rows"] if done else []
        for r in runs:
            r.pop("rows", None)
        devices = ["cpu"]
        if args.device == "cuda":  # every GPU of the machine (after the runs: this process touches CUDA only now)
            import warp as wp

            devices += [d.alias for d in wp.get_cuda_devices()]
        write_json(args.json, {"meta": run_meta(devices, campaign=str(args.campaign), device=args.device),
                               "summary": summary, "configs": runs, "rows": rows})
        print(f"wrote {args.json}")
    if summary["rows_differ_in"] or summary["failed"]:
        sys.exit(1)


if __name__ == "__main__":
    main()
