#!/usr/bin/env python3
"""Digests (SHA-256) of everything a short filter run leaves behind — particles, weights, Kalman P, nominal INS,
the update records — per model, likelihood and batch size: the check that a change to how the step runs (fused
launches, graphs, kernel restructuring) keeps the same bits for the same seed. Run it on two commits (same machine,
same device) and compare the JSON files:

    python scripts/step_digest.py --device cpu --json before.json   # on the old commit
    python scripts/step_digest.py --device cpu --json after.json --compare before.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys

import numpy as np

import warptan as wt
from warptan.filter.mpf import MarginalizedParticleFilter
from warptan.filter.prior import InitialErrors, initial_nominal, prior_linear_cov
from warptan.kernels import mpf as kmpf
from warptan.meta import run_meta
from warptan.nav.imu import ImuModel
from warptan.nav.trajectory import Straight, Trajectory, Turn
from warptan.outputs import write_json

CASES = [("sliding", "gaussian", 1), ("sliding", "paper", 1), ("sliding", "student_t", 1), ("sliding", "gaussian", 3),
         ("dda", "gaussian", 1), ("dda", "paper", 1), ("dda", "gaussian", 3), ("mesh", "gaussian", 1),
         ("altimeter", "gaussian", 1), ("altimeter", "paper", 2)]


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def run_case(terrain, model_name, likelihood, batch, device, updates=12, imu_per_meas=10, seed=7, n=300,
             closed_loop=False):
    truth = Trajectory.build([Straight(0.5), Turn(5.0, 20.0, 0.3), Straight(1.0)], 100.0,
                             [0.0, 0.0, -(terrain.h_max + 500.0)])
    imu = ImuModel("tactical", 100.0, seed=seed)
    f, w, _ = imu.corrupt(truth.f_b, truth.w_b)
    rng = np.random.default_rng(seed)
    initial = InitialErrors()
    nominal = [initial_nominal(truth.state(0), initial, rng) for _ in range(batch)]
    lik = wt.Likelihood(likelihood, r_err=16.0)
    if model_name == "sliding":
        model = wt.SlidingModel(terrain, lik, surface=True)
    elif model_name == "altimeter":
        model = wt.AltimeterModel(terrain, lik)
    else:
        model = wt.RaycastModel(terrain, lik, caster=wt.RayCaster(model_name))
    mpf = MarginalizedParticleFilter(model, nominal if batch > 1 else nominal[0], imu.grade, 100.0,
                                     np.asarray(initial.pos_m), prior_linear_cov(initial, imu), n_particles=n,
                                     device=device, seed=list(range(seed, seed + batch)) if batch > 1 else seed,
                                     closed_loop=closed_loop, integrity_window=2)
    sensor = wt.PointCloudSensor(wt.ScanPattern.grid(8, 8, 30.0))
    alt, baro = wt.RadarAltimeter(), wt.Barometer()
    k = 0
    for _ in range(updates):
        for _ in range(imu_per_meas):
            mpf.predict(np.repeat(f[k][None], batch, 0) if batch > 1 else f[k],
                        np.repeat(w[k][None], batch, 0) if batch > 1 else w[k])
            k += 1
        if model_name == "altimeter":
            meas = [wt.AltimeterReading(alt.measure(terrain, truth.pos_n[k], rng), baro.measure(truth.pos_n[k], rng))
                    for _ in range(batch)]
        else:
            meas = sensor.measure_many(terrain, truth.pos_n[k], truth.quat_nb[k], [rng] * batch, device=device)
        mpf.update(meas if batch > 1 else meas[0], sync=False)
    st = mpf.state
    return {"particles": _digest(st.dp.numpy(), st.lin.numpy(), st.logw.numpy()), "history": _digest(mpf.history()),
            "P": _digest(mpf.covariance_history(), mpf.P), "nominal": _digest(mpf.nominal_history()),
            "stages": int(mpf.history()[:, :, kmpf.H_STAGES].sum())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", dest="json_out")
    parser.add_argument("--compare", help="a JSON file of this script from another commit: exit 1 unless identical")
    args = parser.parse_args(argv)
    terrain = wt.Terrain.synthetic("rugged")
    rows = {}
    for model, lik, batch in CASES:
        for closed in (False, True):
            key = f"{model}/{lik}/B{batch}" + ("/closed" if closed else "")
            rows[key] = run_case(terrain, model, lik, batch, args.device, closed_loop=closed)
            print(key, rows[key])
    if args.json_out:
        write_json(args.json_out, {"meta": run_meta([args.device]), "digests": rows})
    if args.compare:
        with open(args.compare) as fh:
            ref = json.load(fh)["digests"]
        diff = [k for k in rows if rows[k] != ref.get(k)]
        print("identical" if not diff else f"DIFFERENT: {', '.join(diff)}")
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
