"""CPU whole-run real-time factor of two source trees on one machine, alternated (a shared VM's speed drifts by up
to 1.6x within an hour, so only runs interleaved in one session compare): each round runs every scenario with the
``base`` tree, then with the installed package, each in a fresh process (:func:`bench_filter_step.real_time_factor`:
N = 500, the scenario's 10 x 10 scan, 20 s flown, seed 0, the median of ``--repeats`` runs).

    python3 benchmarks/issue32/rtf_ab.py BASE_SRC --base-rev REV --scenario S7 S8 --rounds 2 --json OUT.json

(from a folder outside the checkout).

``BASE_SRC`` holds the base commit's ``warptan`` with its ``kernels`` copied to ``warptan/kernels`` (``git archive
REV warptan kernels``).
"""
import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"
ONE = ("import json, sys; sys.path.insert(0, {scripts!r}); import bench_filter_step as b; "
       "print(json.dumps(b.real_time_factor({sid!r}, 'cpu', 500, 20.0, repeats={repeats})))")


def one(sid: str, repeats: int, base: str | None) -> dict:
    env = dict(os.environ)
    if base:
        env["PYTHONPATH"] = base + os.pathsep + env.get("PYTHONPATH", "")
    code = ONE.format(scripts=str(SCRIPTS), sid=sid, repeats=repeats)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True, cwd="/")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("base")
    parser.add_argument("--base-rev", default="", help="the commit BASE_SRC was made from (recorded in meta)")
    parser.add_argument("--scenario", nargs="+", default=["S8", "S7"])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", dest="json_out", required=True)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(SCRIPTS))
    from warptan.meta import run_meta
    from warptan.outputs import write_json

    rounds = []
    for r in range(args.rounds):
        for sid in args.scenario:
            for tree, base in (("base", args.base), ("head", None)):
                row = {"round": r, "scenario": sid, "tree": tree, **one(sid, args.repeats, base)}
                rounds.append(row)
                print(f"round {r} {sid} {tree:4s} RTF {row['real_time_factor']:5.1f}", flush=True)
    meta = run_meta(["cpu"], command=" ".join(sys.argv), base=args.base, base_rev=args.base_rev)
    write_json(args.json_out, {"meta": meta, "rounds": rounds})
    return 0


if __name__ == "__main__":
    sys.exit(main())
