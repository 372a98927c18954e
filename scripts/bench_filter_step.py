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
filter's own timers on (:class:`warptan.filter.records.StepTimer`): the medians ``host_ms`` (Python: IMU buffering,
interval staging, issuing launches or the graph), ``upload_ms`` (validating, packing and copying the measurement to the
device) and ``device_ms`` (the update's device work: CUDA events around it, or the CPU's launches) per interval.

With ``--scenario S8 [S7 ...]`` each row is the filter that scenario flies (its map, surface, likelihood, scan,
rates, tempering, regularisation and attitude update: :func:`warptan.sim.scenarios.scenario_model`,
:meth:`~warptan.sim.scenario_config.FilterSpec.config`), measured on its own flight after ``--settle-s`` of it
(acquisition is not the steady state); ``--n`` and ``--batch`` still apply. With ``--paced-s T`` a filter of B = 1
then flies T s more at the flight's own rates, twice, its host sleeping until each piece is due as a real-time loop's
does (:func:`paced_run`): ``paced_step_ms`` (the interval's samples in one call and the update, synchronised, each
interval started when due) and ``paced_update_ms`` (each IMU sample predicted when due, the update's latency from the
scan to the synchronised end), medians and 90th percentiles: back-to-back steps keep the host's caches and the driver
warm, which a 10 Hz filter's idle gaps do not. Such a row also reports the achieved
point evaluations per second (B · N · M · tempering stages per update time) beside the bare model kernel's rate on
the same poses and scan (the bound: ``model.launch`` alone), and, with ``--rtf-s T``, the real-time factor of a
whole run of the scenario (T s flown by :func:`~warptan.sim.scenarios.run_scenario` with N particles, after a short
run that compiles).

    python scripts/bench_filter_step.py --n 500 5000 --models sliding dda --json step.json
    python scripts/bench_filter_step.py --device cuda:0 --n 500 --batch 1 100 --m-side 20 --graph on off
    python scripts/bench_filter_step.py --scenario S8 S7 --n 500 --rtf-s 20 --json scenario_step.json
    python scripts/bench_filter_step.py --device cuda:0 --scenario S8 S7 --scan-side 20 --n 500 --batch 1 100
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

import warptan as wt
from warptan.cli import count_arg, script_inputs
from warptan.filter.config import FilterConfig
from warptan.filter.mpf import MarginalizedParticleFilter
from warptan.filter.prior import InitialErrors, initial_nominal, prior_linear_cov
from warptan.filter.records import StepTimer
from warptan.kernels import mpf as kmpf
from warptan.meta import run_meta
from warptan.nav.imu import ImuModel
from warptan.nav.trajectory import Straight, Trajectory
from warptan.outputs import write_json

MODELS = ("sliding", "dda", "mesh", "bisection", "altimeter")


def build(model_name: str, terrain, likelihood):
    if model_name == "sliding":
        return wt.SlidingModel(terrain, likelihood)
    if model_name == "altimeter":
        return wt.AltimeterModel(terrain, likelihood)
    return wt.RaycastModel(terrain, likelihood, caster=wt.RayCaster(model_name))


def generic_setup(terrain, model_name, m_side, likelihood, intervals, imu_per_meas=10):
    """The generic configuration: a straight flight 600 m over the terrain, navigation IMU, 30° scan of
    m_side × m_side rays, the likelihood with its defaults (``r_err`` 16 m² for the paper's)."""
    truth = Trajectory.build([Straight(3 * intervals * imu_per_meas / 100.0 + 0.5)], 100.0,
                             [0.0, 0.0, -(terrain.h_max + 600.0)])
    return {"model": build(model_name, terrain, wt.Likelihood(likelihood, r_err=16.0)), "filter": FilterConfig(),
            "truth": truth, "world": terrain, "grade": "navigation", "imu_per_meas": imu_per_meas, "start": 0,
            "sensor": wt.PointCloudSensor(wt.ScanPattern.grid(m_side, m_side, 30.0)),
            "altimeter": (wt.RadarAltimeter(), wt.Barometer()), "initial": InitialErrors(), "label": model_name}


def scenario_setup(sid, device, settle_s, terrain=None, **overrides):
    """The filter scenario ``sid`` flies (model, surface, likelihood, scan, rates, filter keywords; ``overrides`` as
    :func:`~warptan.sim.scenarios.run_scenario` takes them), its flight and world; measurement starts ``settle_s`` into
    the flight (the intervals before run untimed)."""
    from warptan.sim.scenarios import map_terrain, prepare, scenario_likelihood, scenario_model

    scenario, world, flight = prepare(sid, terrain=terrain, device=device, **overrides)
    the_map = map_terrain(world, scenario, int(scenario.run.seed))
    s = scenario.sensor
    model = scenario_model(scenario, the_map, scenario_likelihood(scenario, the_map, world))
    imu_per_meas = round(scenario.imu.rate_hz / s.rate_hz)
    label = s.model if s.model != "raycast" else s.backend
    return {"model": model, "filter": scenario.filter.config(), "truth": flight, "world": world,
            "grade": scenario.imu.grade, "imu_per_meas": imu_per_meas, "label": f"{sid}:{label}",
            "start": round(settle_s * scenario.imu.rate_hz / imu_per_meas),
            "sensor": wt.PointCloudSensor(wt.ScanPattern.grid(s.scan_nx, s.scan_ny, s.scan_half_angle_deg),
                                          range_sigma_m=s.range_sigma_m),
            "altimeter": (wt.RadarAltimeter(s.altimeter_sigma_m), wt.Barometer(s.baro_sigma_m)),
            "initial": scenario.initial_error.errors(), "config": scenario}


def scenario_filter(sid: str, device: str, n: int = 500, scan_side: int = 20, seed: int = 0):
    """One filter of scenario ``sid`` with ``n`` particles and a ``scan_side``² scan, as :func:`bench` builds it:
    ``(filter, specific forces, body rates, setup)`` (the IMU samples of the seed's IMU)."""
    setup = scenario_setup(sid, device, 10.0, scan_nx=scan_side, scan_ny=scan_side)
    truth = setup["truth"]
    imu = ImuModel(setup["grade"], truth.rate_hz, seed=seed)
    f, w, _ = imu.corrupt(truth.f_b, truth.w_b)
    nominal = initial_nominal(truth.state(0), setup["initial"], np.random.default_rng(seed))
    mpf = MarginalizedParticleFilter(setup["model"], nominal, imu.grade, truth.rate_hz,
                                     np.asarray(setup["initial"].pos_m), prior_linear_cov(setup["initial"], imu),
                                     setup["filter"], n_particles=n, device=device, seed=seed)
    return mpf, f, w, setup


def scenario_scans(setup, steps: int, seed: int = 1) -> list:
    """The scans of :func:`scenario_filter`'s flight at its first ``steps`` measurement times (the sensor's noise from
    ``seed``)."""
    ipm, truth, sensor, world = setup["imu_per_meas"], setup["truth"], setup["sensor"], setup["world"]
    rng = np.random.default_rng(seed)
    return [sensor.measure(world, truth.pos_n[(it + 1) * ipm], truth.quat_nb[(it + 1) * ipm], rng)
            for it in range(steps)]


def synchronised_steps(mpf, f, w, setup, steps: int):
    """Fly ``steps`` intervals of :func:`scenario_filter`'s flight (its IMU samples, then :func:`scenario_scans`),
    synchronising the device after each; yields each interval's index once it is done."""
    ipm, scans = setup["imu_per_meas"], scenario_scans(setup, steps)
    for it in range(steps):
        mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
        mpf.update(scans[it], sync=False)
        wp.synchronize_device(mpf.device)
        yield it


def write_cuda_results(path: str, argv: list[str], doc: str, results: dict) -> None:
    """A CUDA benchmark script's JSON (the ``benchmarks/issue32`` scripts): ``meta`` (:func:`~warptan.meta.run_meta` of
    ``cuda:0``, its command the script's name and ``argv``, ``what`` its docstring's first paragraph) and
    ``results``."""
    meta = run_meta(["cuda:0"], command=" ".join([Path(argv[0]).name, *argv[1:]]), what=doc.split("\n\n")[0])
    write_json(path, {"meta": meta, "results": results})


def kernel_rate(model, pos, quat, measurement, device, repeats=20) -> float:
    """Point evaluations per second of the model kernel alone (``launch`` on staged poses; the bound)."""
    m = model.stage(measurement, pos, quat).residual_m.shape[1]
    for _ in range(3):
        model.launch(pos, quat)
    wp.synchronize_device(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        model.launch(pos, quat)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    return pos.shape[0] * m / statistics.median(times)


def bench(setup, n, device, repeats, warmup, seed=0, graph=None, batch=1, paced_s=0.0):
    intervals = repeats + warmup
    truth, terrain, imu_per_meas, start = setup["truth"], setup["world"], setup["imu_per_meas"], setup["start"]
    model = setup["model"]
    imu = ImuModel(setup["grade"], truth.rate_hz, seed=seed)
    f, w, _ = imu.corrupt(truth.f_b, truth.w_b)
    rng = np.random.default_rng(seed)
    initial = setup["initial"]
    nominal = [initial_nominal(truth.state(0), initial, rng) for _ in range(batch)]
    mpf = MarginalizedParticleFilter(model, nominal if batch > 1 else nominal[0], imu.grade, truth.rate_hz,
                                     np.asarray(initial.pos_m), prior_linear_cov(initial, imu), setup["filter"],
                                     n_particles=n, device=device,
                                     seed=list(range(seed, seed + batch)) if batch > 1 else seed, graph=graph)
    f = np.repeat(f[:, None], batch, axis=1) if batch > 1 else f
    w = np.repeat(w[:, None], batch, axis=1) if batch > 1 else w
    sensor, (alt, baro) = setup["sensor"], setup["altimeter"]
    altimeter = isinstance(model, wt.AltimeterModel)
    n_paced = round(paced_s * truth.rate_hz / imu_per_meas)  # intervals of each paced run
    if len(truth.f_b) < (start + 3 * intervals + 2 * n_paced) * imu_per_meas + 1:
        raise SystemExit(f"bench_filter_step: error: the flight of {setup['label']} is too short for --settle-s, "
                         f"{3 * intervals} intervals and --paced-s")
    t_pred, t_upd, t_step, t_est = [], [], [], []
    measurements = []
    for it in range(start + 3 * intervals + 2 * n_paced):
        k_meas = (it + 1) * imu_per_meas
        if altimeter:
            meas = [wt.AltimeterReading(alt.measure(terrain, truth.pos_n[k_meas], rng),
                                        baro.measure(truth.pos_n[k_meas], rng)) for _ in range(batch)]
        else:
            meas = sensor.measure_many(terrain, truth.pos_n[k_meas], truth.quat_nb[k_meas], [rng] * batch,
                                       device=device)
        measurements.append(meas if batch > 1 else meas[0])
    k = 0
    for it in range(start):  # the part of the flight before measuring (a scenario's acquisition)
        mpf.predict_many(f[k:k + imu_per_meas], w[k:k + imu_per_meas])
        k += imu_per_meas
        mpf.update(measurements[it], sync=False)
    measurements = measurements[start:]
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
    med = statistics.median
    mpf.timer = None
    paced = {}
    if n_paced:
        rest = measurements[3 * intervals:]
        step_s, k = paced_run(mpf, f, w, rest[:n_paced], k, imu_per_meas, truth.rate_hz, per_sample=False)
        update_s, k = paced_run(mpf, f, w, rest[n_paced:], k, imu_per_meas, truth.rate_hz, per_sample=True)
        paced = {"paced_s": n_paced * imu_per_meas / truth.rate_hz,
                 "paced_step_ms": 1e3 * med(step_s), "paced_step_p90_ms": 1e3 * float(np.percentile(step_s, 90)),
                 "paced_update_ms": 1e3 * med(update_s),
                 "paced_update_p90_ms": 1e3 * float(np.percentile(update_s, 90))}
    stages = mpf.history()[start + warmup:start + 3 * intervals, :, kmpf.H_STAGES]
    m = 1 if altimeter else sensor.pattern.m
    row = {"model": setup["label"], "likelihood": model.likelihood.kind, "B": batch, "N": n, "graph": mpf.graph,
           "tempering_stages_mean": float(stages.mean()), "tempering_stages_max": int(stages.max()),
           "filter_steps_per_s": batch / med(t_step), "M": m,
           "device": wt.resolve_device(device).alias, "imu_per_meas": imu_per_meas,
           "predict_ms": 1e3 * med(t_pred), "update_ms": 1e3 * med(t_upd), "step_ms": 1e3 * med(t_step),
           "estimate_ms": 1e3 * med(t_est), "throughput_step_ms": throughput_ms, "repeats": repeats,
           "host_ms": parts["host"], "upload_ms": parts["upload"], "device_ms": parts["device"], **paced}
    if "config" in setup:  # the scenario's own filter: what its points cost against the kernel's bound
        row["scenario"] = setup["config"].id
        row["settle_s"] = start * imu_per_meas / truth.rate_hz
        row["point_evals_per_s"] = batch * n * m * float(stages.mean()) / (1e-3 * row["update_ms"])
        row["kernel_point_evals_per_s"] = kernel_rate(model, mpf._pos, mpf._quat, measurements[-1], device)
        row["surface"] = "triangles" if getattr(model, "surface", True) else "bilinear"
    return row


def paced_run(mpf, f, w, measurements, k: int, imu_per_meas: int, rate_hz: float, per_sample: bool):
    """Fly ``measurements`` at the flight's own rates, as a real-time loop does: the host sleeps until each IMU sample
    (``per_sample``: one ``predict_many`` call per sample at 1 / ``rate_hz``, the update's latency timed from its call
    to the synchronised end) or each measurement is due (else the interval's samples in one call and the update,
    synchronised: the step of the synchronised loop, but after the interval's idle time; between two such steps the
    host and device idle as a 10 Hz filter's do, which back-to-back steps never see). Returns (each timed latency in
    s, the next IMU index)."""
    dt = 1.0 / rate_hz
    lat = []
    due = time.perf_counter()
    for meas in measurements:
        if per_sample:
            for _ in range(imu_per_meas):
                due += dt
                time.sleep(max(due - time.perf_counter(), 0.0))
                mpf.predict_many(f[k:k + 1], w[k:k + 1])
                k += 1
            t0 = time.perf_counter()
        else:
            due += imu_per_meas * dt
            time.sleep(max(due - time.perf_counter(), 0.0))
            t0 = time.perf_counter()
            mpf.predict_many(f[k:k + imu_per_meas], w[k:k + imu_per_meas])
            k += imu_per_meas
        mpf.update(meas, sync=False)
        wp.synchronize_device(mpf.device)
        lat.append(time.perf_counter() - t0)
    return lat, k


def real_time_factor(sid, device, n, duration_s, terrain=None, repeats=5, **overrides) -> dict:
    """Whole runs of the scenario (N particles, ``duration_s`` flown, seed 0) after a 2 s run that compiles: flight time
    over the median wall time of ``repeats`` runs (:attr:`warptan.sim.scenarios.ScenarioResult.wall_s`: the filter loop
    with the simulated sensor; one run of a shared 2-core VM varied by up to 1.3×), and every run's wall time."""
    from warptan.sim.scenarios import run_scenario

    run_scenario(sid, 0, device, terrain=terrain, particles=n, duration_s=2.0, **overrides)
    walls = [run_scenario(sid, 0, device, terrain=terrain, particles=n, duration_s=duration_s, **overrides).wall_s
             for _ in range(repeats)]
    wall = statistics.median(walls)
    return {"rtf_flight_s": duration_s, "rtf_wall_s": wall, "rtf_walls_s": walls, "real_time_factor": duration_s / wall}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", nargs="+", default=["cpu"])
    parser.add_argument("--n", type=count_arg, nargs="+", default=[500, 5000])
    parser.add_argument("--scenario", nargs="+", default=None,
                        help="the filters these scenarios fly (default S8 S7 unless --models is given)")
    parser.add_argument("--settle-s", type=float, default=10.0, help="scenario flight before measuring, s")
    parser.add_argument("--scan-side", type=count_arg, default=None,
                        help="scenarios: a scan of this many × this many rays instead of the scenario's")
    parser.add_argument("--rtf-s", type=float, default=0.0,
                        help="also whole runs of each scenario this long: their real-time factor (0: none)")
    parser.add_argument("--rtf-repeats", type=count_arg, default=5,
                        help="whole runs per real-time factor (their median wall time)")
    parser.add_argument("--models", nargs="+", default=None, choices=MODELS,
                        help="the generic configuration instead (straight flight, default likelihood settings)")
    parser.add_argument("--m-side", type=count_arg, nargs="+", default=[10],
                        help="generic: scan is m_side × m_side rays")
    parser.add_argument("--batch", type=count_arg, nargs="+", default=[1], help="filters per batch B")
    parser.add_argument("--graph", nargs="+", default=["auto"], choices=["auto", "on", "off"],
                        help="replay a captured graph (auto: on CUDA only)")
    parser.add_argument("--terrain", default="synthetic:rugged", help="generic: the terrain")
    parser.add_argument("--likelihood", nargs="+", default=["paper"], choices=["paper", "gaussian", "student_t"],
                        help="generic: the likelihood")
    parser.add_argument("--paced-s", type=float, default=0.0,
                        help="B = 1: also fly this long at the flight's own rates, twice (the host sleeping until "
                             "each interval or each IMU sample is due): paced_step_ms, paced_update_ms (0: none)")
    parser.add_argument("--repeats", type=count_arg, default=20)
    parser.add_argument("--warmup", type=count_arg, default=3)
    parser.add_argument("--json", dest="json_out")
    args = parser.parse_args(argv)
    scenarios = args.scenario if args.scenario is not None else ([] if args.models else ["S8", "S7"])
    scan = {} if args.scan_side is None else {"scan_nx": args.scan_side, "scan_ny": args.scan_side}
    terrain = script_inputs("bench_filter_step", args.device, args.terrain)
    if args.settle_s < 0 or args.rtf_s < 0 or args.paced_s < 0:
        parser.error("--settle-s, --rtf-s and --paced-s must be ≥ 0 s")
    from warptan.sim.scenario_config import load_config

    for sid in scenarios:  # an unknown scenario or a bad file: one line, exit 2, before any work
        try:
            load_config(sid, **scan)
        except (ValueError, OSError) as err:
            print(f"bench_filter_step: error: {err}", file=sys.stderr)
            return 2
    rows = []
    print(f"{'device':7s} {'model':12s} {'lik':8s} {'graph':5s} {'B':>4s} {'N':>7s} {'M':>5s} {'predict ms':>11s} "
          f"{'update ms':>10s} {'step ms':>9s} {'pipelined':>9s} {'filter-steps/s':>15s} {'stages':>6s} "
          f"{'host':>6s} {'upload':>6s} {'device':>6s} {'Mpt/s':>7s} {'kernel':>7s} {'RTF':>6s}")
    modes = {"auto": None, "on": True, "off": False}
    intervals = args.repeats + args.warmup
    for device in args.device:
        setups = []
        for sid in scenarios:
            try:
                setups.append(scenario_setup(sid, device, args.settle_s, **scan))
            except (ValueError, OSError) as err:  # a DEM that cannot be read: one line, exit 2
                print(f"bench_filter_step: error: {err}", file=sys.stderr)
                return 2
        setups += [generic_setup(terrain, model, m_side, lik, intervals)
                   for m_side in args.m_side for model in args.models or [] for lik in args.likelihood]
        for setup in setups:
            rtf = {}
            if "config" in setup and args.rtf_s > 0:
                rtf = real_time_factor(setup["config"].id, device, args.n[0], args.rtf_s,
                                       repeats=args.rtf_repeats, **scan)
            for b in args.batch:
                for n in args.n:
                    for g in args.graph:
                        r = {**bench(setup, n, device, args.repeats, args.warmup, graph=modes[g], batch=b,
                                       paced_s=args.paced_s if b == 1 else 0.0),
                             **(rtf if n == args.n[0] and b == 1 else {})}
                        rows.append(r)
                        print(f"{r['device']:7s} {r['model']:12s} {r['likelihood']:8s} {r['graph']!s:5s} {b:>4d} "
                              f"{n:>7d} {r['M']:>5d} {r['predict_ms']:11.3f} {r['update_ms']:10.3f} "
                              f"{r['step_ms']:9.3f} {r['throughput_step_ms']:9.3f} {r['filter_steps_per_s']:15.0f} "
                              f"{r['tempering_stages_mean']:6.2f} {r['host_ms']:6.3f} {r['upload_ms']:6.3f} "
                              f"{r['device_ms']:6.3f} {r.get('point_evals_per_s', float('nan')) / 1e6:7.1f} "
                              f"{r.get('kernel_point_evals_per_s', float('nan')) / 1e6:7.1f} "
                              f"{r.get('real_time_factor', float('nan')):6.1f}")
    if args.json_out:
        meta = run_meta(args.device, terrain=terrain.name if args.models else "the scenarios' own",
                        what="median ms per IMU predict call, per measurement update, and per whole interval "
                             "(imu_per_meas predicts + one update) of B filters x N particles; filter_steps_per_s = "
                             "B / step time; host_ms / upload_ms / device_ms: median breakdown of an interval from "
                             "the filter's StepTimer (warptan.filter.mpf); scenario rows (model 'Sx:kind'): the filter "
                             "the scenario flies, measured after settle_s of its flight, point_evals_per_s = B N M "
                             "stages / update time against kernel_point_evals_per_s (the model kernel alone), "
                             "real_time_factor = rtf_flight_s / rtf_wall_s, the median of rtf_walls_s, whole runs "
                             "(B = 1, the first N)")
        write_json(args.json_out, {"meta": meta, "results": rows})
        print(f"wrote {args.json_out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
