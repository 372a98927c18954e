#!/usr/bin/env python3
"""Whole filter-step timings: one measurement interval of the MPF (``imu_per_meas`` IMU time updates and one
measurement update, resampling included when the filter decides to) for N particles, per model and device.

Reported per configuration (medians over ``--repeats`` intervals after ``--warmup`` intervals, synchronised):
``predict_ms`` (one IMU step: host INS + Riccati, queued particle move), ``update_ms`` (queued moves + poses +
model + weights + resampling), ``step_ms`` (the whole interval) and ``estimate_ms`` (moments → host).

    python scripts/bench_filter_step.py --n 500 5000 --models sliding dda --json step.json
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time

import numpy as np
import warp as wp

import warptan as wt
from warptan.cli import script_inputs
from warptan.imu import ImuModel
from warptan.mpf import MarginalizedParticleFilter
from warptan.runner import InitialErrors, initial_nominal, prior_linear_cov
from warptan.trajectory import Straight, Trajectory

MODELS = ("sliding", "dda", "mesh", "bisection", "altimeter")


def build(model_name: str, terrain, likelihood):
    if model_name == "sliding":
        return wt.SlidingModel(terrain, likelihood)
    if model_name == "altimeter":
        return wt.AltimeterModel(terrain, likelihood)
    return wt.RaycastModel(terrain, likelihood, caster=wt.RayCaster(model_name))


def bench(terrain, model_name, n, m_side, device, repeats, warmup, imu_per_meas=10, seed=0, graph=None):
    intervals = repeats + warmup
    truth = Trajectory.build([Straight(intervals * imu_per_meas / 100.0 + 0.5)], 100.0,
                             [0.0, 0.0, -(terrain.h_max + 600.0)])
    imu = ImuModel("navigation", 100.0, seed=seed)
    f, w, _ = imu.corrupt(truth.f_b, truth.w_b)
    rng = np.random.default_rng(seed)
    initial = InitialErrors()
    mpf = MarginalizedParticleFilter(build(model_name, terrain, wt.Likelihood("paper", r_err=16.0)),
                                     initial_nominal(truth.state(0), initial, rng), imu.grade, 100.0,
                                     np.asarray(initial.pos_m), prior_linear_cov(initial, imu), n_particles=n,
                                     device=device, seed=seed, graph=graph)
    sensor = wt.PointCloudSensor(wt.ScanPattern.grid(m_side, m_side, 30.0))
    alt, baro = wt.RadarAltimeter(), wt.Barometer()
    t_pred, t_upd, t_step, t_est = [], [], [], []
    k = 0
    for it in range(intervals):
        k_meas = k + imu_per_meas
        if model_name == "altimeter":
            meas = wt.AltimeterReading(alt.measure(terrain, truth.pos_n[k_meas], rng),
                                       baro.measure(truth.pos_n[k_meas], rng))
        else:
            meas = sensor.measure(terrain, truth.pos_n[k_meas], truth.quat_nb[k_meas], rng, device=device)
            meas.on_device(device)  # the upload of a scan is part of receiving it, not of the filter step
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        for _ in range(imu_per_meas):
            mpf.predict(f[k], w[k])
            k += 1
        t1 = time.perf_counter()
        mpf.update(meas)
        wp.synchronize_device(device)
        t2 = time.perf_counter()
        mpf.estimate()
        t3 = time.perf_counter()
        if it >= warmup:
            t_pred.append((t1 - t0) / imu_per_meas)
            t_upd.append(t2 - t1)
            t_step.append(t2 - t0)
            t_est.append(t3 - t2)
    med = statistics.median
    return {"model": model_name, "N": n, "M": 1 if model_name == "altimeter" else m_side * m_side,
            "device": wt.resolve_device(device).alias, "imu_per_meas": imu_per_meas,
            "predict_ms": 1e3 * med(t_pred), "update_ms": 1e3 * med(t_upd), "step_ms": 1e3 * med(t_step),
            "estimate_ms": 1e3 * med(t_est), "repeats": repeats}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", nargs="+", default=["cpu"])
    parser.add_argument("--n", type=int, nargs="+", default=[500, 5000])
    parser.add_argument("--m-side", type=int, nargs="+", default=[10], help="scan is m_side × m_side rays")
    parser.add_argument("--models", nargs="+", default=["sliding", "dda"], choices=MODELS)
    parser.add_argument("--terrain", default="synthetic:rugged")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--json", dest="json_out")
    args = parser.parse_args(argv)
    terrain = script_inputs("bench_filter_step", args.device, args.terrain)
    rows = []
    print(f"{'device':7s} {'model':9s} {'N':>7s} {'M':>5s} {'predict ms':>11s} {'update ms':>10s} {'step ms':>9s}")
    for device in args.device:
        for m_side in args.m_side:
            for model in args.models:
                for n in args.n:
                    r = bench(terrain, model, n, m_side, device, args.repeats, args.warmup)
                    rows.append(r)
                    print(f"{r['device']:7s} {model:9s} {n:>7d} {r['M']:>5d} {r['predict_ms']:11.3f} "
                          f"{r['update_ms']:10.3f} {r['step_ms']:9.3f}")
    if args.json_out:
        meta = {"warp_version": wp.config.version, "python": platform.python_version(),
                "devices": {d: wt.resolve_device(d).name for d in args.device}, "terrain": terrain.name,
                "what": "median ms per IMU predict, per measurement update, and per whole interval "
                        "(imu_per_meas predicts + one update)"}
        with open(args.json_out, "w") as f:
            json.dump({"meta": meta, "results": rows}, f, indent=1)
        print(f"wrote {args.json_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
