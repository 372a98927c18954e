"""Per-kernel medians from an Nsight Compute details CSV (``ncu --import REPORT --page details --csv``) of
``ncu_step.py``: duration, registers, theoretical and achieved occupancy, active threads per warp, warp cycles per
issued instruction, SM throughput and waves, per kernel name (the launches profiled of one update and the next
interval).

    python3 ncu_summary.py DETAILS.csv OUT.json "COMMAND" "GPU" "COMMIT"
"""
import csv
import json
import statistics
import sys

METRICS = {
    "Duration": "duration_us", "Registers Per Thread": "registers", "Block Size": "block", "Grid Size": "grid",
    "Theoretical Occupancy": "theoretical_occupancy_pct", "Achieved Occupancy": "achieved_occupancy_pct",
    "Avg. Active Threads Per Warp": "active_threads_per_warp",
    "Warp Cycles Per Issued Instruction": "warp_cycles_per_issued_instruction",
    "Compute (SM) Throughput": "sm_throughput_pct", "Waves Per SM": "waves_per_sm",
}


def number(text: str) -> float:
    return float(text.replace(",", ""))


def main() -> int:
    src, out, command, gpu, commit = sys.argv[1:6]
    per: dict = {}
    for row in csv.DictReader(open(src)):
        key = METRICS.get(row["Metric Name"])
        if key is None or not row["Metric Value"]:
            continue
        name = row["Kernel Name"].split("_cuda_kernel_forward")[0].rsplit("_", 1)[0]
        per.setdefault(name, {}).setdefault(key, {}).setdefault(row["ID"], number(row["Metric Value"]))
    kernels = {name: {"launches": len(vals["duration_us"]),
                      **{k: statistics.median(v.values()) for k, v in vals.items()}}
               for name, vals in per.items()}
    meta = {"command": command, "gpu": gpu, "git_commit": commit,
            "what": __doc__.split("\n\n")[0].replace("\n", " ")}
    with open(out, "w") as fh:
        json.dump({"meta": meta, "results": kernels}, fh, indent=1)
    for name, k in sorted(kernels.items(), key=lambda kv: -kv[1]["duration_us"]):
        print(f"{name:60s} {k['duration_us']:7.2f} us  regs {k['registers']:.0f}  "
              f"threads/warp {k['active_threads_per_warp']:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
