"""Where the host's time of a synchronised step goes after a 100 ms pause (one filter of S7 on CUDA, B = 1; session 41):
host ``perf_counter`` stamps around the filter's methods (``predict_many`` with its run-ahead graph launch, ``check``,
the head's graph, ``stage``, the update's graph, ``_next_set``) and the wait for the device, medians per mode: no pause,
100 ms busy-waiting (also with a CUDA synchronisation or the model's ``check`` every millisecond) or sleeping.
``idle_host_pieces_h100.json``: after a pause every piece of host work is 1.2-4x slower (``predict_many`` 52 -> 244 µs,
its graph launch 21 -> 108 µs; the update's Python 91 -> 192 µs), the device's share is not.

    python3 idle_host_pieces.py SCRIPTS_DIR OUT.json S7 STEPS   (copied outside the checkout)
"""
import json
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])
import bench_filter_step as bfs

from warptan.device import quiet_warp

quiet_warp()
out_path, sid, steps = sys.argv[2], sys.argv[3], int(sys.argv[4])
mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
scans, ipm = bfs.scenario_scans(setup, steps), setup["imu_per_meas"]
marks = {}
pc = time.perf_counter


def wrap(cls, name):
    plain = getattr(cls, name)

    def wrapped(self, *a, **k):
        marks[name + ">"] = pc()
        r = plain(self, *a, **k)
        marks[name + "<"] = pc()
        return r
    setattr(cls, name, wrapped)


for nm in ("_advance", "_stage_interval", "_queue_head", "_queue_update", "_next_set", "_replay"):
    wrap(type(mpf), nm)
for nm in ("check", "stage"):
    wrap(type(mpf.model), nm)


def busy(s, ping=False, touch=False):
    t = pc() + s
    nxt = pc()
    while pc() < t:
        if ping and pc() >= nxt:
            wp.synchronize_device("cuda:0")
            nxt = pc() + 0.001
        if touch and pc() >= nxt:
            mpf.model.check(scans[0])
            nxt = pc() + 0.001


MODES = {"none": lambda: None, "busy100ms": lambda: busy(0.1), "busy100ms+cudaping1ms": lambda: busy(0.1, ping=True),
         "busy100ms+check1ms": lambda: busy(0.1, touch=True), "sleep100ms": lambda: time.sleep(0.1)}
names = list(MODES)
rows = {k: {} for k in names}
for it in range(steps):
    mode = names[it % len(names)]
    wp.synchronize_device("cuda:0")
    MODES[mode]()
    marks.clear()
    t0 = pc()
    mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
    t1 = pc()
    mpf.update(scans[it], sync=False)
    t2 = pc()
    wp.synchronize_device("cuda:0")
    t3 = pc()
    if it < 60:
        continue
    m = marks
    piece = {"wall": t3 - t0, "predict_many": t1 - t0, "advance(graph)": m["_advance<"] - m["_advance>"],
             "update": t2 - t1, "check": m["check<"] - m["check>"],
             "head(graph)": m["_queue_head<"] - m["_queue_head>"],
             "stage": m["stage<"] - m["stage>"], "queue_update(graph)": m["_queue_update<"] - m["_queue_update>"],
             "next_set": m["_next_set<"] - m["_next_set>"], "sync_wait": t3 - t2}
    for k, v in piece.items():
        rows[mode].setdefault(k, []).append(1e6 * v)
res = {mode: {k: round(float(np.median(v)), 1) for k, v in r.items()} for mode, r in rows.items()}
for mode, r in res.items():
    print(sid, mode, json.dumps(r), flush=True)
json.dump(res, open(out_path, "w"), indent=1)
