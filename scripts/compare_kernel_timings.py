#!/usr/bin/env python3
"""Per-step time of each measurement model, CPU vs CUDA: the paper's "raycasting vs pattern sliding" figure.

For every device, model (mesh / dda / bisection ray casts, sliding, altimeter), particle count N and point
count M, times one measurement update as the filter runs it (``model.stage`` + ``model.launch``: the N×M
residual kernel and the per-particle reduction; ``evaluate`` adds a pose check and copies for its caller) as
the median of ``--repeats`` after a warm-up (compilation excluded), synchronised before the clock stops. Prints
a table with rays (or samples) per second and the ratio to sliding; writes JSON
(``--json``) and a log–log plot (``--plot``). Configurations whose predicted time exceeds
``--max-config-s`` (extrapolated from the same model at a smaller N·M) are skipped and listed as such.

    python scripts/compare_kernel_timings.py --quick --json timings.json
    python scripts/compare_kernel_timings.py --device cpu cuda --json t.json --plot t.png
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import warp as wp

import warptan as wt
from warptan.cli import count_arg, number_arg, script_inputs
from warptan.meta import run_meta
from warptan.nav.frames import euler_to_quat
from warptan.outputs import write_json

FULL_N = (100, 500, 2_000, 10_000, 100_000)
FULL_M = (1, 25, 100, 400, 1_000)
QUICK_N = (100, 500, 2_000)
QUICK_M = (1, 25, 100)
MODELS = ("mesh", "dda", "bisection", "sliding", "altimeter")


def pattern_for(m: int) -> wt.ScanPattern:
    """A near-square grid pattern of exactly ``m`` rays over ±30° (``m = 1``: nadir)."""
    if m == 1:
        return wt.ScanPattern.nadir()
    nx = int(np.floor(np.sqrt(m)))
    while m % nx:
        nx -= 1
    return wt.ScanPattern.grid(nx, m // nx, 30.0)


def make_case(terrain, n: int, m: int, device, seed: int = 0):
    """Particle poses scattered around a true pose, and the point cloud measured from the true pose."""
    rng = np.random.default_rng(seed)
    n_min, n_max, e_min, e_max = terrain.bounds_ne
    centre = np.array([0.5 * (n_min + n_max), 0.5 * (e_min + e_max)])
    truth = np.array([centre[0], centre[1], -(terrain.h_max + 600.0)])
    q_true = euler_to_quat(0.02, -0.01, 0.8)
    cloud = wt.PointCloudSensor(pattern_for(m), range_sigma_m=0.5).measure(terrain, truth, q_true, rng,
                                                                            device=device)
    pos = truth + rng.normal(0.0, [100.0, 100.0, 20.0], (n, 3))
    quats = euler_to_quat(rng.normal(0.02, 0.002, n), rng.normal(-0.01, 0.002, n), rng.normal(0.8, 0.01, n))
    pos_d = wp.array(pos.astype(np.float32), dtype=wp.vec3, device=device)
    quat_d = wp.array(quats.astype(np.float32), dtype=wp.vec4, device=device)
    reading = wt.AltimeterReading(wt.RadarAltimeter().measure(terrain, truth, rng), -truth[2])
    return pos_d, quat_d, cloud, reading


def build_model(name: str, terrain):
    if name in ("mesh", "dda", "bisection"):
        return wt.RaycastModel(terrain, caster=wt.RayCaster(name))
    if name == "sliding":
        return wt.SlidingModel(terrain)
    return wt.AltimeterModel(terrain)


def time_one(model, pos_d, quat_d, measurement, device, repeats: int) -> list[float]:
    """Seconds per evaluation as the filter does it (``stage`` + ``launch`` on the model's own buffers; ``evaluate``
    adds a check of the poses and copies of the outputs for its caller), after one warm-up call, synchronised."""
    model.stage(measurement, pos_d, quat_d)
    model.launch(pos_d, quat_d)
    wp.synchronize_device(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        model.stage(measurement, pos_d, quat_d)
        model.launch(pos_d, quat_d)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return times


def run(devices, terrain, ns, ms, models, repeats, max_config_s, log=print):
    results = []
    for dev_name in devices:
        device = wt.resolve_device(dev_name)
        throughput: dict[str, float] = {}  # best-known work units per second per model, for skipping
        for m in ms:
            for n in ns:
                pos_d, quat_d, cloud, reading = make_case(terrain, n, m, device)
                for name in models:
                    if name == "altimeter" and m != ms[0]:
                        continue  # one sample per particle whatever M is: time it once per N
                    work = n if name == "altimeter" else n * m
                    row = {"device": device.alias, "model": name, "N": n, "M": 1 if name == "altimeter" else m,
                           "work_units": work, "unit": "samples" if name in ("sliding", "altimeter") else "rays"}
                    predicted = work / throughput[name] if name in throughput else 0.0
                    if predicted * (repeats + 1) > max_config_s:
                        row.update(skipped=f"predicted {predicted:.2f} s per step exceeds the budget")
                        results.append(row)
                        continue
                    model = build_model(name, terrain)
                    times = time_one(model, pos_d, quat_d, reading if name == "altimeter" else cloud, device,
                                     repeats)
                    med = statistics.median(times)
                    throughput[name] = max(throughput.get(name, 0.0), work / med)
                    row.update(median_s=med, min_s=min(times), repeats=repeats, per_s=work / med)
                    results.append(row)
                    log(f"  {device.alias:7s} {name:9s} N={n:>7d} M={row['M']:>5d}  {med * 1e3:10.3f} ms")
    # ratio to sliding at the same device, N, M
    sliding = {(r["device"], r["N"], r["M"]): r["median_s"] for r in results
               if r["model"] == "sliding" and "median_s" in r}
    for r in results:
        key = (r["device"], r["N"], r["M"])
        if "median_s" in r and key in sliding:
            r["ratio_to_sliding"] = r["median_s"] / sliding[key]
    return results


def format_table(results) -> str:
    head = f"{'device':7s} {'model':9s} {'N':>7s} {'M':>5s} {'median ms':>11s} {'per second':>14s} {'x sliding':>10s}"
    lines = [head, "-" * len(head)]
    for r in sorted(results, key=lambda r: (r["device"], r["M"], r["N"], MODELS.index(r["model"]))):
        if "median_s" not in r:
            lines.append(f"{r['device']:7s} {r['model']:9s} {r['N']:>7d} {r['M']:>5d} {'skipped':>11s}")
            continue
        ratio = f"{r['ratio_to_sliding']:.1f}" if "ratio_to_sliding" in r else "-"
        rate = f"{r['per_s'] / 1e6:.2f} M {r['unit']}"
        lines.append(f"{r['device']:7s} {r['model']:9s} {r['N']:>7d} {r['M']:>5d} {r['median_s'] * 1e3:11.3f} "
                     f"{rate:>14s} {ratio:>10s}")
    return "\n".join(lines)


def plot(results, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    devices = sorted({r["device"] for r in results})
    fig, axes = plt.subplots(1, len(devices), figsize=(6 * len(devices), 4.5), squeeze=False)
    for ax, dev in zip(axes[0], devices, strict=True):
        for name in MODELS:
            rows = sorted((r for r in results if r["device"] == dev and r["model"] == name and "median_s" in r),
                          key=lambda r: r["work_units"])
            if rows:
                ax.loglog([r["work_units"] for r in rows], [r["median_s"] * 1e3 for r in rows], "o-", label=name,
                          ms=3)
        ax.set_xlabel("N × M (rays or samples per step)")
        ax.set_ylabel("time per measurement update (ms)")
        ax.set_title(f"warptan measurement models on {dev}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", nargs="+", default=["cpu"], help="Warp devices, e.g. cpu cuda:0")
    parser.add_argument("--terrain", default="synthetic:rugged", help="DEM path or synthetic:KIND spec")
    parser.add_argument("--quick", action="store_true", help=f"N in {QUICK_N}, M in {QUICK_M}, 3 repeats")
    parser.add_argument("--n", type=count_arg, nargs="+", help="particle counts (overrides the preset)")
    parser.add_argument("--m", type=count_arg, nargs="+", help="points per scan (overrides the preset)")
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    parser.add_argument("--repeats", type=count_arg, default=None, help="timed repeats (default 7, quick 3)")
    parser.add_argument("--max-config-s", type=number_arg(0.0, True), default=20.0,
                        help="skip configurations predicted slower")
    parser.add_argument("--json", dest="json_out", help="write results here")
    parser.add_argument("--plot", help="write a log-log PNG here")
    args = parser.parse_args(argv)

    terrain = script_inputs("compare_kernel_timings", args.device, args.terrain)
    ns = tuple(args.n or (QUICK_N if args.quick else FULL_N))
    ms = tuple(args.m or (QUICK_M if args.quick else FULL_M))
    repeats = args.repeats or (3 if args.quick else 7)
    print(f"terrain {terrain.name}: {terrain.shape[0]}x{terrain.shape[1]} posts; devices {args.device}; "
          f"N {ns}; M {ms}; median of {repeats}")
    t0 = time.perf_counter()
    results = run(args.device, terrain, ns, ms, args.models, repeats, args.max_config_s)
    print(format_table(results))
    print(f"total {time.perf_counter() - t0:.1f} s")
    if args.json_out:
        meta = run_meta(args.device, terrain=terrain.info(), N=ns, M=ms, repeats=repeats,
                        what="seconds per model stage + launch (residual kernel + per-particle reduction), median")
        write_json(args.json_out, {"meta": meta, "results": results})
        print(f"wrote {args.json_out}")
    if args.plot:
        plot(results, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
