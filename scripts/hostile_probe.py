"""Try the ``warptan`` command as a hostile user would and judge every case (issue 66's wider probe).

Each case runs ``warptan.cli.main`` in this process (one Warp start for all) in a fresh folder holding a DEM, a
flight log, tables, a scenario file and a user's own files, all checksummed before and after. A case is **bad**
when a file the command did not write changed or vanished, when a raw traceback, errno or crash reached the user,
or when a case that must fail exited 0; **unclear** when the error is not one line starting ``warptan: error:``;
else good. Writes ``--json`` (every case, its status, exit code and last stderr line) and prints the bad and
unclear ones::

    python scripts/hostile_probe.py --json results/hostile_probe.json
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

QUICK = ["--duration-s", "0.5", "--particles", "16", "--quiet", "--no-plots"]
SCENARIO_EDITS = {"particles-str": ("particles = ", 'particles = "many"\n#'),
                  "rate-neg": ("rate_hz = ", "rate_hz = -100\n#"),
                  "scan-huge": ("scan_nx = ", "scan_nx = 100000\n#"),
                  "duration-nan": ("duration_s = ", "duration_s = nan\n#"),
                  "unknown-key": ("[filter]", "[filter]\nparticels = 5"),
                  "dup-key": ("[filter]", "[filter]\nparticles = 5\nparticles = 6")}
CAMPAIGNS = {"empty": "", "no-scenarios": "seeds = 2\n", "bad-seeds": 'scenarios=["S8"]\nseeds=-1\n',
             "unknown-override": 'scenarios=["S8"]\n[overrides]\nparticules=10\n',
             "sweep-empty": 'scenarios=["S8"]\n[sweep]\nparticles=[]\n',
             "sweep-bad": 'scenarios=["S8"]\n[sweep]\nparticles=[0]\n', "huge": 'scenarios=["S8"]\nseeds=1000000\n',
             "dem-in-out": 'scenarios=["S8"]\n[overrides]\nduration_s=0.5\nparticles=16\nterrain="cout/dem.npz"\n',
             "not-toml": "[[["}
BAD_WORDS = ("Traceback", "[Errno", "Errno ", "Segmentation", "core dumped", "Exception ignored")


def _checksums(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and not p.is_symlink():
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _fixtures(base: Path) -> dict[str, Path]:
    """A DEM (GeoTIFF crop of the shipped rugged tile as .npz and .tif), a flight log, its tables, a scenario."""
    from warptan import cli
    from warptan.io.flightlog import read_log
    from warptan.io.logcsv import write_tables
    from warptan.terrain.grid import Terrain

    base.mkdir(parents=True)
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        status = cli.main(["run", "S8", *QUICK, "--export-log", str(base / "L"), "--out", str(base / "R")])
    if status != 0:
        raise SystemExit(f"the fixture run failed: {err.getvalue()[-2000:]}")
    log = base / "L" / "S8_seed0.h5"
    tables = write_tables(read_log(log), base / "tables")
    Terrain.synthetic(size_m=8000.0).save_npz(base / "dem.npz")
    scenario = Path(cli.__file__).resolve().parents[1] / "scenario_files" / "S8.toml"
    shutil.copy(scenario, base / "S8.toml")
    return {"log": log, "tables": tables, "npz": base / "dem.npz", "toml": base / "S8.toml"}


def _cases(f: dict[str, Path]) -> list[tuple[str, list[str], str]]:
    """(name, argv, expect) with expect 'ok' (exit 0), 'error' (exit 1 or 2) or 'any'."""
    log, npz, toml, tables = (str(f[k]) for k in ("log", "npz", "toml", "tables"))
    cases: list[tuple[str, list[str], str]] = []

    def add(name, argv, expect="error"):
        cases.append((name, [str(a) for a in argv], expect))

    # output folders
    for name, out in [("out=input-dem", npz), ("out=input-log", log), ("out=tables-folder", Path(tables).parent),
                      ("out=log-folder", Path(log).parent), ("out=user-folder", "mine"), ("out=file", "afile"),
                      ("out=dev-null", "/dev/null"), ("out=proc", "/proc/self"), ("out=empty", ""),
                      ("out=long", "x" * 300), ("out=root", "/"), ("out=dot", "."), ("out=inside-file", "afile/sub")]:
        add(f"run {name}", ["run", "S8", *QUICK, "--out", out])
    add("run out=newline", ["run", "S8", *QUICK, "--out", "a\nb"], "any")  # (a legal folder name)
    add("run out=readonly", ["run", "S8", *QUICK, "--out", "ro/sub"], "ok" if os.geteuid() == 0 else "error")
    add("run out=readonly-parent-ok-elsewhere", ["run", "S8", *QUICK, "--out", "fresh"], "ok")
    add("replay out=log", ["replay", log, "--quiet", "--no-plots", "--out", log])
    add("replay out=tables", ["replay", log, "--quiet", "--no-plots", "--out", Path(tables).parent])
    add("replay out=user", ["replay", log, "--quiet", "--no-plots", "--out", "mine"])
    add("export-log=out", ["run", "S8", *QUICK, "--out", "same", "--export-log", "same"])
    add("export-log=user", ["run", "S8", *QUICK, "--out", "new1", "--export-log", "mine"])
    add("export-log=file", ["run", "S8", *QUICK, "--out", "new2", "--export-log", "afile"])
    add("terrain info out=input", ["terrain", "info", npz, "--information", "--out", npz, "--overwrite"])
    add("terrain export out=input", ["terrain", "export", npz, npz, "--overwrite"])
    add("terrain export out=log", ["terrain", "export", npz, log, "--overwrite"])
    add("terrain export out=dir", ["terrain", "export", npz, "mine"])
    add("terrain export bad-suffix", ["terrain", "export", npz, "x.docx"])
    add("log import out=log", ["log", "import", tables, "--out", log])
    add("log import out=user-file", ["log", "import", tables, "--out", "afile"])
    add("log import out=dir", ["log", "import", tables, "--out", "mine"])
    add("log export out=tables", ["log", "export", log, "--out", Path(tables).parent])
    add("log export out=user", ["log", "export", log, "--out", "mine"])
    add("log export out=log", ["log", "export", log, "--out", log])
    # terrains
    for name, t in [("missing", "nope.tif"), ("empty", "empty.tif"), ("text", "text.tif"), ("npz-text", "text.npz"),
                    ("log-as-dem", log), ("toml-as-dem", toml), ("dir", "mine"), ("band0", f"{npz}#band=0"),
                    ("band-x", "nope.tif#band=x"), ("synth-kind", "synthetic:hilly"),
                    ("synth-size0", "synthetic:rugged,size_m=0"), ("synth-spacing-neg", "synthetic:rugged,spacing=-3"),
                    ("synth-seed-float", "synthetic:rugged,seed=1.5"), ("synth-seed-neg", "synthetic:rugged,seed=-1"),
                    ("synth-dup", "synthetic:rugged,seed=1,seed=2"), ("synth-huge", "synthetic:rugged,size_m=1e9"),
                    ("synth-tiny-spacing", "synthetic:rugged,spacing=0.001"),
                    ("synth-nan", "synthetic:rugged,seed=nan"),
                    ("synth-empty-opt", "synthetic:rugged,"), ("synth-small", "synthetic:rugged,size_m=500"),
                    ("empty-name", ""), ("url", "https://example.com/dem.tif"), ("npz-nan", "nan.npz"),
                    ("npz-1x1", "one.npz")]:
        add(f"run terrain={name}", ["run", "S8", *QUICK, "--terrain", t, "--out", f"o-{name}"])
        add(f"info terrain={name}", ["terrain", "info", t], "any" if name == "synth-small" else "error")
    add("replay terrain=missing", ["replay", log, "--terrain", "nope.tif", "--quiet", "--out", "o"])
    add("replay terrain=other-synth", ["replay", log, "--terrain", "synthetic:flat", "--quiet", "--out", "o"])
    add("replay terrain=npz-nan", ["replay", log, "--terrain", "nan.npz", "--quiet", "--out", "o"])
    # numbers on the command line
    for flag, values in [("--particles", ["0", "1", "-5", "1e3", "abc", "1000000000000", "2.5"]),
                         ("--duration-s", ["0", "-1", "nan", "inf", "1e9", "1e-9", "x"]),
                         ("--seeds", ["0", "-1", "1e6", "1.5", "100000000"]),
                         ("--map-error-m", ["-1", "nan", "inf", "1e12"]),
                         ("--map-error-confidence", ["0", "-1", "nan", "1e9"]),
                         ("--sim-map-noise-m", ["-1", "nan", "1e9"]), ("--sim-map-bias-m", ["nan", "inf"]),
                         ("--sim-map-spacing-m", ["0", "-30", "1e9"]), ("--world-error-m", ["-1", "nan"]),
                         ("--world-error-corr-m", ["0", "-5"]), ("--world-clutter-fraction", ["2", "-1"]),
                         ("--world-refine", ["0", "1000"]), ("--world-seed", ["-2", "x"]),
                         ("--backend", ["warp9", ""]), ("--likelihood", ["gausian", ""]),
                         ("--surface", ["mesh", ""]), ("--device", ["cuda:9", "gpu", "", "cpu:1"])]:
        for v in values:
            add(f"run {flag}={v!r}", ["run", "S8", *QUICK, flag, v, "--out", f"n{len(cases)}"])
    add("run corr-without-rms", ["run", "S8", *QUICK, "--map-error-corr-m", "1000", "--out", "c1"])
    add("run corr-tiny", ["run", "S8", *QUICK, "--map-error-m", "4", "--map-error-corr-m", "1e-6", "--out", "c2"])
    add("run corr-tiny-check", ["run", "S8", "--map-error-m", "4", "--map-error-corr-m", "1e-6", "--check"])
    add("run unknown-scenario", ["run", "S13", *QUICK])
    add("run scenario-missing-file", ["run", "nope.toml", *QUICK])
    add("run scenario=log", ["run", log, *QUICK])
    for v in ["nan", "inf", "1e300", "-1e300", "x"]:
        add(f"info heading={v}", ["terrain", "info", "rugged", "--information", "--heading-deg", v])
    for flag, v in [("--scans", "0"), ("--scans", "1000000000"), ("--stride", "0"), ("--stride", "1000000"),
                    ("--altitude-agl", "-100"), ("--altitude-agl", "1e9"), ("--spacing", "0"), ("--spacing", "-1"),
                    ("--spacing", "1e-3"), ("--sensor", "S13"), ("--map-error-m", "-2")]:
        add(f"info {flag}={v}", ["terrain", "info", "rugged", "--information", flag, v])
    for flag, v in [("--particles", "0"), ("--particles", "1000000000"), ("--seed", "-1"), ("--seed", "x"),
                    ("--model", "lidar"), ("--backend", "warp9"), ("--map-error-m", "nan"),
                    ("--map-error-corr-m", "1000"), ("--imu-grade", "nasa"), ("--device", "cuda:7")]:
        add(f"replay {flag}={v}", ["replay", log, flag, v, "--quiet", "--out", f"r{len(cases)}"])
    # logs
    for name in ["missing.h5", "empty.h5", "text.h5", "dem.npz", "mine", "nan.h5", "cut.h5"]:
        add(f"replay log={name}", ["replay", name, "--quiet", "--out", f"rl{len(cases)}"])
        add(f"log export log={name}", ["log", "export", name, "--out", f"le{len(cases)}"])
    for name in ["missing.toml", "text.tif", "empty.h5", "tables-broken/layout.toml"]:
        add(f"log import layout={name}", ["log", "import", name, "--out", f"li{len(cases)}.h5"])
    # campaigns
    for name in CAMPAIGNS:
        add(f"campaign {name}", ["campaign", f"{name}.camp.toml", "--quiet", "--no-plots", "--out", "cout"])
    # scenario files
    for name in SCENARIO_EDITS:
        add(f"run scenario-file {name}", ["run", f"{name}.toml", "--check"])  # (QUICK would override the key)
    return cases


def _stage(base: Path, f: dict[str, Path]) -> None:
    """The hostile files the cases name, written into ``base``."""
    import numpy as np

    (base / "mine").mkdir()
    (base / "mine" / "notes.txt").write_text("my notes")
    (base / "mine" / "results.json").write_text("{}")
    (base / "mine" / "S8_seed0_track.png").write_bytes(b"\x89PNG mine")
    (base / "afile").write_text("mine")
    (base / "ro").mkdir()
    (base / "empty.tif").write_bytes(b"")
    (base / "text.tif").write_text("not a raster\n")
    (base / "text.npz").write_text("not an archive\n")
    (base / "empty.h5").write_bytes(b"")
    (base / "text.h5").write_text("not hdf5\n")
    data = f["log"].read_bytes()
    (base / "cut.h5").write_bytes(data[: len(data) // 2])
    heights = np.full((40, 40), 300.0)
    heights[5:9, 5:9] = np.nan
    np.savez(base / "nan.npz", heights_m=heights, grid=np.array([0.0, 0.0, 30.0, 30.0]))
    np.savez(base / "one.npz", heights_m=np.full((1, 1), 300.0), grid=np.array([0.0, 0.0, 30.0, 30.0]))
    import h5py

    shutil.copy(f["log"], base / "nan.h5")
    with h5py.File(base / "nan.h5", "r+") as h:
        h["imu"]["f_b"][3, 1] = np.nan
    broken = base / "tables-broken"
    shutil.copytree(Path(f["tables"]).parent, broken)
    (broken / "imu.csv").write_text("t,ax\n0,1\n")
    toml = f["toml"].read_text()
    for name, (key, repl) in SCENARIO_EDITS.items():
        (base / f"{name}.toml").write_text(toml.replace(key, repl, 1))
    for name, text in CAMPAIGNS.items():
        (base / f"{name}.camp.toml").write_text(text)
    (base / "cout").mkdir()
    shutil.copy(f["npz"], base / "cout" / "dem.npz")


def _judge(argv, expect, rc, err, raised, before, after) -> tuple[str, str]:
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip() and "Warp CUDA warning" not in ln
             and "%|" not in ln]
    last = lines[-1] if lines else ""
    lost = [k for k in before if k not in after or after[k] != before[k]]
    if lost:
        return "bad", f"changed or deleted: {', '.join(lost[:4])}"
    if raised:
        return "bad", f"raised {raised}"
    if any(w in err for w in BAD_WORDS):
        return "bad", f"raw error: {last[:200]}"
    if expect == "error" and rc == 0:
        return "bad", "exit 0 for a case that must fail"
    if expect == "ok" and rc != 0:
        return "unclear", f"exit {rc} for a case that should run: {last[:200]}"
    if rc != 0:
        errors = [ln for ln in lines if ln.startswith("warptan: error:") or ln.startswith("usage:")
                  or ln.startswith("warptan: terminated") or "error:" in ln]
        if not errors:
            return "unclear", f"exit {rc} without an error line: {last[:200]}"
    return "good", last[:200]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, help="write every case's verdict here")
    parser.add_argument("-k", default="", help="only cases whose name contains this")
    args = parser.parse_args(argv)
    from warptan import cli

    root = Path(tempfile.mkdtemp(prefix="warptan-probe-"))
    fixtures = _fixtures(root / "fixtures")
    verdicts = []
    cwd = os.getcwd()
    try:
        for name, case_argv, expect in _cases(fixtures):
            if args.k not in name:
                continue
            base = Path(tempfile.mkdtemp(prefix="case-", dir=root))
            _stage(base, fixtures)
            os.chmod(base / "ro", 0o555)
            before = {**{f"fixtures/{k}": v for k, v in _checksums(root / "fixtures").items()}, **_checksums(base)}
            out, err, raised, rc = io.StringIO(), io.StringIO(), "", None
            start = time.perf_counter()
            os.chdir(base)
            try:
                with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                    rc = cli.main(case_argv)
            except SystemExit as e:
                rc = e.code if isinstance(e.code, int) else 2
            except BaseException as e:  # (any escape is a finding)
                raised = f"{type(e).__name__}: {str(e)[:200]}"
            finally:
                os.chdir(cwd)
            after = {**{f"fixtures/{k}": v for k, v in _checksums(root / "fixtures").items()}, **_checksums(base)}
            status, why = _judge(case_argv, expect, rc, err.getvalue(), raised, before, after)
            partial = [p.name for p in base.rglob("*warptan-partial*")]
            if partial:
                status, why = "bad", f"partial left: {partial[:2]}"
            verdicts.append({"case": name, "argv": case_argv, "expect": expect, "exit": rc, "status": status,
                             "why": why, "seconds": round(time.perf_counter() - start, 2)})
            if status != "good":
                print(f"{status:8s} {name}: {why}", flush=True)
            os.chmod(base / "ro", 0o755)
            shutil.rmtree(base, ignore_errors=True)
    finally:
        os.chdir(cwd)
        shutil.rmtree(root, ignore_errors=True)
    counts = {s: sum(v["status"] == s for v in verdicts) for s in ("good", "unclear", "bad")}
    print(f"{len(verdicts)} cases: {counts}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        from warptan.meta import run_meta

        args.json.write_text(json.dumps({"meta": run_meta(["cpu"]), "counts": counts, "cases": verdicts},
                                        indent=1) + "\n")
    return 1 if counts["bad"] else 0


if __name__ == "__main__":
    sys.exit(main())
