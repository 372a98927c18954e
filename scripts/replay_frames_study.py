"""Flights tied to the Earth, measured over many seeds: each simulated flight (``warptan run`` in memory, over the
package's geographic rugged tile) is replayed from its log over the same DEM, through geodetic CSV tables (GPS
latitude/longitude/height, true-north attitude), over a crop of the DEM (the same posts, another origin), over a
UTM copy (reprojected, bilinear: another map of the same ground) and over a control copy resampled the same way in
the log's own frame (the copies' surfaces against the tile's are measured too). Per scenario: converged horizontal
RMSE, mean ± 95 % interval, per replay; the seeds within issue 36's mark (``≤ 1.25 × the in-memory RMSE + 1 m``);
whether the own-DEM and CSV replays give the in-memory bits. Writes JSON.

    python scripts/replay_frames_study.py --scenarios S8 S7 S9 --seeds 20 --json results/replay_frames.json

An existing ``--json`` file keeps its other scenarios' rows (a row is replaced by its scenario's new one) and lists
every run that wrote it (``meta.runs``, each with its whole provenance; ``meta`` itself is the latest run's); the
file is written after each scenario.
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from warptan.device import quiet_warp
from warptan.io.logcsv import read_tables, write_tables
from warptan.meta import run_meta
from warptan.nav.geoframe import GeoFrame
from warptan.sim.replay import replay
from warptan.sim.report import ci95
from warptan.sim.scenarios import run_scenario
from warptan.terrain.grid import Terrain, named_terrain_file

REPLAYS = ("own", "csv", "crop", "utm", "tmerc")
SAME_FRAME = ("own", "csv")
"""Replays whose estimates are in the in-memory run's frame (compared bit for bit)."""
CROP_POSTS = 40
"""Posts cut from the west and north edges of the geographic tile for the crop (about 2.5 km and 3.7 km)."""
UTM = ("EPSG:32632", 60.0)
"""The projected copy: UTM zone 32N at 60 m posts, bilinear from the 3″ tile."""
TMERC_M = 60.0
"""The control copy: the tile resampled the same way (bilinear, 60 m posts) into its own transverse Mercator, the
log's frame (no convergence, scale 1): what resampling alone changes, without a projection."""


def make_dems(folder: Path) -> dict:
    """The crop, the UTM copy and the transverse Mercator control copy of the package's rugged tile, as GeoTIFFs in
    ``folder``."""
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
        own = GeoFrame.of_terrain(Terrain.load("rugged")).crs_wkt
        for name, (crs, res) in {"utm": UTM, "tmerc": (own, TMERC_M)}.items():  # bilinear copies at 60 m posts
            tr, w, h = calculate_default_transform(src.crs, crs, src.width, src.height, *src.bounds, resolution=res)
            copy = np.full((h, w), -32768.0, np.float32)
            reproject(data, copy, src_transform=t, src_crs=src.crs, dst_transform=tr, dst_crs=crs,
                      resampling=Resampling.bilinear, src_nodata=-32768.0, dst_nodata=-32768.0)
            out = dict(prof, crs=crs, transform=tr, width=w, height=h)
            with rasterio.open(folder / f"{name}.tif", "w", **out) as dst:
                dst.write(copy, 1)
    return {name: str(folder / f"{name}.tif") for name in ("crop", "utm", "tmerc")}


def surface_difference(dems: dict, half_m: float = 8000.0, n: int = 20000) -> dict:
    """RMS and 99th percentile (m) of each copy's triangulated surface minus the tile's at random places within
    ``half_m`` of the tile's centre (the same places on the Earth), each copy read as a replay reads it (onto the
    tile's posts when it is resampled with their spacing; ``own``: the crop read on its own instead): what the copy
    changes in the map."""
    from warptan.nav.geoframe import frame_change

    world = Terrain.load("rugged")
    posts = (GeoFrame.of_terrain(world).crs_wkt, (0.0, 0.0),
             (world.n0, world.e0, world.dn, world.de, *world.heights_m.shape))
    rng = np.random.default_rng(0)
    pos = np.column_stack([rng.uniform(-half_m, half_m, (n, 2)), np.zeros(n)])
    out = {}
    for name, path in {**dems, "crop_own": dems["crop"]}.items():
        copy = Terrain.load(path) if name == "crop_own" else Terrain.load(path, posts=posts)
        moved = frame_change(world, copy, pos[:5]).positions(pos)
        d = copy.surface_height_at(moved[:, 0], moved[:, 1]) - world.surface_height_at(pos[:, 0], pos[:, 1])
        d = d[np.isfinite(d)]
        out[name] = {"rms_m": float(np.sqrt(np.mean(d**2))), "p99_abs_m": float(np.percentile(np.abs(d), 99))}
    return out


def horizontal(result) -> float:
    return float(np.hypot(*result.rmse_converged[:2]))


def one_seed(sid: str, seed: int, dems: dict, folder: Path, duration_s: float | None, device: str) -> dict:
    logs = []
    kw = {} if duration_s is None else {"duration_s": duration_s}
    ref = run_scenario(sid, seed=seed, export_logs=logs, device=device, **kw)
    log = logs[0]
    runs = {"own": replay(log, device=device),
            "csv": replay(read_tables(write_tables(log, folder / f"{sid}_{seed}")), device=device),
            **{name: replay(log, path, device=device) for name, path in dems.items()}}
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
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--surface-only", action="store_true", help="print the copies' surface differences only")
    args = parser.parse_args()
    quiet_warp()
    out = Path(args.json) if args.json else None
    data = json.loads(out.read_text()) if out is not None and out.exists() else {"meta": {"runs": []}, "rows": []}
    this = run_meta(devices=(args.device,))
    runs = [*data["meta"].get("runs", []), this]
    data["meta"] = {**this, "runs": runs, "crop_posts": CROP_POSTS, "utm": list(UTM), "tmerc_m": TMERC_M,
                    "seeds": args.seeds}  # the latest run's provenance, and every run's
    with tempfile.TemporaryDirectory() as tmp:
        dems = make_dems(Path(tmp))
        data["meta"]["copy_minus_tile"] = surface_difference(dems)
        print(json.dumps({"copy_minus_tile": data["meta"]["copy_minus_tile"]}), flush=True)
        for sid in [] if args.surface_only else args.scenarios:
            t0 = time.perf_counter()
            seeds = []
            for seed in range(args.seeds):
                seeds.append(one_seed(sid, seed, dems, Path(tmp), args.duration_s, args.device))
                print(json.dumps({k: v for k, v in seeds[-1].items() if not k.startswith("coverage")}), flush=True)
            row = {**summarise(sid, seeds), "device": args.device, "wall_s": time.perf_counter() - t0}
            print(json.dumps({k: v for k, v in row.items() if k != "per_seed"}), flush=True)
            data["rows"] = [r for r in data["rows"] if r["scenario"] != sid] + [row]
            if out is not None:
                out.write_text(json.dumps(data, indent=1) + "\n")


if __name__ == "__main__":
    main()
