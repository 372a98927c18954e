"""Shared fixtures: a ``device`` fixture over "cpu" and every CUDA device Warp sees, and the real DEMs.

``--device cpu`` (repeatable) restricts the device list. Without a GPU the CUDA case is reported as a
visible skip. Warp's kernel cache honours ``WARP_CACHE_PATH`` (``.ci/run`` points it at a directory CI
can keep between runs).
"""

import os
from pathlib import Path

import pytest
import warp as wp

wp.config.quiet = True
wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)

# The real DEM tiles the tests fly ship in tests/data/dem (public-domain data, provenance in its README.md);
# WARPTAN_DEM_DIR points elsewhere.
DEM_DIR = Path(os.environ.get("WARPTAN_DEM_DIR") or Path(__file__).resolve().parent / "data" / "dem")
THURINGIA = DEM_DIR / "thuringia_hilly_srtm3_n50e010.tif"
GANGES = DEM_DIR / "ganges_plain_flat_srtm3_n28e078.tif"
BOSPHORUS = DEM_DIR / "bosphorus_istanbul_dted0.tif"


def pytest_addoption(parser):
    parser.addoption("--device", action="append", default=None,
                     help="run device tests only on this Warp device (repeatable), e.g. --device cpu")


def _devices(config):
    wanted = config.getoption("--device")
    present = ["cpu"] + [d.alias for d in wp.get_cuda_devices()]
    if wanted:
        return [d if d in present else pytest.param(d, marks=pytest.mark.skip(reason=f"device {d} not present"))
                for d in wanted]
    if len(present) == 1:
        present.append(pytest.param("cuda:0", marks=pytest.mark.skip(reason="no CUDA device visible to Warp")))
    return present


def pytest_generate_tests(metafunc):
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", _devices(metafunc.config))


def dem_path(path: Path) -> str:
    """The path of a real DEM tile of tests/data/dem (or WARPTAN_DEM_DIR); a missing one is an error, not a skip."""
    if not path.exists():
        raise FileNotFoundError(f"real DEM tile missing: {path} (tests/data/dem ships it; WARPTAN_DEM_DIR = "
                                f"{os.environ.get('WARPTAN_DEM_DIR')!r})")
    return str(path)


@pytest.fixture(scope="session")
def thuringia():
    from warptan import Terrain

    return Terrain.from_raster(dem_path(THURINGIA))


@pytest.fixture(scope="session")
def thuringia_crop():
    """The package's Thuringia crop (``Terrain.load("rugged")``: package data, present on every install)."""
    from warptan import Terrain

    return Terrain.load("rugged")


@pytest.fixture(scope="session")
def rugged_small():
    from warptan import Terrain

    return Terrain.synthetic("rugged", size_m=6000.0, spacing=30.0, seed=1)
