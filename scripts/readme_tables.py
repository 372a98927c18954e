#!/usr/bin/env python3
"""Render every measured table and figure reference of the README and the documentation's pages
(``docs/user-guide.md``, ``docs/results.md``) from committed artifacts (never typed by hand).

Blocks are delimited in the pages (:data:`PAGES`) by ``<!-- generated:NAME -->`` … ``<!-- /generated:NAME -->``;
each is rendered from JSON under ``results/`` or ``benchmarks/`` (the block names its sources and the commit and machine
from the artifact's ``meta``). Outside the blocks a page carries no measured number: ``--check`` also fails
on a timing, percentage, ratio or decimal length written in the prose (:func:`hand_numbers`).

    python scripts/readme_tables.py            # print the blocks
    python scripts/readme_tables.py --write    # replace them in the pages
    python scripts/readme_tables.py --check    # exit 1 if a page differs from the artifacts or has hand numbers
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if importlib.util.find_spec("warptan") is None:  # not installed: the checkout's package (pure-Python modules only)
    sys.path.insert(0, str(ROOT))


def _load(path: str | Path) -> dict:
    with open(ROOT / path) as f:
        return json.load(f)


def _provenance(*paths: str) -> str:
    """"Sources: `a` (commit abc1234, GPU/CPU), …" from the artifacts' meta."""
    parts = []
    for p in paths:
        meta = _load(p).get("meta", {})
        where = (", ".join(meta["gpu"]["names"]) if "gpu" in meta else
                 f"{meta.get('cpu_model', '?')}, {meta.get('cpu_threads', '?')} threads")
        parts.append(f"`{p}` (commit {str(meta.get('git_commit', '?'))[:7]}, {where})")
    return "Sources: " + "; ".join(parts) + "."


def _triple(mean, half=None, fmt="{:.2f}") -> str:
    if half is None:
        return " / ".join(fmt.format(v) for v in mean)
    return " / ".join(f"{fmt.format(m)}±{fmt.format(h)}" for m, h in zip(mean, half, strict=True))


def _pct(values) -> str:
    return " / ".join(f"{100 * c:.0f}%" for c in values)


def _sid_key(s: str) -> int:
    return int(s[1:])


def claims_lines(path: str) -> list[str]:
    data = _load(path)
    return [f"- **{c['verdict']}** — {c['claim']}: {c['evidence']}" for c in data["claims"]] + [
        "", "Tests: " + "; ".join(sorted({c["test"] for c in data["claims"]})) + "."]


def paper_block(folder: str = "results/paper") -> str:
    side = _load(f"{folder}/likelihoods.json")
    kinds = side["likelihoods"]
    results = {k: _load(f"{folder}/{k}/results.json") for k in kinds}
    terrains = sorted({r["terrain"] for k in kinds for r in results[k]["runs"]})
    default = kinds[0]
    lines = [f"{side['seeds']} seeds per scenario, device `{side['device']}`, 500 particles, 120 s; "
             "converged = after 30 s. RMSE north / east / down in metres, mean ± 95 % interval over seeds; "
             "3σ coverage pooled over seeds and epochs after convergence; re-spreads = integrity flags (filter "
             "declared lost) over all seeds. Terrain: " + ", ".join(f"`{t}`" for t in terrains) + ". "
             + _provenance(f"{folder}/likelihoods.json"), "",
             "| id | model | paper's RMSE | "
             + " | ".join(f"{k}: RMSE | {k}: 3σ coverage | {k}: re-spreads" for k in kinds)
             + " |", "|" + "---|" * (3 + 3 * len(kinds))]
    for sid in sorted(side["scenarios"], key=_sid_key):
        agg = results[default]["scenarios"][sid]
        cells = [sid, agg.get("model", ""), _triple(agg["paper_rmse_m"])]
        for k in kinds:
            e = side["scenarios"][sid][k]
            flags = sum(r["respreads"] for r in results[k]["runs"] if r["scenario"] == sid)
            cells += [_triple(e["rmse_converged_mean_m"], e["rmse_converged_ci95_m"]),
                      _pct(e["coverage_3sigma_mean"]), str(flags)]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"The paper's claims with the `{default}` likelihood (`{folder}/{default}/claims.json`):", ""]
    lines += claims_lines(f"{folder}/{default}/claims.json")
    return "\n".join(lines)


def attitude_block(folder: str = "results/paper/gaussian") -> str:
    from warptan.sim.report import attitude_table

    data = _load(f"{folder}/results.json")
    return ("Attitude error = Log(q_true⁻¹ q_est) in body axes after convergence, RMS over seeds of the runs' RMSE; "
            "gyro-bias RMSE after 60 s; mean reported σ over the RMSE (≈ 1: the 3σ neither lies nor balloons). "
            + _provenance(f"{folder}/results.json") + "\n\n" + attitude_table(data["scenarios"]))


def closed_loop_block() -> str:
    open_, closed = _load("results/paper/gaussian/results.json"), _load("results/closed_loop/gaussian/results.json")
    lines = ["Converged RMSE north / east / down (m, mean ± 95 % interval) and 3σ coverage, open loop (the default) "
             "and closed loop (`--closed-loop`), same seeds. " + _provenance("results/paper/gaussian/results.json",
                                                                            "results/closed_loop/gaussian/results.json"),
             "", "| id | open loop RMSE | open loop 3σ | closed loop RMSE | closed loop 3σ |", "|---|---|---|---|---|"]
    for sid in sorted(closed["scenarios"], key=_sid_key):
        a, b = open_["scenarios"][sid], closed["scenarios"][sid]
        cells = [sid] + [f"{_triple(x['rmse_converged_mean_m'], x['rmse_converged_ci95_m'])} | "
                         f"{_pct(x['coverage_3sigma_mean'])}" for x in (a, b)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def map_error_block() -> str:
    data = _load("results/map_error/study.json")
    meta, rows = data["meta"], data["rows"]
    lines = [f"World `{meta['terrain']}`; map = the world at coarser posts (block means) + white noise per post; "
             f"{meta['seeds']} seeds per row, {meta['duration_s']:g} s. Converged horizontal RMSE (m, mean ± 95 % "
             "interval) and the smaller of the N/E 3σ coverages, with the map-aware σ (left) and with the stated "
             "noise only (right; on the world's own grid both are the same). Full table: `results/map_error/study.md`"
             ". " + _provenance("results/map_error/study.json"), "",
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


def long_flight_block() -> str:
    data = _load("results/long_flight_check.json")
    terrain = Path(data.get("terrain", "?")).name  # (the file's name: the path was the measuring machine's)
    lines = [data["what"], f"Terrain `{terrain}`. " + _provenance("results/long_flight_check.json"),
             "", "| likelihood | runs | epochs outside 3σ (mean) | runs > 5 % outside | runs re-spread | "
             "outside > 5 % and never re-spread | largest horizontal error after 30 s (m) |",
             "|---|---|---|---|---|---|---|"]
    kinds = sorted({k.split("/")[0] for k in data["runs"]})
    for kind in kinds:
        runs = [v for k, v in data["runs"].items() if k.startswith(kind + "/")]
        out = [r["frac_outside_3sigma_after_30s"] for r in runs]
        flagged = [bool(r["respreads_at_s"]) for r in runs]
        silent = sum(1 for o, f in zip(out, flagged, strict=True) if o > 0.05 and not f)
        lines.append(f"| {kind} | {len(runs)} | {100 * sum(out) / len(out):.2f}% | {sum(o > 0.05 for o in out)} | "
                     f"{sum(flagged)} | {silent} | {max(r['max_horizontal_error_after_30s_m'] for r in runs):.1f} |")
    return "\n".join(lines)


def _bench_rows(paths):
    """(device names, row) of every result of the benchmark JSONs ``paths``."""
    for path in paths:
        data = _load(path)
        device = ", ".join(data["meta"]["devices"].values())
        for r in data["results"]:
            yield device, r


def step_block() -> str:
    lines = ["| device | model | likelihood | graph | N | M | step ms | pipelined ms | stages per update |",
             "|---|---|---|---|---|---|---|---|---|"]
    sources = [f"benchmarks/{name}" for name in ("filter_step_device_cpu.json", "filter_step_device_h100.json",
                                                  "filter_step_device_batch_h100.json")]
    for device, r in _bench_rows(sources):
        pipelined = f"{r['throughput_step_ms']:.2f}" if "throughput_step_ms" in r else "—"
        lines.append(f"| {device} | {r['model']} | {r['likelihood']} | {'on' if r['graph'] else 'off'} | "
                     f"{r['B']} × {r['N']} | {r['M']} | {r['step_ms']:.2f} | {pipelined} | "
                     f"{r['tempering_stages_mean']:.2f} |")
    commands = "; ".join(f"`{_load(p)['meta']['command']}`" for p in sources)
    return ("The generic configuration (`--models`: a straight flight 600 m over the synthetic rugged terrain, the "
            "likelihood's defaults, bilinear sliding): median whole step (10 IMU samples + one update, synchronised) "
            "and the pipelined step (the next intervals back to back, one synchronisation at the end); N is filters × "
            "particles. " + _provenance(*sources)
            + " Commands: " + commands + ".\n\n" + "\n".join(lines))


def _paced(r: dict, digits: int) -> str:
    """A row's paced step and update latency (``bench_filter_step.py --paced-s``), or — where it has none."""
    if "paced_step_ms" not in r:
        return "—"
    return f"{r['paced_step_ms']:.{digits}f} / {r['paced_update_ms']:.{digits}f}"


def scenario_step_block() -> str:
    """The filters the scenarios fly (``bench_filter_step.py --scenario``): what one update costs against its model
    kernel alone, and a whole run's real-time factor."""
    sources = [p for p in ("benchmarks/issue32/scenario_step_cpu_xeon.json",
                           "benchmarks/issue32/scenario_step_h100.json") if (ROOT / p).exists()]
    lines = ["| device | scenario filter | likelihood, surface | N | M | update ms | step ms | pipelined ms | "
             "paced step / update ms | stages per update | point evaluations per s: achieved / kernel alone | "
             "real-time factor |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for device, r in _bench_rows(sources):
        rtf = f"{r['real_time_factor']:.1f}" if "real_time_factor" in r else "—"
        lines.append(f"| {device} | {r['model']} | {r['likelihood']}, {r['surface']} | {r['B']} × {r['N']} | "
                     f"{r['M']} | {r['update_ms']:.2f} | {r['step_ms']:.2f} | {r['throughput_step_ms']:.2f} | "
                     f"{_paced(r, 2)} | {r['tempering_stages_mean']:.2f} | {r['point_evals_per_s'] / 1e6:.1f} M / "
                     f"{r['kernel_point_evals_per_s'] / 1e6:.1f} M | {rtf} |")
    commands = "; ".join(f"`{_load(p)['meta']['command']}`" for p in sources)
    return ("The filter each scenario flies (its map surface, likelihood, scan, rates, tempering and attitude update), "
            "measured on its own flight after its first seconds; the real-time factor is flight time over the median "
            "wall time of whole runs of the scenario (seed 0; one run where the artifact has no rtf_walls_s). Step and "
            "pipelined times are of intervals run back to back; paced (B = 1): the same filter flown at the flight's "
            "own rates, the host sleeping until each piece is due, as a real-time loop does: the step (the "
            "interval's IMU samples in one call, then the update, synchronised) and the update's latency when each "
            "IMU sample is predicted as it comes (medians). "
            + _provenance(*sources) + " Commands: " + commands
            + ".\n\n" + "\n".join(lines))


def step_spread_block() -> str:
    """One GPU filter's synchronised step in several processes on one machine (``scenario_step_h100.json`` and the
    runs of ``scenario_step_spread_h100.json``): the host's share varies from process to process, the device's not."""
    sources = ["benchmarks/issue32/scenario_step_h100.json", "benchmarks/issue32/scenario_step_spread_h100.json"]
    first = [r for r in _load(sources[0])["results"] if r["B"] == 1]
    runs = [first] + [[r for r in run if r["B"] == 1] for run in _load(sources[1])["runs"]]
    lines = ["| process | scenario filter | step ms (synchronised) | host + upload ms | device ms | pipelined ms | "
             "estimate ms | paced step / update ms |", "|---|---|---|---|---|---|---|---|"]
    for k, run in enumerate(runs, start=1):
        for r in run:
            lines.append(f"| {k} | {r['model']} | {r['step_ms']:.3f} | {r['host_ms'] + r['upload_ms']:.3f} | "
                         f"{r['device_ms']:.3f} | {r['throughput_step_ms']:.3f} | {r['estimate_ms']:.3f} | "
                         f"{_paced(r, 3)} |")
    return ("One filter (B = 1, N = 500, M = 400) of the table above in separate processes, one after the other on "
            "the same machine: medians of 200 synchronised intervals each; host + upload is the Python of an interval "
            "before the update's graph is launched (the filter's StepTimer), device the update's device time, "
            "estimate one ``estimate()`` after the step (outside the step's clock); paced as in the table above. "
            + _provenance(*sources) + "\n\n" + "\n".join(lines))


IDLE_MODES = (("none", "none"), ("busy5ms", "5 ms, host busy-waiting"), ("sleep5ms", "5 ms, host sleeping"),
              ("gpuspin5ms+sleep", "5 ms, host sleeping, GPU running a kernel"),
              ("busy100ms", "100 ms, host busy-waiting"), ("sleep100ms", "100 ms, host sleeping"),
              ("gpuspin100ms+sleep", "100 ms, host sleeping, GPU running a kernel"))
IDLE_PIECES = ("predict_many", "advance(graph)", "update", "check", "head(graph)", "stage", "queue_update(graph)",
               "next_set", "sync_wait", "wall")


def idle_block() -> str:
    """One GPU filter's synchronised step after a pause (``benchmarks/issue32/idle_gap.py``) and its host pieces after
    none or a 100 ms one (``idle_host_pieces.py``)."""
    sources = ["benchmarks/issue32/idle_gap_h100.json", "benchmarks/issue32/idle_host_pieces_h100.json"]
    gap, pieces = (_load(p)["results"] for p in sources)
    lines = ["| pause before the step | step µs (wall) | host µs until ``update`` returns |", "|---|---|---|"]
    lines += [f"| {label} | {gap[k]['wall_us']:.0f} | {gap[k]['host_us']:.0f} |" for k, label in IDLE_MODES]
    lines += ["", "| host piece (µs) | no pause | after 100 ms, busy-waiting | after 100 ms, sleeping |",
              "|---|---|---|---|"]
    lines += [f"| ``{k}`` | {pieces['none'][k]:.0f} | {pieces['busy100ms'][k]:.0f} | {pieces['sleep100ms'][k]:.0f} |"
              for k in IDLE_PIECES]
    return ("One S7 filter on CUDA (B = 1, N = 500, M = 400) stepped synchronised with a pause before each step, the "
            "pauses alternated step by step (medians of 100 steps each); then the host's pieces of a step "
            "(``perf_counter`` stamps around the filter's methods; ``advance(graph)`` is the run-ahead graph's launch "
            "inside ``predict_many``, ``sync_wait`` the wait for the device after ``update`` returned). "
            + _provenance(*sources) + "\n\n" + "\n".join(lines))


STAGE_PHASES = ("candidates' ESS", "exponent", "log-weights", "maximum", "exponentials", "weight statistics",
                "normalisation + Kalman update", "CDF partials", "CDF", "ancestors", "gather", "put + poses")
RECORD_PHASES = ("integrity", "summary partials", "record", "covariance", "end")


def stamps_block() -> str:
    """One GPU filter's update graph by pieces and its stage and record blocks by phases, from the globaltimer stamps of
    ``benchmarks/issue32/stamps_update.py`` and ``stamps_blocks.py`` (phase k ends at the block's k-th barrier)."""
    sources = ["benchmarks/issue32/update_stamps_h100.json", "benchmarks/issue32/block_stamps_h100.json"]
    upd, blk = (_load(p)["results"] for p in sources)
    sids = list(upd)
    head = ["| piece | " + " | ".join(f"{s} µs" for s in sids) + " |", "|---|" + "---|" * len(sids)]
    lines = head + [f"| {k} | " + " | ".join(f"{upd[s][k]['median_us']:.1f}" for s in sids) + " |"
                    for k in upd[sids[0]]]
    phases = head[:]
    for prefix, names in (("stage", STAGE_PHASES), ("record", RECORD_PHASES)):
        keys = [k for k in blk[sids[0]] if k.startswith(prefix + " ") and "->" in k]
        for k, name in zip(keys, names, strict=False):
            phases.append(f"| {prefix} block: {name} | " + " | ".join(f"{blk[s][k]:.2f}" for s in sids) + " |")
        total = f"{prefix} total"
        if total in blk[sids[0]]:
            phases.append(f"| {prefix} block: total | " + " | ".join(f"{blk[s][total]:.2f}" for s in sids) + " |")
    return ("One filter's update graph (B = 1, N = 500, M = 400, the scenarios' filters): medians over the steps of "
            "the device time between the GPU's globaltimer stamps written between its pieces (each stamp a graph node "
            "of its own), then the stage block of an update's last stage and the record block by phases (lane 0's "
            "stamps after each barrier). " + _provenance(*sources) + "\n\n" + "\n".join(lines) + "\n\n"
            + "\n".join(phases))


def profile_block(top: int = 10) -> str:
    data = _load("benchmarks/step_profile_h100.json")
    lines = []
    for r in data["results"]:
        lines += [f"`{r['likelihood']}` likelihood, eager step {r['eager_step_ms']:.2f} ms with the profiler on, "
                  f"{r['stages']:.2f} tempering stages per update; the {top} costliest kernels (device µs per step):",
                  "", "| kernel | µs per step | calls per step |", "|---|---|---|"]
        lines += [f"| `{k['kernel']}` | {k['us_per_step']:.1f} | {k['calls_per_step']:.1f} |"
                  for k in r["kernels"][:top]]
    m = data["meta"]
    return (f"Device time per kernel (`{m['command']}`, model {m.get('model')}, N = {m.get('N')}, M = {m.get('M')}). "
            + _provenance("benchmarks/step_profile_h100.json") + "\n\n" + "\n".join(lines))


def kernels_block() -> str:
    sources = ["benchmarks/kernel_timings_cpu.json", "benchmarks/kernel_timings_h100.json"]
    rows = {}
    for p in sources:
        for r in _load(p)["results"]:
            rows.setdefault((r["device"], r["N"], r["M"]), {})[r["model"]] = r["median_s"]
    models = ["mesh", "dda", "bisection", "sliding"]
    lines = ["| device | N × M | " + " | ".join(f"{m} ms" for m in models) + " | dda / sliding |",
             "|---|---|" + "---|" * (len(models) + 1)]
    for (dev, n, m), t in sorted(rows.items(), key=lambda kv: (kv[0][0], kv[0][1] * kv[0][2])):
        if n * m < 50_000:
            continue
        ratio = f"{t['dda'] / t['sliding']:.1f}" if "dda" in t and "sliding" in t else "—"
        lines.append(f"| {dev} | {n} × {m} | " + " | ".join(f"{1e3 * t[k]:.3f}" if k in t else "—" for k in models)
                     + f" | {ratio} |")
    return ("One model update as the filter runs it (`stage` + `launch`: N × M residual kernel + per-particle "
            "reduction; `evaluate` before it returned copies), median after warm-up, on the "
            "generated rugged terrain; configurations from N·M = 50 000 up. " + _provenance(*sources) + "\n\n"
            + "\n".join(lines))


def threads_block() -> str:
    one, two = _load("benchmarks/cpu_threads_1.json"), _load("benchmarks/kernel_timings_cpu.json")
    t1 = {(r["model"], r["N"], r["M"]): r["median_s"] for r in one["results"]}
    lines = [f"One model update with {one['meta']['cpu_threads']} thread (`WARPTAN_CPU_THREADS=1`) against "
             f"{two['meta']['cpu_threads']} threads, same machine. "
             + _provenance("benchmarks/cpu_threads_1.json", "benchmarks/kernel_timings_cpu.json"), "",
             "| model | N × M | 1 thread ms | all threads ms | speed-up |", "|---|---|---|---|---|"]
    for r in two["results"]:
        key = (r["model"], r["N"], r["M"])
        if key in t1:
            lines.append(f"| {r['model']} | {r['N']} × {r['M']} | {1e3 * t1[key]:.2f} | {1e3 * r['median_s']:.2f} | "
                         f"{t1[key] / r['median_s']:.2f}× |")
    return "\n".join(lines)


def numpy_block() -> str:
    data = _load("benchmarks/numpy_baseline_cpu.json")
    lines = ["Same inputs, same CPU: warptan's model against vectorised NumPy (sliding) and trimesh's ray–triangle "
             "intersector (ray casts); the largest difference of the two errors shows they compute the same thing. "
             + _provenance("benchmarks/numpy_baseline_cpu.json"), "",
             "| model | N × M | warptan ms | baseline ms | speed-up | max difference (m) |",
             "|---|---|---|---|---|---|"]
    for r in data["results"]:
        lines.append(f"| {r['model']} ({r.get('numpy_impl', '')}) | {r['N']} × {r['M']} | {r['warptan_ms']:.2f} | "
                     f"{r['numpy_ms']:.1f} | {r['speedup']:.1f}× | {r['max_abs_error_difference_m']:.1e} |")
    return "\n".join(lines)


def batch_block() -> str:
    data = _load("results/s7_batch100/results.json")
    s7, m = data["scenarios"]["S7"], data["meta"]
    return (f"`{m['command']}`: {len(s7['seeds'])} runs of S7 (120 s, 500 particles, 100 rays) as one batched filter "
            f"took {s7['wall_s_mean']:.1f} s wall time including the simulation of truth, IMU errors and scans. "
            f"Converged RMSE {_triple(s7['rmse_converged_mean_m'], s7['rmse_converged_ci95_m'])} m. "
            + _provenance("results/s7_batch100/results.json"))


def campaign_block() -> str:
    sources = ("results/campaign_engines_cpu.json", "results/campaign_engines_2gpu.json",
               "results/campaign_engines_100seeds_2gpu.json")
    lines = ["| campaign | configuration | wall time (s) | first batch start → last batch end (s) | sum of batch "
             "times (s) | batches at once | devices | rows identical to the first configuration |",
             "|---|---|---|---|---|---|---|---|"]
    for path in sources:
        data = _load(path)
        same = set(data["summary"]["rows_identical_in"])
        name = Path(data["meta"]["campaign"]).name
        for c in data["configs"]:
            where = ", ".join(sorted({t["device"] for t in c["timeline"]}))
            config = c["config"] if c.get("cuda_visible_devices") is None else \
                f"{c['engine']}, CUDA_VISIBLE_DEVICES={c['cuda_visible_devices']}"
            lines.append(f"| `{name}` | {config} | {c['wall_s']:.1f} | {c['tasks_span_s']:.1f} | "
                         f"{c['batch_s_sum']:.1f} | {c['max_concurrent_batches']} | {where} | "
                         f"{'yes' if c['config'] in same else 'NO'} |")
        for missing in data["summary"].get("not_run", []):
            lines.append(f"| `{name}` | {missing}: not measured | | | | | | |")
    ratios = []
    for path in sources[1:]:
        data = _load(path)
        walls = {c["config"]: c["wall_s"] for c in data["configs"]}
        ratios.append(f"`{Path(data['meta']['campaign']).name}` {walls['ray:0'] / walls['ray:0,1']:.2f}×")
    lines += ["", "Wall time of Ray on one GPU over Ray on two: " + ", ".join(ratios) + ". " + _provenance(*sources)]
    return "\n".join(lines)


def world_block(path: str = "results/world/study.json") -> str:
    """Worlds that are not the map: per scenario and map error, the three estimators side by side."""
    data = _load(path)
    rows = data["rows"]
    order = ("gaussian", "paper", "stated")
    names = {"gaussian": "per-point (not told)", "paper": "paper's scalar error", "stated": "told the DEM's accuracy"}
    keys = sorted({(r["scenario"], r["error_rms_m"], r["error_corr_m"]) for r in rows},
                  key=lambda k: (_sid_key(k[0]), k[2] != 1000.0, k[1], k[2]))
    lines = [f"{data['meta']['seeds']} seeds over {data['meta']['worlds']} world realisations per row, "
             f"{data['meta']['duration_s']:g} s, sub-post relief `{data['meta']['relief']}` on the 90 m rugged tile "
             "(every scenario, S12 included, flies it); converged horizontal RMSE (m, mean ± 95 % interval) and 3σ "
             "coverage N / E / D; a dash: not run. Full table: `results/world/study.md`. " + _provenance(path), "",
             "| scenario | map error RMS / corr (m) | " + " | ".join(names[e] for e in order) + " |",
             "|---|---|" + "---|" * len(order)]
    for sid, rms, corr in keys:
        cells = []
        for e in order:
            r = next((r for r in rows if (r["scenario"], r["error_rms_m"], r["error_corr_m"], r["estimator"])
                      == (sid, rms, corr, e)), None)
            cells.append("–" if r is None else
                         f"{r['horizontal_rmse_mean_m']:.1f}±{r['horizontal_rmse_ci95_m']:.1f} "
                         f"({_pct(r['coverage_3sigma_mean'])})")
        lines.append(f"| {sid} | {rms:g} / {corr:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def learned_block(path: str = "results/learned/study.json") -> str:
    """The map's error learned in flight: per scenario and world family, the learner on, off, and told the truth."""
    data = _load(path)
    rows = data["rows"]
    order = ("learn", "off", "told")
    names = {"learn": "told nothing, learned (default)", "off": "told nothing, learner off",
             "told": "told the world's error (a prior)"}
    keys = sorted({(r["scenario"], r["family"]) for r in rows}, key=lambda k: (_sid_key(k[0]), k[1]))
    lines = ["20 seeds over 4 world realisations per row, 120 s; converged horizontal RMSE (m, mean ± 95 % interval), "
             "3σ coverage N / E / D and, for the learner, the learned RMS (m, mean over seeds); a dash: not run. "
             "Families and devices: `results/learned/study.md`. " + _provenance(path), "",
             "| scenario | family (map − world RMS) | " + " | ".join(names[m] for m in order) + " |",
             "|---|---|" + "---|" * len(order)]
    for sid, family in keys:
        cells, world = [], ""
        for mode in order:
            r = next((r for r in rows if (r["scenario"], r["family"], r["mode"]) == (sid, family, mode)), None)
            if r is None:
                cells.append("–")
                continue
            world = f"{r['world_rms_m']:.1f} m"
            learned = f", σ_e {sum(r['learned_m']) / len(r['learned_m']):.2f} m" if r["learned_m"] else ""
            cells.append(f"{r['horizontal_rmse_m']:.2f}±{r['horizontal_rmse_ci95_m']:.2f} "
                         f"({_pct(r['coverage_3sigma'])}{learned})")
        lines.append(f"| {sid} | {family} ({world}) | " + " | ".join(cells) + " |")
    misstated = ("learn", "told", "rms-half", "rms-double", "corr-third", "corr-triple")
    keys = sorted({(r["scenario"], r["family"]) for r in rows if r["mode"] in misstated[2:]},
                  key=lambda k: (_sid_key(k[0]), k[1]))
    if keys:
        lines += ["", "Misstated: the family's own error stated with its RMS × 0.5 or × 2, or its correlation length "
                  "× 1/3 or × 3 (each a prior the learner starts from); over the `exact` family (the map is the world) "
                  "the statement is 5 m / 1 km (told) and its scaled forms, beside nothing stated.", "",
                  "| scenario | family | nothing stated | told | RMS × 0.5 | RMS × 2 | correlation × 1/3 | "
                  "correlation × 3 |",
                  "|---|---|" + "---|" * len(misstated)]
        for sid, family in keys:
            cells = []
            for mode in misstated:
                r = next((r for r in rows if (r["scenario"], r["family"], r["mode"]) == (sid, family, mode)), None)
                cells.append("–" if r is None else f"{r['horizontal_rmse_m']:.2f}±{r['horizontal_rmse_ci95_m']:.2f} "
                             f"({_pct(r['coverage_3sigma'])})")
            lines.append(f"| {sid} | {family} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def replay_frames_block(path: str = "results/replay_frames.json") -> str:
    """Flights tied to the Earth over many seeds: in memory, replayed over the own DEM, through geodetic CSV tables,
    over another cut of the DEM and over a UTM copy."""
    data = _load(path)
    names = {"memory": "in memory", "own": "own DEM", "csv": "CSV tables", "crop": "another cut",
             "utm": "UTM copy", "tmerc": "own-frame copy"}
    lines = ["Converged horizontal RMSE (m, mean ± 95 % interval over the seeds) and pooled 3σ coverage N / E / D; "
             "within: seeds whose RMSE is at most 1.25 × the in-memory run's + 1 m; same bits: seeds whose estimate "
             "equals the in-memory one bit for bit. Source: `" + path + "` (" + "; ".join(
                 f"`{' '.join(r['command']) if isinstance(r['command'], list) else r['command']}` at "
                 f"{str(r.get('git_commit', '?'))[:7]} on "
                 f"{', '.join(r['gpu']['names'] if 'gpu' in r else r['devices'].values())}"
                 for r in data["meta"]["runs"]) + ").", "",
             "| scenario | seeds | " + " | ".join(names.values()) + " | within (cut / UTM / own-frame) | same bits "
             "(own / CSV) |",
             "|---|---|" + "---|" * (len(names) + 2)]
    for r in data["rows"]:
        cells = [f"{r[f'{k}_rmse_mean_m']:.2f}±{r[f'{k}_rmse_ci95_m']:.2f} ({_pct(r[f'{k}_coverage_mean'])})"
                 for k in names]
        lines.append(f"| {r['scenario']} | {r['seeds']} | " + " | ".join(cells)
                     + f" | {r['crop_within_mark']} / {r['utm_within_mark']} / {r['tmerc_within_mark']} | "
                       f"{r['own_identical']} / "
                       f"{r['csv_identical']} |")
    return "\n".join(lines)


def bound_block(path: str = "results/bound/bound_study.json") -> str:
    """Each scenario's filter against its flights' posterior Cramér–Rao bound (``scripts/bound_study.py``)."""
    data = _load(path)
    lines = ["Horizontal RMSE after convergence (all seeds of a scenario pooled) beside the flight's posterior "
             "Cramér–Rao bound (the best any filter can do on it, `warptan.filter.bound`); below the bound: the "
             "filter better than the bound by more than twice its Monte-Carlo error (never allowed). "
             + _provenance(path), "",
             "| scenario | model | seeds | horizontal RMSE (m) | bound (m) | RMSE / bound | below the bound |",
             "|---|---|---|---|---|---|---|"]
    for r in data["rows"]:
        lines.append(f"| {r['scenario']} | {r['model']} | {r['seeds']} | {r['rmse_horizontal_converged_m']:.3g} | "
                     f"{r['bound_converged_m']:.3g} | {r['rmse_over_bound']:.2f} | "
                     f"{'yes' if r['below_bound_beyond_mc_error'] else 'no'} |")
    return "\n".join(lines)


def floor_block(path: str = "results/bound/floor_study.json") -> str:
    """The filter told a correlated map error against the flight's exact floor (``scripts/bound_study.py``, merged
    runs): per scenario and RMS, at each correlation length, converged horizontal RMSE / floor (ratio)."""
    data = _load(path)
    rows = [r for r in data["rows"] if r.get("bound") == "exact floor"]
    lengths = sorted({r["world"]["world_error_corr_m"] for r in rows})
    machines = sorted({", ".join(r["meta"]["gpu"]["names"]) if "gpu" in r["meta"] else "CPU" for r in rows})
    commits = sorted({str(r["meta"].get("git_commit", "?"))[:7] for r in rows})
    fast = [r["fast_bound_converged_m"] / r["bound_converged_m"] for r in rows]
    lines = [f"Told the world's error (RMS and correlation length; a Gaussian field on the map's own posts, world seed "
             f"2000), {rows[0]['seeds']} seeds a cell, 120 s: converged horizontal RMSE / the exact floor "
             "(`warptan.filter.floor.exact_pcrb`: the whole flight's Fisher information with the error field in "
             "the state), in metres, and their ratio. The fast per-scan bound is "
             f"{min(fast):.2f}–{max(fast):.2f} × the floor over these cells. Sources: `{path}` (commits "
             f"{', '.join(commits)}; {', '.join(machines)}; each row's command in its `meta`).", "",
             "| scenario | RMS (m) | " + " | ".join(f"L = {length / 1e3:g} km" for length in lengths) + " |",
             "|---|---|" + "---|" * len(lengths)]
    cells = {(r["scenario"], r["world"]["world_error_rms_m"], r["world"]["world_error_corr_m"]): r for r in rows}
    for sid, rms in sorted({(k[0], k[1]) for k in cells}, key=lambda k: (_sid_key(k[0]), k[1])):
        out = []
        for length in lengths:
            r = cells.get((sid, rms, length))
            out.append("–" if r is None else f"{r['rmse_horizontal_converged_m']:.2f} / {r['bound_converged_m']:.3f} "
                                              f"({r['rmse_over_bound']:.0f}×)")
        lines.append(f"| {sid} | {rms:g} | " + " | ".join(out) + " |")
    return "\n".join(lines)


BLOCKS = {"paper": paper_block, "attitude": attitude_block, "paper30": lambda: paper_block("results/paper30"),
          "closed_loop": closed_loop_block, "map_error": map_error_block, "long_flight": long_flight_block,
          "step": step_block, "scenario_step": scenario_step_block, "step_spread": step_spread_block,
          "idle": idle_block,
          "profile": profile_block, "stamps": stamps_block, "kernels": kernels_block,
          "threads": threads_block, "numpy": numpy_block, "batch": batch_block, "campaign": campaign_block,
          "world": world_block, "learned": learned_block, "replay_frames": replay_frames_block, "bound": bound_block,
          "floor": floor_block}

_BLOCK = re.compile(r"<!-- generated:(\w+) -->\n.*?<!-- /generated:\1 -->", re.S)
_FENCE = re.compile(r"```.*?```", re.S)
# A measured-looking number: a time, a percentage or ratio, or a decimal with a length / time / angle unit.
_HAND = re.compile(r"(?<![\w.])(\d[\d,]*(?:\.\d+)?\s?(?:ms|µs|%|×)(?![\w/])|\d+\.\d+\s?(?:m|s|°|°/h)(?![\w/²]))")


def hand_numbers(text: str) -> list[tuple[int, str]]:
    """(line, text) of every measured-looking number outside the generated blocks and code fences."""
    blanked = _BLOCK.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    blanked = _FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), blanked)
    found = []
    for i, line in enumerate(blanked.splitlines(), start=1):
        found += [(i, m.group(0)) for m in _HAND.finditer(line)]
    return found


def render(text: str) -> str:
    """``text`` with each generated block it holds rendered anew from the artifacts."""
    for name, make in BLOCKS.items():
        pattern = re.compile(rf"(<!-- generated:{name} -->\n)(?:.*?\n)?(<!-- /generated:{name} -->)", re.S)
        if pattern.search(text):
            body = make()
            text = pattern.sub(lambda m, body=body: m.group(1) + body + "\n" + m.group(2), text)
    return text


PAGES = ("README.md", "docs/user-guide.md", "docs/results.md")
"""The pages that hold generated blocks (every block is in at least one; the README keeps the headline table)."""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--write", action="store_true", help="replace the blocks in the pages")
    parser.add_argument("--check", action="store_true",
                        help="exit 1 when a page differs from the artifacts or carries a hand-typed number")
    parser.add_argument("--page", action="append", default=None,
                        help=f"a page to check or write (repeatable; default {', '.join(PAGES)})")
    args = parser.parse_args(argv)
    pages = [Path(p) if Path(p).is_absolute() else ROOT / p for p in (args.page or PAGES)]
    texts = {page: page.read_text() for page in pages}
    if args.check or args.write:
        held = {name for text in texts.values() for name in BLOCKS if f"<!-- generated:{name} -->" in text}
        missing = [name for name in BLOCKS if name not in held]
        if missing and args.page is None:
            print(f"no page holds the generated block(s) {', '.join(missing)}", file=sys.stderr)
            return 1
    if args.check:
        status = 0
        for page, text in texts.items():
            if render(text) != text:
                print(f"{page}: a generated block differs from the artifacts: run scripts/readme_tables.py --write",
                      file=sys.stderr)
                status = 1
            for line, number in hand_numbers(text):
                print(f"{page}:{line}: measured number outside a generated block: {number!r}", file=sys.stderr)
                status = 1
        return status
    if args.write:
        for page, text in texts.items():
            page.write_text(render(text))
        return 0
    for name, make in BLOCKS.items():
        print(f"## {name}\n{make()}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
