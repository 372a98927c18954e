"""Where the stage block and the record block of one filter's update spend their time, on CUDA (S8 / S7, B = 1, N = 500,
20 x 20 scan): copies of ``stage_block_kernel`` and ``record_block_kernel`` in which lane 0 writes the GPU's
``%globaltimer`` at the start, after every barrier and at the end (generated from ``kernels/filter/blocks.py``'s
source into a scratch module) replace them in the filter's launches; medians over the steps of the time from one stamp
to the next (µs; stamp k follows the k-th barrier, 63 is the end; the stage block of an update's last stage).

    python3 benchmarks/issue32/stamps_blocks.py scripts OUT.json STEPS S8 S7   (from a folder outside the checkout)
"""
import importlib.util
import itertools
import json
import re
import statistics
import sys
import tempfile

import numpy as np
import warp as wp

sys.path.insert(0, sys.argv[1])  # scripts/: bench_filter_step's scenario setup
import bench_filter_step as bfs

import warptan.filter.program as prog
import warptan.kernels.filter.blocks as blocks
from warptan.device import quiet_warp

GTIME = '''
@wp.func_native('unsigned long long t; asm volatile("mov.u64 %0, %%globaltimer;" : "=l"(t)); return (wp::int64)t;')
def gtime() -> wp.int64: ...


'''
END = "    more: wp.array(dtype=wp.int32),\n):"


def _stamped(body: str, old: str, new: str) -> str:
    """``body`` (one kernel's source) renamed ``new``, with a ``tbuf`` argument and lane 0's stamps."""
    body = body.replace(END, "    more: wp.array(dtype=wp.int32),\n    tbuf: wp.array(dtype=wp.int64),\n):", 1)
    body = body.replace(f"def {old}(", f"def {new}(", 1)
    count = [0]

    def stamp_after(m):
        count[0] += 1
        ind = m.group(1)
        return f"{ind}block_sync()\n{ind}if lane == 0:\n{ind}    tbuf[{count[0]}] = gtime()\n"
    body = re.sub(r"^( +)block_sync\(\)\n", stamp_after, body, flags=re.M)
    first = "    b, lane = wp.tid()\n"
    body = body.replace(first, first + "    if lane == 0:\n        tbuf[0] = gtime()\n", 1)
    return body.rstrip("\n") + "\n    if lane == 0:\n        tbuf[63] = gtime()\n\n\n"


def stamped_module():
    src = open(blocks.__file__).read()
    a = src.index("@wp.kernel(cuda_max_registers=STAGE_MAX_REGISTERS)\ndef stage_block_kernel(")
    e = src.index("@wp.kernel\ndef move_pose_kernel(")
    r = src.index("@wp.kernel\ndef record_block_kernel(")
    text = (src[:a] + GTIME + _stamped(src[a:e], "stage_block_kernel", "stage_block_stamped") + src[e:r]
            + _stamped(src[r:], "record_block_kernel", "record_block_stamped"))
    path = tempfile.mkdtemp() + "/stamped_blocks.py"
    with open(path, "w") as fh:
        fh.write(text)
    spec = importlib.util.spec_from_file_location("stamped_blocks", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _intervals(t: np.ndarray, prefix: str, rows: dict) -> None:
    idx = [i for i in range(64) if t[i] != 0]
    for p, q in itertools.pairwise(idx):
        rows.setdefault(f"{prefix}{p}->{q}", []).append((t[q] - t[p]) * 1e-3)
    rows.setdefault(f"{prefix}total", []).append((t[63] - t[0]) * 1e-3)


def main():
    quiet_warp()
    out_path, steps = sys.argv[2], int(sys.argv[3])
    sb = stamped_module()
    stage_t, record_t = (wp.zeros(64, dtype=wp.int64, device="cuda:0") for _ in range(2))
    plain_launch = prog.launch

    def launch(kernel, *args, **kw):
        if kernel is prog.kmpf.stage_block_kernel:
            kernel, kw["outputs"] = sb.stage_block_stamped, [*kw["outputs"], stage_t]
        elif kernel is prog.kmpf.record_block_kernel:
            kernel, kw["outputs"] = sb.record_block_stamped, [*kw["outputs"], record_t]
        return plain_launch(kernel, *args, **kw)
    prog.launch = launch
    res = {}
    for sid in sys.argv[4:]:
        mpf, f, w, setup = bfs.scenario_filter(sid, "cuda:0")
        rows = {}
        for it in bfs.synchronised_steps(mpf, f, w, setup, steps):
            if it >= 30:
                _intervals(stage_t.numpy(), "stage ", rows)
                _intervals(record_t.numpy(), "record ", rows)
            stage_t.zero_()
            record_t.zero_()
        res[sid] = {k: statistics.median(v) for k, v in rows.items()}
        print(sid, json.dumps({k: round(v, 2) for k, v in res[sid].items()}))
    bfs.write_cuda_results(out_path, sys.argv, __doc__, res)


if __name__ == "__main__":
    main()
