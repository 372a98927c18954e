"""The benchmark scripts run end to end (no timing is asserted)."""

import json
import math
import runpy
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_compare_kernel_timings_quick(tmp_path):
    """`compare_kernel_timings.py --quick` finishes and its JSON has every model, N, M and the timing fields."""
    out = tmp_path / "t.json"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "compare_kernel_timings.py"), "--quick",
                           "--json", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "x sliding" in proc.stdout
    data = json.loads(out.read_text())
    rows = data["results"]
    assert {r["model"] for r in rows} == {"mesh", "dda", "bisection", "sliding", "altimeter"}
    assert {r["N"] for r in rows} == {100, 500, 2000}
    assert {r["M"] for r in rows if r["model"] != "altimeter"} == {1, 25, 100}
    for r in rows:
        assert r["median_s"] > 0 and r["per_s"] > 0 and r["ratio_to_sliding"] > 0, r
    assert data["meta"]["warp_version"] and data["meta"]["repeats"] == 3


def test_compare_kernel_timings_rejects_unknown_device():
    """An unknown device name is a one-line error, exit 2."""
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "compare_kernel_timings.py"), "--quick",
                           "--device", "tpu"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "unknown or absent device 'tpu'" in proc.stderr


def test_step_timeline_runs_on_cuda_or_refuses(tmp_path):
    """`step_timeline.py` reads CUDA events: on a CUDA device it writes each scenario's stamps (the step's end after
    its start), on the CPU it refuses in one line, exit 2."""
    import warp as wp

    script = str(ROOT / "scripts" / "step_timeline.py")
    if not wp.get_cuda_device_count():
        proc = subprocess.run([sys.executable, script, "--device", "cpu"], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and "records CUDA events" in proc.stderr
        return
    out = tmp_path / "t.json"
    proc = subprocess.run([sys.executable, script, "--scenario", "S8", "--steps", "10", "--json", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    row = json.loads(out.read_text())["results"]["S8"]
    assert 0 < row["device_head_start"] < row["device_main_end"] < row["host_sync_return"]


def test_readme_tables_come_from_the_artifacts(tmp_path):
    """`scripts/readme_tables.py --check` passes on the committed pages (README, docs/results.md) and fails when a
    number in a generated block is edited by hand, or when a measured number is typed into the prose."""
    script = str(ROOT / "scripts" / "readme_tables.py")

    def check(*pages):
        args = [a for p in pages for a in ("--page", str(p))]
        return subprocess.run([sys.executable, script, "--check", *args], capture_output=True, text=True, timeout=300)

    ok = check()
    assert ok.returncode == 0, ok.stderr
    text = (ROOT / "README.md").read_text()
    block = text.index("<!-- generated:paper -->")
    row = text.index("| S1 |", block)
    cell = text.index("±", row)
    start = cell - 4  # the digits before the first "±" of S1's row, e.g. "0.24"
    edited = text[:start] + ("9.99" if text[start:cell] != "9.99" else "8.88") + text[cell:]
    (tmp_path / "edited.md").write_text(edited)
    bad = check(tmp_path / "edited.md")
    assert bad.returncode == 1 and "differs from the artifacts" in bad.stderr
    results = (ROOT / "docs" / "results.md").read_text()
    prose = results.replace("# Results\n", "# Results\n\nA step takes 0.42 ms here.\n", 1)
    (tmp_path / "prose.md").write_text(prose)
    bad = check(tmp_path / "prose.md")
    assert bad.returncode == 1 and "'0.42 ms'" in bad.stderr


@pytest.mark.slow
def test_bench_filter_step_records_stages(tmp_path):
    """`bench_filter_step.py` runs a tiny configuration and records the tempering stages with the timings."""
    out = tmp_path / "s.json"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_filter_step.py"), "--n", "64", "--models",
                           "sliding", "--likelihood", "gaussian", "--repeats", "2", "--warmup", "1",
                           "--json", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    row = json.loads(out.read_text())["results"][0]
    assert row["likelihood"] == "gaussian" and row["tempering_stages_mean"] >= 1 and row["step_ms"] > 0


@pytest.mark.slow
def test_bench_filter_step_flies_the_scenarios_filter(tmp_path):
    """`bench_filter_step.py --scenario S8` builds the filter S8 flies (its likelihood, surface, scan) and reports the
    achieved point evaluations beside the kernel's bound and the real-time factor of the median of whole runs; an
    unknown scenario is one line and exit 2."""
    out = tmp_path / "s.json"
    script = str(ROOT / "scripts" / "bench_filter_step.py")
    proc = subprocess.run([sys.executable, script, "--scenario", "S8", "--n", "64", "--repeats", "2", "--warmup",
                           "1", "--settle-s", "1", "--rtf-s", "2", "--rtf-repeats", "3", "--paced-s", "0.5", "--json",
                           str(out)],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    row = json.loads(out.read_text())["results"][0]
    assert row["model"] == "S8:sliding" and row["scenario"] == "S8" and row["M"] == 100
    assert row["likelihood"] == "gaussian" and row["surface"] == "triangles" and row["settle_s"] == 1.0
    assert row["point_evals_per_s"] > 0 and row["kernel_point_evals_per_s"] > 0 and row["real_time_factor"] > 0
    assert len(row["rtf_walls_s"]) == 3 and row["rtf_wall_s"] == sorted(row["rtf_walls_s"])[1]
    assert row["paced_s"] == 0.5 and 0 < row["paced_step_ms"] <= row["paced_step_p90_ms"]
    assert 0 < row["paced_update_ms"] <= row["paced_update_p90_ms"]
    bad = subprocess.run([sys.executable, script, "--scenario", "S99"], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    errors = [line for line in bad.stderr.splitlines() if line.startswith("bench_filter_step: error:")]
    assert bad.returncode == 2 and len(errors) == 1 and "S99" in errors[0] and not bad.stdout


def test_paced_run_keeps_the_flights_clock(monkeypatch):
    """`bench_filter_step.paced_run` calls the filter as a real-time loop would: one IMU sample per call when due (or
    the interval's samples in one call), the update after them, and never runs ahead of the flight's clock."""
    import time

    monkeypatch.syspath_prepend(str(ROOT / "scripts"))
    import bench_filter_step as bfs
    import numpy as np
    import warp as wp

    wp.init()  # (the loop synchronises the filter's device after each update)

    class Fake:
        device = "cpu"

        def __init__(self):
            self.calls = []

        def predict_many(self, f, w):
            self.calls.append(("predict", len(f), time.perf_counter()))

        def update(self, meas, sync=True):
            self.calls.append(("update", meas, time.perf_counter()))

    f = w = np.zeros((40, 3))
    for per_sample, n_pred in ((True, 1), (False, 4)):
        mpf, t0 = Fake(), time.perf_counter()
        lat, k = bfs.paced_run(mpf, f, w, ["a", "b"], 0, 4, 100.0, per_sample=per_sample)
        assert k == 8 and len(lat) == 2 and all(x >= 0 for x in lat)
        kinds = [c[0] for c in mpf.calls]
        assert kinds == (["predict"] * 4 + ["update"]) * 2 if per_sample else ["predict", "update"] * 2
        assert all(c[1] == n_pred for c in mpf.calls if c[0] == "predict")
        assert [c[1] for c in mpf.calls if c[0] == "update"] == ["a", "b"]
        updates = [c[2] - t0 for c in mpf.calls if c[0] == "update"]
        assert updates[0] >= 0.04 and updates[1] >= 0.08  # each scan no earlier than its time (4 samples at 100 Hz)


@pytest.mark.slow
def test_world_study_runs_resumes_and_reports(tmp_path):
    """`world_study.py` on a tiny plan: rows with the three estimators, meta with the command; a resume adds only the
    missing rows; the Markdown table names every row."""
    script, out = str(ROOT / "scripts" / "world_study.py"), tmp_path / "w"
    base = [sys.executable, script, "--seeds", "2", "--worlds", "2", "--duration-s", "35", "--scenarios", "S8",
            "--errors", "5", "--out", str(out)]
    proc = subprocess.run([*base, "--estimators", "gaussian"], capture_output=True, text=True, timeout=600,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    proc = subprocess.run([*base, "--resume"], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((out / "study.json").read_text())
    assert sorted(r["estimator"] for r in data["rows"]) == ["gaussian", "paper", "stated"]
    assert all(r["seeds"] == 2 and r["worlds"] == 2 and "world(" in r["world"] for r in data["rows"])
    assert len(data["meta"]["commands"]) == 2 and "git_commit" in data["meta"]
    assert (out / "study.md").read_text().count("| S8 |") == 3


def test_reproduce_paper_checks_its_output_before_the_work(tmp_path):
    """`reproduce_paper.py`: an --out whose parent is missing is one error line before any run (exit 2); with
    --likelihoods a missing OUT is made (it used to fail after the whole run), and a run shorter than the
    convergence time writes dashes, not a traceback."""
    script = str(ROOT / "scripts" / "reproduce_paper.py")
    proc = subprocess.run([sys.executable, script, "--seeds", "1", "--scenarios", "S8", "--no-plots",
                           "--out", str(tmp_path / "missing" / "out")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "its parent folder" in proc.stderr and "Traceback" not in proc.stderr
    out = tmp_path / "new" / "x"
    proc = subprocess.run([sys.executable, script, "--seeds", "1", "--scenarios", "S8", "--duration-s", "5",
                           "--no-baro-runs", "--no-plots", "--likelihoods", "paper", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert (out / "paper" / "results.json").exists() and "| S8 |" in (out / "likelihoods.md").read_text()


@pytest.mark.slow
def test_learn_study_runs_resumes_and_reports(tmp_path):
    """`learn_study.py` on a tiny plan (2 seeds, one family, 35 s): a row per mode, the learned RMS and white error
    only where the learner ran, the lost seeds without a flag counted; a resume adds only the missing row; the Markdown
    table names every row."""
    script, out = str(ROOT / "scripts" / "learn_study.py"), tmp_path / "l"
    base = [sys.executable, script, "--seeds", "2", "--worlds", "1", "--duration-s", "35", "--scenarios", "S8",
            "--families", "short", "--out", str(out)]
    proc = subprocess.run([*base, "--modes", "learn"], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    proc = subprocess.run([*base, "--modes", "learn", "off", "--resume"], capture_output=True, text=True, timeout=600,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    rows = json.loads((out / "study.json").read_text())["rows"]
    assert sorted(r["mode"] for r in rows) == ["learn", "off"]
    learned = {r["mode"]: r["learned_m"] for r in rows}
    assert learned["off"] is None and len(learned["learn"]) == 2 and all(v > 0 for v in learned["learn"])
    assert all(np.isfinite(r["horizontal_rmse_m"]) and r["worlds"] == 1 for r in rows)
    assert all(r["lost_unflagged"] == sum(v > 50.0 for v in r["per_seed_m"]) - r["declared_unconverged"] == 0
               for r in rows)  # (S8 converges: nothing lost, nothing declared)
    white = {r["mode"]: r["white_learned_m"] for r in rows}
    assert white["off"] is None and len(white["learn"]) == 2
    assert (out / "study.md").read_text().count("| S8 | short |") == 2
    for r in rows:  # the attitude's and the velocity's honesty beside the position's
        assert len(r["attitude_coverage_3sigma"]) == 3 and len(r["velocity_coverage_3sigma"]) == 3
        assert all(0.0 <= c <= 1.0 for c in (*r["attitude_coverage_3sigma"], *r["velocity_coverage_3sigma"]))
        assert all(v > 0 for v in r["attitude_sigma_over_rmse"])
    old = {k: v for k, v in rows[0].items() if not k.startswith(("attitude_", "velocity_"))}
    md = tmp_path / "old.md"
    runpy.run_path(script)["write_md"]([old], md)  # a row recorded before the attitude was: a dash
    assert "| — | — |" in md.read_text()


def test_bench_learned_cost_pools_alternated_runs(tmp_path):
    """`bench_learned_cost.py --pool`: the rows of alternated runs are pooled per code, scenario and config, every
    run's walls kept and the medians taken over them (the updates a row's wall is divided by, its own)."""
    files = []
    for k, (label, walls) in enumerate([("new", [1.0, 2.0, 3.0]), ("old", [0.5, 0.5, 0.6]), ("new", [4.0, 5.0, 6.0])]):
        row = {"scenario": "S8", "config": "world", "device": "cpu", "particles": 500, "flight_s": 30.0,
               "walls_s": walls, "real_time_factor": 30.0 / walls[1], "ms_per_update": 1e3 * walls[1] / 300}
        path = tmp_path / f"run{k}.json"
        path.write_text(json.dumps({"meta": {"label": label, "git_commit": "x"}, "rows": [row]}))
        files.append(str(path))
    out = tmp_path / "pooled.json"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_learned_cost.py"), "--pool", *files,
                           "--json", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    data = json.loads(out.read_text())
    rows = {r["code"]: r for r in data["rows"]}
    assert rows["new"]["walls_s"] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0] and rows["new"]["runs"] == 2
    assert rows["new"]["real_time_factor"] == pytest.approx(30.0 / 3.5)
    assert rows["new"]["ms_per_update"] == pytest.approx(1e3 * 3.5 / 300)
    assert rows["old"]["ms_per_update"] == pytest.approx(1e3 * 0.5 / 300)
    assert len(data["meta"]["runs"]) == 3 and "3 runs alternated" in data["meta"]["label"]


def test_attitude_leak_matches_its_float64_oracle(tmp_path):
    """`attitude_leak.py` over S8's last seconds: the kernel's attitude information under the map-error modes,
    accumulated at the true pose, is its float64 oracle's (finite-difference Jacobians, the model's table, Woodbury with
    the attitude weights, Schur against the position), and removing modes from it only widens the claimed σ."""
    out = tmp_path / "leak.json"
    runpy.run_path(str(ROOT / "scripts" / "attitude_leak.py"))["main"](["--from-s", "112", "--json", str(out)])
    rows = {r["weights"]: r for r in json.loads(out.read_text())["rows"]}
    kernel, oracle = rows["kernel"], rows["oracle"]
    np.testing.assert_allclose(kernel["sigma_deg"], oracle["sigma_deg"], rtol=0.02)
    np.testing.assert_allclose(kernel["theta_deg"], oracle["theta_deg"], rtol=0.05,
                               atol=0.05 * max(oracle["sigma_deg"]))
    for name in ("kappa-1 modes out", "modes past 9 out", "all modes out"):
        assert all(a >= b * (1 - 1e-6) for a, b in zip(rows[name]["sigma_deg"], oracle["sigma_deg"], strict=True))


def test_bound_study_merges_runs_and_draws_how_close_to_the_floor(tmp_path):
    """`bound_study.py --merge`: every run's rows in one file, each keeping its run's meta, ordered by scenario, RMS
    and length; `--plot` draws the exact-floor rows; the results' `floor` block reads the merged file (a cell per
    scenario, RMS and length, "–" where none ran)."""
    sys.path.insert(0, str(ROOT / "scripts"))
    import readme_tables

    files = []
    for k, (sid, rms, corr, rmse, floor) in enumerate([("S8", 5.0, 1000.0, 2.5, 0.2), ("S1", 2.0, 300.0, 3.0, 0.25),
                                                       ("S8", 5.0, 300.0, 6.0, 0.3)]):
        row = {"scenario": sid, "seeds": 20, "model": "sliding", "rmse_horizontal_converged_m": rmse,
               "bound_converged_m": floor, "rmse_over_bound": rmse / floor, "fast_bound_converged_m": 1.5 * floor,
               "bound": "exact floor", "world": {"world_error_rms_m": rms, "world_error_corr_m": corr},
               "below_bound_beyond_mc_error": False}
        path = tmp_path / f"run{k}.json"
        path.write_text(json.dumps({"meta": {"git_commit": f"c{k}", "devices": ["cpu"]}, "rows": [row]}))
        files.append(str(path))
    merged, png = tmp_path / "floor.json", tmp_path / "floor.png"
    script = str(ROOT / "scripts" / "bound_study.py")
    for argv in (["--merge", *files, "--json", str(merged)], ["--plot", str(merged), "--png", str(png)]):
        proc = subprocess.run([sys.executable, script, *argv], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
    data = json.loads(merged.read_text())
    assert [(r["scenario"], r["world"]["world_error_corr_m"]) for r in data["rows"]] == [
        ("S1", 300.0), ("S8", 300.0), ("S8", 1000.0)]
    assert [r["meta"]["git_commit"] for r in data["rows"]] == ["c1", "c2", "c0"] and len(data["meta"]["runs"]) == 3
    again = tmp_path / "again.json"  # a merged file merged with a newer run of one of its cells
    newer = {**json.loads((tmp_path / "run2.json").read_text()), "meta": {"git_commit": "c3", "devices": ["cpu"]}}
    newer["rows"][0]["rmse_horizontal_converged_m"] = 5.0
    (tmp_path / "run3.json").write_text(json.dumps(newer))
    proc = subprocess.run([sys.executable, script, "--merge", str(merged), str(tmp_path / "run3.json"), "--json",
                           str(again)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(again.read_text())["rows"]
    assert [(r["scenario"], r["meta"]["git_commit"], r["rmse_horizontal_converged_m"]) for r in rows] == [
        ("S1", "c1", 3.0), ("S8", "c3", 5.0), ("S8", "c0", 2.5)]
    assert png.stat().st_size > 10_000
    block = readme_tables.floor_block(str(merged))
    assert "| S8 | 5 | 6.00 / 0.300 (20×) | 2.50 / 0.200 (12×) |" in block
    assert "| S1 | 2 | 3.00 / 0.250 (12×) | – |" in block and "1.50–1.50 × the floor" in block


@pytest.mark.slow
def test_bound_study_splits_the_seeds_over_worlds(tmp_path):
    """`bound_study.py --worlds 2`: four seeds over two realisations of the world's error (world seeds 2000, 2001),
    the pooled RMSE the root mean of the two worlds' mean squares, the floor beside it; more worlds than seeds is
    a usage error."""
    out = tmp_path / "w.json"
    script = str(ROOT / "scripts" / "bound_study.py")
    argv = ["--scenarios", "S8", "--duration-s", "30", "--world-error-m", "5", "--world-corr-m", "1000", "--told",
            "--world-refine", "1", "--worlds", "2"]
    proc = subprocess.run([sys.executable, script, *argv, "--seeds", "4", "--json", str(out)], capture_output=True,
                          text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    row = json.loads(out.read_text())["rows"][0]
    assert row["worlds"] == 2 and len(row["per_seed_rmse_horizontal_m"]) == 4
    per_world = np.array(row["rmse_horizontal_per_world_m"])
    assert len(per_world) == 2 and not np.isclose(per_world[0], per_world[1])
    assert row["rmse_horizontal_converged_m"] == pytest.approx(math.sqrt(np.mean(per_world**2)), rel=1e-9)
    assert row["bound"] == "exact floor" and row["bound_converged_m"] > 0
    bad = subprocess.run([sys.executable, script, *argv[:-2], "--worlds", "3", "--seeds", "2"], capture_output=True,
                         text=True, timeout=120, cwd=tmp_path)
    assert bad.returncode == 2 and "--worlds 3 needs at least as many --seeds" in bad.stderr


@pytest.mark.slow
def test_profile_update_host_times_the_pieces_per_segment(tmp_path):
    """`profile_update_host.py`: per configuration the loop's period and the host time of the update's pieces per 30 s
    segment (a short flight: one segment), the update's own time within the loop's; the median update of each kind
    and the device time from the filter's timers; the world with the learner off reads no learner."""
    out = tmp_path / "prof.json"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "profile_update_host.py"), "--device", "cpu",
                           "--duration-s", "2", "--json", str(out)], capture_output=True, text=True, timeout=600,
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [r["config"] for r in rows] == ["map=world", "world", "world-off"]
    for r in rows:
        assert len(r["period_ms"]) == 1 and r["updates"] > 10
        update = r["host_us_per_update"]["update"][0]
        assert 0.0 < update * r["updates"] < 1e6 * r["wall_s"]  # (the updates' host time within the run's wall; the
        # mean period leaves out the first update, which builds the first mode table, so a 2 s flight's mean update
        # can exceed it)
        assert 0.0 < r["update_median_ms"]["plain"] < r["period_median_ms"]
        assert 0.0 < r["device_ms"]["median"] < r["period_median_ms"]  # (the CPU's launches, within the update)
    assert "_learn_map_error" in rows[1]["host_us_per_update"]
    assert "_learn_map_error" in rows[1]["update_median_ms"] and "_read_again" in rows[1]["update_median_ms"]
    assert "_learn_map_error" not in rows[2]["host_us_per_update"]  # (world-off: the learner off)
