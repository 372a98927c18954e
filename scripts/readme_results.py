#!/usr/bin/env python3
"""Render the README's generated blocks from committed artifacts (never typed by hand).

Blocks are delimited in README.md by ``<!-- generated:NAME -->`` … ``<!-- /generated:NAME -->``:

* ``paper`` — ``results/paper/likelihoods.json`` (+ each likelihood's ``results.json`` and ``claims.json``):
  converged RMSE and 3σ coverage of every scenario with the per-point and the paper likelihood, the
  integrity re-spreads, and the claim verdicts of the default likelihood;
* ``step`` — ``benchmarks/filter_step_device_{cpu,h100,batch_h100}.json``: whole filter-step times.

    python scripts/readme_results.py            # print the blocks
    python scripts/readme_results.py --write    # replace them in README.md
    python scripts/readme_results.py --check    # exit 1 if README.md differs from the artifacts
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _load(path: Path) -> dict:
    with open(ROOT / path) as f:
        return json.load(f)


def _triple(mean, half=None) -> str:
    if half is None:
        return " / ".join(f"{v:.2f}" for v in mean)
    return " / ".join(f"{m:.2f}±{h:.2f}" for m, h in zip(mean, half, strict=True))


def paper_block(folder: str = "results/paper") -> str:
    side = _load(Path(f"{folder}/likelihoods.json"))
    kinds = side["likelihoods"]
    results = {k: _load(Path(f"{folder}/{k}/results.json")) for k in kinds}
    terrains = sorted({r["terrain"] for k in kinds for r in results[k]["runs"]})
    default = kinds[0]
    lines = [f"{side['seeds']} seeds per scenario, device `{side['device']}`, 500 particles, 120 s; "
             "converged = after 30 s. RMSE north / east / down in metres, mean ± 95 % interval over seeds; "
             "3σ coverage pooled over "
             "seeds and epochs after convergence; re-spreads = integrity flags (filter declared lost) over all "
             "seeds. Terrain: " + ", ".join(f"`{t}`" for t in terrains) + ". Source: `" + folder
             + "/likelihoods.json`, `" + folder + "/{" + ",".join(kinds) + "}/`.", "",
             "| id | model | paper's RMSE | "
             + " | ".join(f"{k}: RMSE | {k}: 3σ coverage | {k}: re-spreads" for k in kinds)
             + " |", "|" + "---|" * (3 + 3 * len(kinds))]
    for sid in sorted(side["scenarios"], key=lambda s: int(s[1:])):
        agg = results[default]["scenarios"][sid]
        cells = [sid, agg.get("model", ""), _triple(agg["paper_rmse_m"])]
        for k in kinds:
            e = side["scenarios"][sid][k]
            flags = sum(r["respreads"] for r in results[k]["runs"] if r["scenario"] == sid)
            cells += [_triple(e["rmse_converged_mean_m"], e["rmse_converged_ci95_m"]),
                      " / ".join(f"{100 * c:.0f}%" for c in e["coverage_3sigma_mean"]), str(flags)]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"The paper's claims with the `{default}` likelihood (`{folder}/{default}/claims.json`):", ""]
    for c in _load(Path(f"{folder}/{default}/claims.json")):
        verdict = {True: "holds", False: "does not hold", None: "not run"}[c["holds"]]
        lines.append(f"- **{verdict}** — {c['claim']}: {c['evidence']}")
    return "\n".join(lines)


def step_block() -> str:
    lines = ["| device | model | likelihood | graph | N | M | step ms | pipelined ms | stages per update |",
             "|---|---|---|---|---|---|---|---|---|"]
    sources = []
    for name in ("filter_step_device_cpu.json", "filter_step_device_h100.json", "filter_step_device_batch_h100.json"):
        path = Path("benchmarks") / name
        if not (ROOT / path).exists():
            continue
        sources.append(f"`{path}`")
        data = _load(path)
        device = ", ".join(data["meta"]["devices"].values())
        for r in data["results"]:
            pipelined = f"{r['throughput_step_ms']:.2f}" if "throughput_step_ms" in r else "—"
            lines.append(f"| {device} | {r['model']} | {r['likelihood']} | {'on' if r['graph'] else 'off'} | "
                         f"{r['B']} × {r['N']} | {r['M']} | {r['step_ms']:.2f} | {pipelined} | "
                         f"{r['tempering_stages_mean']:.2f} |")
    return ("Median whole step (10 IMU samples + one update, synchronised) and the pipelined step (the next intervals "
            "back to back, one synchronisation at the end), `scripts/bench_filter_step.py` with `--likelihood gaussian "
            "--m-side 10 20` (CPU) or `--m-side 20` (H100); N is filters × particles. Sources: "
            + ", ".join(sources) + ".\n\n" + "\n".join(lines))


def map_error_block() -> str:
    data = _load(Path("results/map_error/study.json"))
    meta, rows = data["meta"], data["rows"]
    lines = [f"World `{meta['terrain']}`; map = the world at coarser posts (block means) + white noise per post; "
             f"{meta['seeds']} seeds per row, {meta['duration_s']:g} s. Converged horizontal RMSE (m, mean ± 95 % "
             "interval) and the smaller of the N/E 3σ coverages, with the map-aware σ (left) and with the stated "
             "noise only (right; on the world's own 30 m grid both are the same). Source: "
             "`results/map_error/study.json` (full table: `results/map_error/study.md`).", "",
             "| model | map noise (m) | " + " | ".join(f"{s:g} m posts" for s in meta["spacings"]) + " |",
             "|---|---|" + "---|" * len(meta["spacings"])]

    def cell(r):
        cover = 100 * min(r["coverage_3sigma_mean"][:2])
        return f"{r['horizontal_rmse_mean_m']:.1f}±{r['horizontal_rmse_ci95_m']:.1f} ({cover:.0f}%)"

    for sid in meta["scenarios"]:
        model = {"S7": "S7 ray casting", "S8": "S8 sliding", "S9": "S9 altimeter"}.get(sid, sid)
        for noise in meta["noises"]:
            cells = []
            for spacing in meta["spacings"]:
                found = {r["map_aware"]: r for r in rows if r["scenario"] == sid and r["map_spacing_m"] == spacing
                         and r["map_noise_m"] == noise}
                if not found:
                    cells.append("")
                elif False not in found:
                    cells.append(cell(found[True]))
                else:
                    cells.append(f"{cell(found[True])} · {cell(found[False])}")
            lines.append(f"| {model} | {noise:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


BLOCKS = {"paper": paper_block, "paper30": lambda: paper_block("results/paper30"), "map_error": map_error_block,
          "step": step_block}


def render(text: str) -> str:
    for name, make in BLOCKS.items():
        pattern = re.compile(rf"(<!-- generated:{name} -->\n)(?:.*?\n)?(<!-- /generated:{name} -->)", re.S)
        if not pattern.search(text):
            raise SystemExit(f"README.md has no <!-- generated:{name} --> block")
        body = make()
        text = pattern.sub(lambda m, body=body: m.group(1) + body + "\n" + m.group(2), text)
    return text


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--write", action="store_true", help="replace the blocks in README.md")
    parser.add_argument("--check", action="store_true", help="exit 1 when README.md differs from the artifacts")
    args = parser.parse_args(argv)
    readme = ROOT / "README.md"
    text = readme.read_text()
    new = render(text)
    if args.check:
        if new != text:
            print("README.md is out of date with the artifacts: run scripts/readme_results.py --write", file=sys.stderr)
            return 1
        return 0
    if args.write:
        readme.write_text(new)
        return 0
    for name, make in BLOCKS.items():
        print(f"## {name}\n{make()}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
