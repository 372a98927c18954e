#!/usr/bin/env python3
"""Whole filter-step timings: one measurement interval of the MPF (``imu_per_meas`` IMU samples and one
measurement update, resampling included when the filter decides to) for B filters × N particles, per model,
device and launch mode (eager launches or a replayed graph).

Reported per configuration (medians over ``--repeats`` intervals after ``--warmup`` intervals, synchronised
before the clock stops): ``predict_ms`` (per IMU sample: the interval's samples are buffered by one
``predict_many`` call), ``update_ms``
(the interval's INS + Riccati, particle moves, poses, model, weights, resampling, record),
``step_ms`` (the whole interval, synchronised: the latency), ``filter_steps_per_s`` (B / step time),
``throughput_step_ms`` (the same intervals run back to back with one synchronisation at the end: the host stages
interval k + 1 while the device runs interval k) and ``estimate_ms`` (moments → host, not part of a step). The
measurement upload is part of the step (``stage``); simulating it is not. Then a third run of intervals with the
filter's own timers on (:class:`warptan.mpf.StepTimer`): the medians ``host_ms`` (Python: IMU buffering, interval
staging, issuing launches or the graph), ``upload_ms`` (validating, packing and copying the measurement to the
device) and ``device_ms`` (the update's device work: CUDA events around it, or the CPU's launches) per interval.

    python scripts/bench_filter_step.py --n 500 5000 --models sliding dda --json step.json
    python scripts/bench_filter_step.py --device cuda:0 --n 500 --batch 1 100 --m-side 20 --graph on off
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import warp as wp

import warptan as wt
from warptan.cli import count_arg, script_inputs
from warptan.imu import ImuModel
from warptan.kernels import mpf as kmpf
from warptan.meta import run_meta
from warptan.mpf import MarginalizedParticleFilter, StepTimer
from warptan.outputs import write_json
from warptan.runner import InitialErrors, initial_nominal, prior_linear_cov
from warptan.trajectory import Straight, Trajectory

MODELS = ("sliding", "dda", "mesh", "bisection", "altimeter")


def build(model_name: str, terrain, likelihood):
    if model_name == "sliding":
        return wt.SlidingModel(terrain, likelihood)
    if model_name == "altimeter":
        return wt.AltimeterModel(terrain, likelihood)
    return wt.RaycastModel(terrain, likelihood, caster=wt.RayCaster(model_name))


def bench(terrain, model_name, n, m_side, device, repeats, warmup, imu_per_meas=10, seed=0, graph=None, batch=1,
          likelihood="paper"):
    intervals = repeats + warmup
    truth = Trajectory.build([Straight(3 * intervals * imu_per_meas / 100.0 + 0.5)], 100.0,
                             [0.0, 0.0, -(terrain.h_max + 600.0)])
    imu = ImuModel("navigation", 100.0, seed=seed)
    f, w, _ = imu.corrupt(truth.f_b, truth.w_b)
    rng = np.random.default_rng(seed)
    initial = InitialErrors()
    nominal = [initial_nominal(truth.state(0), initial, rng) for _ in range(batch)]
    mpf = MarginalizedParticleFilter(build(model_name, terrain, wt.Likelihood(likelihood, r_err=16.0)),
                                     nominal if batch > 1 else nominal[0], imu.grade, 100.0,
                                     np.asarray(initial.pos_m), prior_linear_cov(initial, imu), n_particles=n,
                                     device=device, seed=list(range(seed, seed + batch)) if batch > 1 else seed,
                                     graph=graph)
    f = np.repeat(f[:, None], batch, axis=1) if batch > 1 else f
    w = np.repeat(w[:, None], batch, axis=1) if batch > 1 else w
    sensor = wt.PointCloudSensor(wt.ScanPattern.grid(m_side, m_side, 30.0))
    alt, baro = wt.RadarAltimeter(), wt.Barometer()
    t_pred, t_upd, t_step, t_est = [], [], [], []
    measurements = []
    for it in range(3 * intervals):
        k_meas = (it + 1) * imu_per_meas
        if model_name == "altimeter":
            meas = [wt.AltimeterReading(alt.measure(terrain, truth.pos_n[k_meas], rng),
                                        baro.measure(truth.pos_n[k_meas], rng)) for _ in range(batch)]
        else:
            meas = sensor.measure_many(terrain, truth.pos_n[k_meas], truth.quat_nb[k_meas], [rng] * batch,
                                       device=device)
        measurements.append(meas if batch > 1 else meas[0])
    k = 0
    for it in range(intervals):  # latency: each interval synchronised before the clock stops
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        mpf.predict_many(f[k:k + imu_per_meas], w[k:k + imu_per_meas])
        k += imu_per_meas
        t1 = time.perf_counter()
        mpf.update(measurements[it], sync=False)
        wp.synchronize_device(device)
        t2 = time.perf_counter()
        mpf.estimate()
        t3 = time.perf_counter()
        if it >= warmup:
            t_pred.append((t1 - t0) / imu_per_meas)
            t_upd.append(t2 - t1)
            t_step.append(t2 - t0)
            t_est.append(t3 - t2)
    # throughput: the next intervals back to back, one synchronisation at the end (the host prepares interval
    # k + 1 while the device runs interval k)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for it in range(intervals, 2 * intervals):
        mpf.predict_many(f[k:k + imu_per_meas], w[k:k + imu_per_meas])
        k += imu_per_meas
        mpf.update(measurements[it], sync=False)
    wp.synchronize_device(device)
    throughput_ms = 1e3 * (time.perf_counter() - t0) / intervals
    # breakdown: the filter's timers, each interval synchronised (CUDA event times are read at the end)
    mpf.timer = StepTimer()
    for it in range(2 * intervals, 3 * intervals):
        mpf.predict_many(f[k:k + imu_per_meas], w[k:k + imu_per_meas])
        k += imu_per_meas
        mpf.update(measurements[it], sync=False)
        wp.synchronize_device(device)
    parts = {name: float(np.median(v[warmup:])) for name, v in mpf.timer.times().items()}
    mpf.timer = None
    med = statistics.median
    stages = mpf.history()[warmup:, :, kmpf.H_STAGES]
    return {"model": model_name, "likelihood": likelihood, "B": batch, "N": n, "graph": mpf.graph,
            "tempering_stages_mean": float(stages.mean()), "tempering_stages_max": int(stages.max()),
            "filter_steps_per_s": batch / med(t_step), "M": 1 if model_name == "altimeter" else m_side * m_side,
            "device": wt.resolve_device(device).alias, "imu_per_meas": imu_per_meas,
            "predict_ms": 1e3 * med(t_pred), "update_ms": 1e3 * med(t_upd), "step_ms": 1e3 * med(t_step),
            "estimate_ms": 1e3 * med(t_est), "throughput_step_ms": throughput_ms, "repeats": repeats,
            "host_ms": parts["host"], "upload_ms": parts["upload"], "device_ms": parts["device"]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", nargs="+", default=["cpu"])
    parser.add_argument("--n", type=count_arg, nargs="+", default=[500, 5000])
    parser.add_argument("--m-side", type=count_arg, nargs="+", default=[10], help="scan is m_side × m_side rays")
    parser.add_argument("--models", nargs="+", default=["sliding", "dda"], choices=MODELS)
    parser.add_argument("--batch", type=count_arg, nargs="+", default=[1], help="filters per batch B")
    parser.add_argument("--graph", nargs="+", default=["auto"], choices=["auto", "on", "off"],
                        help="replay a captured graph (auto: on CUDA only)")
    parser.add_argument("--terrain", default="synthetic:rugged")
    parser.add_argument("--likelihood", nargs="+", default=["paper"], choices=["paper", "gaussian", "student_t"])
    parser.add_argument("--repeats", type=count_arg, default=20)
    parser.add_argument("--warmup", type=count_arg, default=3)
    parser.add_argument("--json", dest="json_out")
    args = parser.parse_args(argv)
    terrain = script_inputs("bench_filter_step", args.device, args.terrain)
    rows = []
    print(f"{'device':7s} {'model':9s} {'lik':8s} {'graph':5s} {'B':>4s} {'N':>7s} {'M':>5s} {'predict ms':>11s} "
          f"{'update ms':>10s} {'step ms':>9s} {'pipelined':>9s} {'filter-steps/s':>15s} {'stages':>6s} "
          f"{'host':>6s} {'upload':>6s} {'device':>6s}")
    modes = {"auto": None, "on": True, "off": False}
    for device in args.device:
        for m_side in args.m_side:
            for model in args.models:
                for b in args.batch:
                    for n in args.n:
                        for g in args.graph:
                            for lik in args.likelihood:
                                r = bench(terrain, model, n, m_side, device, args.repeats, args.warmup,
                                          graph=modes[g], batch=b, likelihood=lik)
                                rows.append(r)
                                print(f"{r['device']:7s} {model:9s} {lik:8s} {r['graph']!s:5s} {b:>4d} {n:>7d} "
                                      f"{r['M']:>5d} {r['predict_ms']:11.3f} {r['update_ms']:10.3f} "
                                      f"{r['step_ms']:9.3f} {r['throughput_step_ms']:9.3f} "
                                      f"{r['filter_steps_per_s']:15.0f} "
                                      f"{r['tempering_stages_mean']:6.2f} {r['host_ms']:6.3f} "
                                      f"{r['upload_ms']:6.3f} {r['device_ms']:6.3f}")
    if args.json_out:
        meta = run_meta(args.device, terrain=terrain.name,
                        what="median ms per IMU predict call, per measurement update, and per whole interval "
                             "(imu_per_meas predicts + one update) of B filters x N particles; filter_steps_per_s = "
                             "B / step time; host_ms / upload_ms / device_ms: median breakdown of an interval from "
                             "the filter's StepTimer (warptan.mpf)")
        write_json(args.json_out, {"meta": meta, "results": rows})
        print(f"wrote {args.json_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
