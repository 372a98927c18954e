"""``warptan log import`` and ``warptan log export``: CSV tables to a flight log and back, written whole or not at
all."""

from __future__ import annotations

import os
from pathlib import Path


def _log_import(args) -> int:
    from warptan.io.flightlog import LogError, write_log
    from warptan.io.logcsv import read_tables
    from warptan.outputs import write_failure

    out = Path(args.out)
    if out.exists():
        raise LogError(f"--out {out}", ["exists; remove it or choose another name"])
    log = read_tables(args.layout)
    try:
        write_log(log, out, exclusive=True)
    except FileExistsError:
        raise LogError(f"--out {out}", ["was written by another process meanwhile; nothing was replaced"]) from None
    except OSError as err:
        raise LogError(f"--out {out}", [f"writing it failed: {write_failure(err)}; nothing was written"]) from None
    f = log.frame
    print(f"wrote {out}: {len(log.imu_t)} IMU samples, {len(log.scan_t) if log.has_scans else 0} scans, "
          f"{len(log.alt_t) if log.has_altimeter else 0} altimeter readings; frame origin lat {f.origin_lat_deg:.6f}°, "
          f"lon {f.origin_lon_deg:.6f}° (datum {f.vertical_datum or 'not stated'})")
    return 0


def _log_export(args) -> int:
    import shutil
    import tempfile

    from warptan.io.flightlog import LogError, read_log
    from warptan.io.logcsv import write_tables
    from warptan.outputs import current_umask, write_failure

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise LogError(f"--out {out}", ["is a file; give the name of a new folder"])
    if out.exists() and any(out.iterdir()):
        raise LogError(f"--out {out}", ["is not empty; choose a new folder"])
    if not out.absolute().parent.is_dir():
        raise LogError(f"--out {out}", [f"its parent folder {out.absolute().parent} does not exist"])
    log = read_log(args.log)
    # the tables are written into a folder beside --out and renamed into place whole: a failed write (a full disk)
    # leaves nothing (it had left a truncated scans.csv and no layout.toml)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.warptan-partial-", dir=out.absolute().parent))
    try:
        layout = write_tables(log, tmp).name
        os.chmod(tmp, 0o777 & ~current_umask())
        if out.exists():
            out.rmdir()  # (empty)
        os.rename(tmp, out)
    except OSError as err:
        where = Path(err.filename).name if err.filename else "a table"
        raise LogError(f"--out {out}", [f"writing {where} failed: {write_failure(err)}; nothing was written"]) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"wrote {out / layout} and its tables in {out}")
    return 0
