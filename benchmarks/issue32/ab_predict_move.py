"""In-process A/B of one synchronised S7 / S8 step on CUDA (B = 1, N = 500, 20 x 20 scan), filters stepped alternately:

* ``base``: ``predict_many`` / ``_buffer`` / ``_advance`` as at the revision whose ``warptan/filter/intake.py`` and
  ``program.py`` are given (bound to that filter);
* ``new``: the code as it is;
* ``premove``: the code as it is, and ``predict_many`` (run-ahead) also moves the particles: the interval's samples,
  the moves, the poses and the statistics' reset in one graph at ``predict_many`` (the update's head), so that the
  update queues no head of its own (a prototype bound here).

Their estimates must be bit-identical (one ``predict_many`` per interval).

    python3 benchmarks/issue32/ab_predict_move.py scripts OLD_INTAKE.py OLD_PROGRAM.py OUT.json
"""
import importlib.util
import json
import statistics
import sys
import types

import numpy as np

sys.path.insert(0, sys.argv[1])  # scripts/: bench_filter_step's scenario setup
import bench_filter_step as bfs
from ab_interval_first import alternate  # (this folder)

STEPS, WARMUP = 900, 100


def load(name, path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


old_intake, old_program = load("old_intake", sys.argv[2]), load("old_program", sys.argv[3])


def premove_advance(self):
    if not (self._k and self._run_ahead and self._head_first()):
        return
    if not self.graph or self._graph_key is None:
        return type(self)._advance(self)
    self._stage_interval()
    self._replay("premove", self._launch_lean_head)
    self._premoved = True


def premove_update(self, measurement, sync=True):
    if not (getattr(self, "_premoved", False) and self._k == 0):
        return type(self).update(self, measurement, sync=sync)
    self._stage_interval = lambda: None
    self._queue_head = lambda: None
    try:
        return type(self).update(self, measurement, sync=sync)
    finally:
        del self._stage_interval, self._queue_head
        self._premoved = False


def build(sid, variant):
    mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
    if variant == "base":
        mpf._imu_np = [x.numpy() for x in mpf._imu_host]  # (what 3cd212c's _buffer writes through)
        for name in ("predict_many", "_buffer"):
            setattr(mpf, name, types.MethodType(getattr(old_intake.ImuIntake, name), mpf))
        mpf._advance = types.MethodType(old_program.UpdateProgram._advance, mpf)
    elif variant == "premove":
        mpf._advance = types.MethodType(premove_advance, mpf)
        mpf.update = types.MethodType(premove_update, mpf)
    return mpf, f, w, setup


def main():
    out = {}
    for sid in ("S7", "S8"):
        filters = {v: build(sid, v) for v in ("base", "new", "premove")}
        setup = filters["base"][3]
        ipm, truth, sensor, world = setup["imu_per_meas"], setup["truth"], setup["sensor"], setup["world"]
        rng = np.random.default_rng(1)
        scans = [sensor.measure(world, truth.pos_n[(it + 1) * ipm], truth.quat_nb[(it + 1) * ipm], rng)
                 for it in range(STEPS)]
        times = alternate(filters, scans, ipm, STEPS, WARMUP, 1e6)
        est = {name: filters[name][0].estimate().nav.pos_n.tolist() for name in filters}
        out[sid] = {name: {"median_us": statistics.median(v), "p25": float(np.percentile(v, 25)),
                           "p75": float(np.percentile(v, 75))} for name, v in times.items()}
        out[sid]["same_estimate"] = {name: est[name] == est["base"] for name in filters}
        print(sid, json.dumps(out[sid]), flush=True)
    with open(sys.argv[4], "w") as fh:
        json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
