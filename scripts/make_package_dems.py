"""Write the real terrains shipped with the package (``warptan/data/dem``) from the source tiles.

Each output is a window of a source tile read without resampling (the same int16 posts, georeferencing, nodata
and tags; DEFLATE, tiled), centred on the source's centre so that the scenarios' ``centre`` placement and the
reprojection centre are where they are on the full tile. The windows hold every scenario's track with its
margin in any heading: ±22 km for the rugged tile (S5/S6 orbit beside the highest hill, 17–18 km north-east
of the centre), ±12 km for the flat one; the 30 m tile (19 × 36 km) is shipped whole. Provenance:
``warptan/data/dem/README.md``.

    python scripts/make_package_dems.py --source tests/data/dem
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import rasterio
from rasterio.windows import Window

# package name -> (source file, half-size north and east in m; None: the whole file)
CROPS = {
    "thuringia_hilly_srtm3_crop44km.tif": ("thuringia_hilly_srtm3_n50e010.tif", 22_000.0),
    "ganges_plain_flat_srtm3_crop24km.tif": ("ganges_plain_flat_srtm3_n28e078.tif", 12_000.0),
    "san_gabriel_rugged_srtm1_30m_utm11.tif": ("san_gabriel_rugged_srtm1_30m_utm11.tif", None),
}
EARTH_M_PER_DEG = 111_195.0  # mean-sphere metres per degree of latitude (only sizes the window)


def window_for(src, half_m: float | None) -> Window:
    """A window centred on the source's centre pixel, ``half_m`` each side (whole raster for None)."""
    if half_m is None:
        return Window(0, 0, src.width, src.height)
    if src.crs.is_geographic:
        lat = src.xy(src.height // 2, src.width // 2)[1]
        dy = abs(src.transform.e) * EARTH_M_PER_DEG
        dx = abs(src.transform.a) * EARTH_M_PER_DEG * math.cos(math.radians(lat))
    else:
        dx, dy = abs(src.transform.a), abs(src.transform.e)
    hr, hc = math.ceil(half_m / dy), math.ceil(half_m / dx)
    # symmetric about the centre: the same number of pixels dropped from either side
    r0, c0 = (src.height - (2 * hr + 1)) // 2, (src.width - (2 * hc + 1)) // 2
    if r0 < 0 or c0 < 0:
        raise SystemExit(f"{src.name}: a ±{half_m:g} m window is larger than the raster")
    return Window(c0, r0, src.width - 2 * c0, src.height - 2 * r0)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", default="tests/data/dem", help="folder of the source tiles")
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "warptan" / "data" / "dem"))
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, (source, half_m) in CROPS.items():
        with rasterio.open(Path(args.source) / source) as src:
            win = window_for(src, half_m)
            data = src.read(1, window=win)
            profile = src.profile.copy()
            profile.update(width=int(win.width), height=int(win.height), transform=src.window_transform(win),
                           compress="deflate", predictor=2, tiled=True, blockxsize=256, blockysize=256)
            tags = src.tags()
            tags["CROP"] = (f"rows {win.row_off}..{win.row_off + win.height - 1}, cols {win.col_off}.."
                            f"{win.col_off + win.width - 1} of {source} ({src.height}×{src.width}), posts unchanged")
            with rasterio.open(out / name, "w", **profile) as dst:
                dst.write(data, 1)
                dst.update_tags(**tags)
            nodata = int(np.count_nonzero(data == src.nodata)) if src.nodata is not None else 0
            print(f"{name}: {data.shape[0]}×{data.shape[1]} posts from {source}, {nodata} nodata, "
                  f"{(out / name).stat().st_size / 1024:.0f} KiB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
