#!/usr/bin/env python3
"""Two sets of scenario results side by side (``results.json`` written by ``warptan run`` or
``scripts/reproduce_paper.py``): converged RMSE (mean ± 95 % interval), pooled 3σ coverage and, where both
have them, the attitude RMSE, per scenario.

    python scripts/compare_results.py results/issue11_baseline/gaussian results/paper/gaussian \\
        --labels "issue 11 (C = 0)" "issue 12 (C ≠ 0)" --out results/paper/compare_issue11.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def load(path: Path) -> dict:
    file = path / "results.json" if path.is_dir() else path
    try:
        with open(file) as f:
            return json.load(f)["scenarios"]
    except (OSError, ValueError, KeyError) as err:
        raise SystemExit(f"compare_results: error: {file}: not a results.json ({err})") from None


def cells(a: dict | None) -> list[str]:
    if a is None:
        return ["", "", ""]
    m, h = a["rmse_converged_mean_m"], a["rmse_converged_ci95_m"]
    att = a.get("attitude_rmse_deg")
    return [" / ".join(f"{x:.2f}±{y:.2f}" for x, y in zip(m, h, strict=True)),
            " / ".join(f"{100 * c:.0f}%" for c in a["coverage_3sigma_mean"]),
            " / ".join(f"{v:.3f}" for v in att) if att else "—"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--labels", nargs=2, default=["before", "after"])
    parser.add_argument("--out", type=Path, default=None, help="write the Markdown table here (default: print)")
    args = parser.parse_args(argv)
    before, after = load(args.before), load(args.after)
    ids = sorted(set(before) | set(after), key=lambda s: int(s[1:]) if s[1:].isdigit() else 99)
    head = ["id"] + [f"{lab}: {col}" for lab in args.labels
                     for col in ("RMSE after convergence N / E / D (m)", "3σ coverage", "attitude RMSE (°)")]
    lines = [f"# {args.labels[0]} vs {args.labels[1]}", "",
             f"`{args.before}` vs `{args.after}`; RMSE mean ± 95 % interval over seeds, coverage pooled over seeds "
             "and epochs after convergence.", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for sid in ids:
        lines.append("| " + " | ".join([sid, *cells(before.get(sid)), *cells(after.get(sid))]) + " |")
    text = "\n".join(lines) + "\n"
    if args.out:
        args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
