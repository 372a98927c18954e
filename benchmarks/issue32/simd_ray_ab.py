"""The CPU's DDA ray casts in SIMD lanes (``kernels/simd_ray.py``) against the per-particle Warp kernel they stand in
for (``raycast_residual_rows_kernel``), on the inputs a scenario's filter gives them (session 41): the filter of
``SID`` (N = 500, its 10 x 10 scan, CPU) flies 40 updates; at every eighth its last model launch's inputs are cast by
both kernels into fresh outputs (ranges, normals and heights above the map compared bit for bit), and at the last two
both are timed as the scenario launches them, alternated, 40 launches each on one thread (``wp.launch``: no split over
cores), medians in ms.

    python3 benchmarks/issue32/simd_ray_ab.py OUT.json [S7 S5 ...]   (from a folder outside the checkout)
"""
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import bench_filter_step as bfs

import warptan.sensing.measurement as meas
from warptan.device import quiet_warp
from warptan.kernels import raycast as kray
from warptan.kernels import simd_ray as ksimd_ray
from warptan.meta import run_meta


def run(sid: str) -> dict:
    captured = {}
    plain = meas.launch_rows

    def capture(kernel, rows, args, device, **kw):
        if kernel.key.startswith("raycast_residual_rows"):
            captured["launch"] = (rows, args)
        return plain(kernel, rows, args, device, **kw)

    meas.launch_rows = capture
    try:
        mpf, f, w, setup = bfs.scenario_filter(sid, "cpu", scan_side=10)
        scans, ipm = bfs.scenario_scans(setup, 40), setup["imu_per_meas"]
        checks, times = [], {"warp_ms": [], "simd_ms": []}
        for it in range(40):
            mpf.predict_many(f[it * ipm:(it + 1) * ipm], w[it * ipm:(it + 1) * ipm])
            mpf.update(scans[it], sync=True)
            if it % 8 != 7:
                continue
            rows, args = captured["launch"]
            ins, outs = args(None, None)
            got = {}
            for name, kernel in (("warp_ms", kray.raycast_residual_rows_kernel),
                                 ("simd_ms", ksimd_ray.raycast_residual_rows_simd_kernel)):
                o = [wp.clone(outs[0]), wp.clone(outs[1]), 1, wp.clone(outs[3])]  # (heights above the map too)
                wp.launch(kernel, dim=rows, inputs=ins, outputs=o, device="cpu")
                got[name] = (o[0].numpy(), o[1].numpy(), o[3].numpy())
            same = all(np.array_equal(a.view(np.uint32), b.view(np.uint32))
                       for a, b in zip(got["warp_ms"], got["simd_ms"], strict=True))
            checks.append({"update": it, "rays": int(got["warp_ms"][0].size), "bit_identical": same,
                           "hits": int(np.isfinite(got["warp_ms"][0]).sum())})
            if it >= 31:  # timed as the scenario runs them (its own want_vertical)
                o = [wp.clone(outs[0]), wp.clone(outs[1]), outs[2], wp.clone(outs[3])]
                for _ in range(40):
                    for name, kernel in (("warp_ms", kray.raycast_residual_rows_kernel),
                                         ("simd_ms", ksimd_ray.raycast_residual_rows_simd_kernel)):
                        t0 = time.perf_counter()
                        wp.launch(kernel, dim=rows, inputs=ins, outputs=o, device="cpu")
                        times[name].append(1e3 * (time.perf_counter() - t0))
    finally:
        meas.launch_rows = plain
    res = {k: statistics.median(v) for k, v in times.items()}
    return {"checks": checks, **res, "speedup": res["warp_ms"] / res["simd_ms"]}


def main():
    quiet_warp()
    out, sids = sys.argv[1], sys.argv[2:] or ["S7"]
    results = {sid: run(sid) for sid in sids}
    for sid, r in results.items():
        print(sid, json.dumps({k: v for k, v in r.items() if k != "checks"}),
              "bit-identical" if all(c["bit_identical"] for c in r["checks"]) else "DIFFERENT")
    meta = run_meta(["cpu"], command=" ".join(["simd_ray_ab.py", *sys.argv[1:]]), what=__doc__.split("\n\n")[0])
    with open(out, "w") as fh:
        json.dump({"meta": meta, "results": results}, fh, indent=1)


if __name__ == "__main__":
    main()
