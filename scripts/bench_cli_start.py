"""How long the ``warptan`` command takes to answer when it does no work: ``--help`` of the command and its
subcommands, and a usage error (issue 67: at most 1.5 s warm). Each command line runs ``--warmup`` times (the
interpreter's and the file system's caches), then ``--repeats`` times; the wall time of each process, from its start to
its exit, is kept and the median reported. Writes JSON with the machine's meta.

    python scripts/bench_cli_start.py --json benchmarks/cli_start_cpu.json
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from warptan.device import quiet_warp
from warptan.meta import run_meta

COMMANDS = (["--help"], ["run", "--help"], ["replay", "--help"], ["campaign", "--help"], ["terrain", "info", "--help"],
            ["run", "--seeds", "0"])
"""What is timed: the helps, and a usage error (``--seeds 0``: refused by the parser, exit 2)."""


def wall(argv: list[str]) -> tuple[float, int]:
    """Wall time (s) and exit status of one ``warptan ARGV`` process."""
    t0 = time.perf_counter()
    proc = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
    return time.perf_counter() - t0, proc.returncode


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    quiet_warp()  # (the meta's Warp import printed its banner among the results)
    exe = shutil.which("warptan")
    base = [exe] if exe else [sys.executable, "-m", "warptan"]
    rows = []
    for command in COMMANDS:
        for _ in range(args.warmup):
            wall(base + command)
        walls, codes = zip(*(wall(base + command) for _ in range(args.repeats)), strict=True)
        rows.append({"command": "warptan " + " ".join(command), "exit_status": sorted(set(codes)),
                     "walls_s": list(walls), "median_s": float(sorted(walls)[len(walls) // 2])})
        print(f"{rows[-1]['command']}: median {rows[-1]['median_s']:.3f} s (exit {rows[-1]['exit_status']})",
              flush=True)
    if args.json:
        args.json.write_text(json.dumps({"meta": run_meta(("cpu",), command=sys.argv), "entry": base,
                                         "repeats": args.repeats, "warmup": args.warmup, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
