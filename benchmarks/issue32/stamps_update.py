"""Where one filter's update graph spends its device time, on CUDA (S8 / S7, B = 1, N = 500, 20 x 20 scan): a
one-thread kernel writes the GPU's ``%globaltimer`` between the graph's pieces (the scan's staged copies, each stage's
model, each stage's tempering and resampling, the tail), captured into the graph with them; medians over the steps of
the time from one stamp to the next (µs; each stamp adds a node of its own, ~1-2 µs).

    python3 benchmarks/issue32/stamps_update.py scripts OUT.json STEPS S8 S7   (from a folder outside the checkout)
"""
import json
import statistics
import sys

import warp as wp

sys.path.insert(0, sys.argv[1])  # scripts/: bench_filter_step's scenario setup
import bench_filter_step as bfs

from warptan.device import quiet_warp
from warptan.filter.program import UpdateProgram


@wp.func_native('unsigned long long t; asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(t)); return (wp::int64)t;')
def gtime() -> wp.int64: ...


@wp.kernel
def stamp_kernel(buf: wp.array(dtype=wp.int64), i: int):
    buf[i] = gtime()


BUF = None
LABELS = []


def stamp(label: str) -> None:
    LABELS.append(label)
    wp.launch(stamp_kernel, dim=1, inputs=[BUF, len(LABELS) - 1], device="cuda:0")


def instrument() -> None:
    def staged_update(self, staged, out, read_flags=False):
        LABELS.clear()
        BUF.zero_()
        stamp("start")
        for work in staged:
            work()
        stamp("scan_staged")
        self._device_update(out, read_flags=read_flags)
        stamp("end")

    def after(name, label):
        plain = getattr(UpdateProgram, name)

        def inner(self, *a, **k):
            r = plain(self, *a, **k)
            stamp(label(a))
            return r
        setattr(UpdateProgram, name, inner)

    UpdateProgram._staged_update = staged_update
    after("_launch_stage", lambda a: f"stage{a[1]}")
    after("_launch_resample", lambda a: f"resample{a[0]}")


def main():
    global BUF
    quiet_warp()
    out_path, steps = sys.argv[2], int(sys.argv[3])
    BUF = wp.zeros(64, dtype=wp.int64, device="cuda:0")
    instrument()
    res = {}
    for sid in sys.argv[4:]:
        mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
        model_cls = type(mpf.model)
        if "_plain_launch" not in model_cls.__dict__:
            model_cls._plain_launch = model_cls.launch

            def model_launch(self, pos, quat, cls=model_cls):
                r = cls._plain_launch(self, pos, quat)
                stamp("model")
                return r
            model_cls.launch = model_launch
        rows = {}
        for it in bfs.synchronised_steps(mpf, f, w, setup, steps):
            if it < 30:
                continue
            t, prev = BUF.numpy(), None
            for i, label in enumerate(LABELS):
                if t[i] == 0:  # (a stage that did not run)
                    continue
                if prev is not None:
                    rows.setdefault(f"{prev[1]}->{label}", []).append((t[i] - prev[0]) * 1e-3)
                prev = (t[i], label)
            rows.setdefault("total start->end", []).append((t[LABELS.index("end")] - t[0]) * 1e-3)
        res[sid] = {k: {"median_us": statistics.median(v), "count": len(v)} for k, v in rows.items()}
        print(sid, json.dumps({k: (round(v["median_us"], 1), v["count"]) for k, v in res[sid].items()}))
    bfs.write_cuda_results(out_path, sys.argv, __doc__, res)


if __name__ == "__main__":
    main()
