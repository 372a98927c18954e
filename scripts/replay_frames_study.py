"""Flights tied to the Earth, measured over many seeds: each simulated flight (``warptan run`` in memory, over the
package's geographic rugged tile) is replayed from its log over the same DEM, through geodetic CSV tables (GPS
latitude/longitude/height, true-north attitude), over a crop of the DEM (the same posts, another origin) and over
a UTM copy (reprojected, bilinear: another map of the same ground). Per scenario: converged horizontal RMSE, mean
± 95 % interval, per replay; the seeds within issue 36's mark (``≤ 1.25 × the in-memory RMSE + 1 m``); whether the
own-DEM and CSV replays give the in-memory bits. Writes JSON.

    python scripts/replay_frames_study.py --scenarios S8 S7 S9 --seeds 20 --json results/replay_frames.json
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from warptan.device import quiet_warp
from warptan.logcsv import read_tables, write_tables
from warptan.meta import run_meta
from warptan.replay import replay
from warptan.report import ci95
from warptan.scenarios import run_scenario
from warptan.terrain import named_terrain_file

REPLAYS = ("own", "csv", "crop", "utm")
SAME_FRAME = ("own", "csv")
"""Replays whose estimates are in the in-memory run's frame (compared bit for bit)."""
CROP_POSTS = 40
"""Posts cut from the west and north edges of the geographic tile for the crop (about 2.5 km and 3.7 km)."""
UTM = ("EPSG:32632", 60.0)
"""The projected copy: UTM zone 32N at 60 m posts, bilinear from the 3″ tile."""


def make_dems(folder: Path) -> dict:
    """The crop and the UTM copy of the package's rugged tile, as GeoTIFFs in ``folder``."""
    import rasterio
    from rasterio.warp import Resampling, calculate_default_transform, reproject
    from rasterio.windows import Window, transform

    with rasterio.open(named_terrain_file("rugged")) as src:
        data, prof, t = src.read(1).astype(np.float32), src.profile, src.transform
        prof.update(dtype="float32", nodata=-32768.0)
        win = Window(CROP_POSTS, CROP_POSTS, src.width - CROP_POSTS, src.height - CROP_POSTS)
        crop = dict(prof, width=win.width, height=win.height, transform=transform(win, t))
        with rasterio.open(folder / "crop.tif", "w", **crop) as dst:
            dst.write(data[CROP_POSTS:, CROP_POSTS:], 1)
        crs, res = UTM
        tr, w, h = calculate_default_transform(src.crs, crs, src.width, src.height, *src.bounds, resolution=res)
        utm = np.full((h, w), -32768.0, np.float32)
        reproject(data, utm, src_transform=t, src_crs=src.crs, dst_transform=tr, dst_crs=crs,
                  resampling=Resampling.bilinear, src_nodata=-32768.0, dst_nodata=-32768.0)
        with rasterio.open(folder / "utm.tif", "w", **dict(prof, crs=crs, transform=tr, width=w, height=h)) as dst:
            dst.write(utm, 1)
    return {"crop": str(folder / "crop.tif"), "utm": str(folder / "utm.tif")}


def horizontal(result) -> float:
    return float(np.hypot(*result.rmse_converged[:2]))


def one_seed(sid: str, seed: int, dems: dict, folder: Path, duration_s: float | None) -> dict:
    logs = []
    kw = {} if duration_s is None else {"duration_s": duration_s}
    ref = run_scenario(sid, seed=seed, export_logs=logs, **kw)
    log = logs[0]
    runs = {"own": replay(log), "csv": replay(read_tables(write_tables(log, folder / f"{sid}_{seed}"))),
            "crop": replay(log, dems["crop"]), "utm": replay(log, dems["utm"])}
    row = {"seed": seed, "memory": horizontal(ref), "coverage_memory": ref.summary()["coverage_3sigma"]}
    for name, r in runs.items():
        row[name] = horizontal(r)
        row[f"coverage_{name}"] = r.summary()["coverage_3sigma"]
        if name in SAME_FRAME:  # the others' estimates are in their DEM's frame
            row[f"max_est_diff_{name}_m"] = float(np.max(np.abs(r.run.est_pos - ref.run.est_pos)))
            row[f"{name}_identical"] = bool(np.array_equal(r.run.est_pos, ref.run.est_pos))
        else:
            row[f"{name}_turn_deg"] = float(r.run.info.get("frame_turn_deg", 0.0))
    return row


def summarise(sid: str, seeds: list[dict]) -> dict:
    ref = np.array([s["memory"] for s in seeds])
    out = {"scenario": sid, "seeds": len(seeds)}
    for name in ("memory", *REPLAYS):
        h = np.array([s[name] for s in seeds])
        mean, half = ci95(h)
        out[f"{name}_rmse_mean_m"], out[f"{name}_rmse_ci95_m"] = float(mean), float(half)
        if name != "memory":
            out[f"{name}_within_mark"] = int(np.sum(h <= 1.25 * ref + 1.0))
            if name in SAME_FRAME:
                out[f"{name}_identical"] = int(sum(s[f"{name}_identical"] for s in seeds))
                out[f"{name}_max_est_diff_m"] = float(max(s[f"max_est_diff_{name}_m"] for s in seeds))
            out[f"{name}_coverage_mean"] = np.mean([s[f"coverage_{name}"] for s in seeds], axis=0).tolist()
    out["memory_coverage_mean"] = np.mean([s["coverage_memory"] for s in seeds], axis=0).tolist()
    out["per_seed"] = seeds
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=["S8", "S7", "S9"])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--duration-s", type=float, default=None, help="default: the scenario's")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    quiet_warp()
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        dems = make_dems(Path(tmp))
        for sid in args.scenarios:
            seeds = []
            for seed in range(args.seeds):
                seeds.append(one_seed(sid, seed, dems, Path(tmp), args.duration_s))
                print(json.dumps({k: v for k, v in seeds[-1].items() if not k.startswith("coverage")}), flush=True)
            rows.append(summarise(sid, seeds))
            print(json.dumps({k: v for k, v in rows[-1].items() if k != "per_seed"}), flush=True)
    if args.json:
        meta = run_meta(command="replay_frames_study.py " + " ".join(
            f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}"
            for k, v in vars(args).items() if v is not None and k != "json"))
        meta.update(wall_s=time.perf_counter() - t0, crop_posts=CROP_POSTS, utm=list(UTM))
        Path(args.json).write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
