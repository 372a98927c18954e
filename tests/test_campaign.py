"""Campaigns (``warptan campaign``): the file, validation before work, rows against direct runs, the local and Ray
engines giving identical rows, retries and failure reports."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from warptan.sim.campaign import Campaign, CampaignError
from warptan.sim.campaign_report import write_campaign
from warptan.sim.campaign_run import make_row, run_batch, run_campaign
from warptan.sim.report import ci95
from warptan.sim.scenarios import run_scenario, run_scenario_batch

SMALL = {"scenarios": ["S8"], "seeds": 2, "overrides": {"duration_s": 3.0}, "sweep": {"particles": [100, 200, 300]}}
"""A campaign of three short batches (about 1 s on the CPU together)."""


def _rows_json(rows) -> str:
    from warptan.outputs import json_ready

    return json.dumps(json_ready(rows), sort_keys=True, allow_nan=False)


def _cli(*args, cwd):
    """``warptan ARGS`` with the current directory off the import path (as the installed console script runs)."""
    code = "import sys; sys.path.pop(0); from warptan.cli import main; sys.exit(main())"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=cwd, timeout=600)


@pytest.fixture(scope="module")
def small_local():
    campaign = Campaign.from_dict(SMALL)
    return run_campaign(campaign, engine="local", progress=False)


def test_file_problems_are_listed_together(tmp_path):
    bad = {"scenarios": ["S8", "all"], "seeds": [1, 1, -2], "overides": {}, "overrides": {"particles": 10, "foo": 1},
           "sweep": {"particles": [1, 2], "likelihood": "paper", "backend": ["dda", "dda"]}}
    with pytest.raises(CampaignError) as err:
        Campaign.from_dict(bad, source="bad.toml")
    text = str(err.value)
    for needle in ("unknown key 'overides' (did you mean 'overrides'?)", "'all' runs every scenario",
                   "seeds must be ≥ 0, got [-2]", "seed(s) [1] given more than once",
                   "[overrides] 'foo' is not a run_scenario keyword", "[sweep] likelihood must be a non-empty list",
                   "[sweep] backend repeats ['dda']", "'particles' is both in [overrides] and in [sweep]"):
        assert needle in text, (needle, text)
    assert text.startswith("8 problem(s) in campaign bad.toml")
    with pytest.raises(CampaignError, match="scenarios is missing"):
        Campaign.from_dict({"seeds": 1})
    with pytest.raises(CampaignError, match="seeds must be a count"):
        Campaign.from_dict({"scenarios": "S8", "seeds": True})
    with pytest.raises(CampaignError, match="unknown scenario 'S13'"):
        Campaign.from_dict({"scenarios": ["S13"], "seeds": 1})
    path = tmp_path / "broken.toml"
    path.write_text("scenarios = [S8\n")
    with pytest.raises(CampaignError, match=r"broken\.toml: not a valid TOML file"):
        Campaign.load(path)


def test_batches_are_the_cartesian_product_and_paths_resolve(tmp_path):
    scenario = Path(__file__).resolve().parents[1] / "warptan" / "scenario_files" / "S8.toml"
    (tmp_path / "mine.toml").write_text(scenario.read_text().replace('id = "S8"', 'id = "MINE"'))
    (tmp_path / "campaign.toml").write_text(
        'scenarios = ["s8", "mine.toml"]\nseeds = [4, 7]\n[overrides]\nduration_s = 3.0\n'
        '[sweep]\nparticles = [100, 200]\nlikelihood = ["paper", "gaussian"]\n')
    c = Campaign.load(tmp_path / "campaign.toml")
    assert c.scenarios == ["S8", str((tmp_path / "mine.toml").resolve())]
    assert [b.label for b in c.batches[:4]] == ["S8 particles=100 likelihood=paper",
                                                "S8 particles=100 likelihood=gaussian",
                                                "S8 particles=200 likelihood=paper",
                                                "S8 particles=200 likelihood=gaussian"]
    assert len(c.batches) == 8 and c.batches[5].name == "mine"
    assert all(b.seeds == (4, 7) and b.overrides["duration_s"] == 3.0 for b in c.batches)


def test_every_batch_is_checked_before_any_runs():
    c = Campaign.from_dict({"scenarios": ["S7", "S8"], "seeds": 1, "overrides": {"duration_s": 3.0},
                            "sweep": {"particles": [100, 0], "backend": ["dda", "warp-drive"]}})
    with pytest.raises(CampaignError) as err:
        run_campaign(c, task=lambda *a: pytest.fail("a batch ran before the campaign was checked"))
    text = str(err.value)
    assert text.startswith("6 of 8 batch(es) of campaign campaign cannot run")
    assert "S7 particles=0 backend=dda" in text and "S8 particles=100 backend=warp-drive" in text
    with pytest.raises(CampaignError, match="unknown engine 'spark'"):
        run_campaign(Campaign.from_dict(SMALL), engine="spark")
    with pytest.raises(CampaignError, match="needs --engine ray"):
        run_campaign(Campaign.from_dict(SMALL), address="ray://head:10001")


def test_rows_are_the_direct_runs_summarised(small_local):
    """Each row is the mean ± 95 % interval of the per-seed RMSE of the batched runs run_scenario_batch gives."""
    assert [r["params"] for r in small_local.rows] == [{"particles": p} for p in (100, 200, 300)]
    assert not small_local.failures and len(small_local.tasks) == 3
    for row in small_local.rows:
        direct = run_scenario_batch("S8", [0, 1], duration_s=3.0, particles=row["params"]["particles"])
        mean, half = ci95([r.rmse for r in direct])
        np.testing.assert_array_equal(row["rmse_m"], mean)
        np.testing.assert_array_equal(row["rmse_ci95_m"], half)
        np.testing.assert_array_equal(row["coverage_3sigma"],
                                      np.mean([r.summary()["coverage_3sigma"] for r in direct], axis=0))
        assert row["seeds"] == [0, 1] and row["scenario"] == "S8"
        assert np.isnan(row["rmse_converged_m"]).all()  # 3 s < converged_after_s: undefined, not made up
    assert small_local.rows[0]["rmse_m"] != small_local.rows[1]["rmse_m"]  # the sweep reached the runs


def test_a_scenario_that_cannot_be_batched_runs_seed_by_seed():
    """A map with per-seed noise (map_seed = -1) gives every seed its own map: the batch runs seed by seed and its
    row is the one run_scenario gives per seed."""
    c = Campaign.from_dict({"scenarios": ["S8"], "seeds": 2,
                            "overrides": {"duration_s": 2.0, "particles": 100, "map_noise_m": 2.0, "map_seed": -1}})
    result = run_campaign(c, progress=False)
    assert c.batches[0].batched is False
    direct = [run_scenario("S8", seed=s, duration_s=2.0, particles=100, map_noise_m=2.0, map_seed=-1)
              for s in (0, 1)]
    assert _rows_json(result.rows) == _rows_json([make_row(c.batches[0], [r.summary() for r in direct])])


def test_a_failing_batch_is_retried_once_then_reported(tmp_path, small_local):
    c = Campaign.from_dict(SMALL)
    result = run_campaign(c, progress=False, task=_flaky_task(tmp_path))
    _assert_flaky_outcome(result, small_local, tmp_path)


def _flaky_task(marks: Path):
    """A batch function whose particles=100 batch fails once (then works) and particles=300 batch always fails;
    every attempt leaves a file in ``marks`` (a closure: Ray ships it to its workers by value)."""
    def task(spec, device, cpu_threads=None):
        p = spec["overrides"]["particles"]
        attempt = len(list(marks.glob(f"p{p}_*")))
        (marks / f"p{p}_{attempt}").touch()
        if (p == 100 and attempt == 0) or p == 300:
            raise RuntimeError(f"injected failure of particles={p}, attempt {attempt}")
        return run_batch(spec, device, cpu_threads)
    return task


def _assert_flaky_outcome(result, reference, marks: Path):
    assert sorted(m.name for m in marks.iterdir()) == ["p100_0", "p100_1", "p200_0", "p300_0", "p300_1"]
    assert _rows_json(result.rows) == _rows_json(reference.rows[:2])  # the retried batch: the same row
    (failure,) = result.failures
    assert failure["params"] == {"particles": 300} and failure["attempts"] == 2 and failure["scenario"] == "S8"
    assert failure["error"] == "RuntimeError: injected failure of particles=300, attempt 1"


def test_outputs_table_json_and_one_plot_per_swept_parameter(tmp_path, small_local, monkeypatch):
    pytest.importorskip("matplotlib", reason="plots need the plot extra")
    import matplotlib.figure

    texts = []
    save = matplotlib.figure.Figure.savefig
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: (
        texts.extend(t.get_text() for ax in fig.axes for t in [ax.title, *ax.texts]), save(fig, *a, **k))[1])
    written = write_campaign(small_local, tmp_path / "out")
    # the plot gives each point's number and the seeds it is a mean over
    seeds = len(small_local.rows[0]["per_seed"])
    assert f"mean over {seeds} seeds" in texts[0] and len(texts) >= 2 and all(float(t) > 0 for t in texts[1:])
    names = sorted(Path(f).name for f in written["files"])
    assert names == ["campaign.json", "campaign.md", "campaign_particles.png"]
    data = json.loads((tmp_path / "out" / "campaign.json").read_text())
    assert data["meta"]["engine"] == "local" and data["meta"]["batches"] == {"done": 3, "failed": 0}
    assert data["meta"]["campaign"]["sweep"] == {"particles": [100, 200, 300]} and data["failures"] == []
    assert {"git_commit", "devices", "wall_s", "command", "tasks"} <= set(data["meta"])
    assert data["rows"][0]["rmse_converged_m"] == [None, None, None]  # strict JSON
    table = (tmp_path / "out" / "campaign.md").read_text()
    assert "| S8 | 200 | 2 |" in table and "Every run: `duration_s = 3.0`" in table


def test_the_plot_interval_of_a_positive_rmse_stays_positive():
    """The campaign plot's interval of the mean RMSE over seeds is a bootstrap percentile interval: with a few skewed
    seeds (1, 1, 1, 100 m) it stays above zero and around the mean, where the symmetric t interval reached -100 m;
    one seed gives the mean itself, no finite seed NaN."""
    from warptan.sim.campaign_report import _rmse_3d
    from warptan.sim.report import ci95

    def row(values):
        return {"per_seed": [{"rmse_m": [v, 0.0, 0.0]} for v in values]}

    mean, lo, hi = _rmse_3d(row([1.0, 1.0, 1.0, 100.0]), "rmse_m")
    assert mean == pytest.approx(25.75) and 1.0 <= lo < mean < hi <= 100.0
    t_mean, t_half = ci95(np.array([1.0, 1.0, 1.0, 100.0]))
    assert t_mean - t_half < 0  # (what the plot drew before)
    assert _rmse_3d(row([3.0]), "rmse_m") == (3.0, 3.0, 3.0)
    assert all(np.isnan(_rmse_3d(row([float("nan")]), "rmse_m")))


def test_cli_check_and_bad_input(tmp_path):
    good = tmp_path / "c.toml"
    good.write_text('scenarios = ["S8"]\nseeds = 2\n[overrides]\nduration_s = 3.0\n[sweep]\nparticles = [100, 200]\n')
    proc = _cli("campaign", str(good), "--check", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "S8 particles=200: ok" in proc.stdout and "2 batch(es)" in proc.stdout
    # its time, from a pilot of each batch (issue 67: --check gave none)
    assert re.search(r"S8 particles=100: ok \(.*; about \d+ s on c", proc.stdout), proc.stdout
    assert re.search(r"2 batch\(es\), about \d+ s one after the other on c", proc.stdout), proc.stdout
    assert not (tmp_path / "warptan-campaign").exists()
    bad = tmp_path / "bad.toml"
    bad.write_text('scenarios = ["S8"]\nseeds = 0\n')
    proc = _cli("campaign", str(bad), "--out", str(tmp_path / "o"), cwd=tmp_path)
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
        f"warptan: error: 1 problem(s) in campaign {bad}: seeds must be ≥ 1, got 0"]
    assert not (tmp_path / "o").exists()
    proc = _cli("campaign", str(good), "--address", "10.0.0.1:6379", cwd=tmp_path)
    assert proc.returncode == 2 and "needs --engine ray" in proc.stderr
    proc = _cli("campaign", str(good), "--engine", "ray", "--device", "cuda:1", "--check", cwd=tmp_path)
    assert proc.returncode == 2 and "give --device cuda" in proc.stderr  # refused already by --check
    proc = _cli("campaign", str(tmp_path / "missing.toml"), cwd=tmp_path)
    assert proc.returncode == 2 and "campaign file not found" in proc.stderr


@pytest.mark.slow
def test_ray_engine_gives_the_local_rows(tmp_path):
    """Issue 18's check: ``campaigns/example_quick.toml`` (S7 and S8 × 3 particle counts × 2 likelihoods, 8 s, 2
    seeds) with ``--engine ray`` on a local cluster (this machine's CPUs) gives the rows of the local engine. The
    command runs in a folder holding a decoy ``warptan`` package that must not reach the workers (Ray puts the
    driver's directory on their import path unless the campaign gives them a working folder of their own)."""
    pytest.importorskip("ray", reason="the Ray engine needs the cluster extra")
    example = Path(__file__).resolve().parents[1] / "campaigns" / "example_quick.toml"
    local = run_campaign(Campaign.load(example), progress=False)
    assert len(local.rows) == 12 and not local.failures
    decoy = tmp_path / "warptan"
    decoy.mkdir()
    (decoy / "__init__.py").write_text("raise ImportError('the decoy warptan in the current directory was imported')")
    proc = _cli("campaign", str(example), "--engine", "ray", "--out", "ray-out", "--quiet", "--no-plots",
                cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    data = json.loads((tmp_path / "ray-out" / "campaign.json").read_text())
    assert _rows_json(data["rows"]) == _rows_json(local.rows)
    assert data["meta"]["engine"] == "ray" and data["meta"]["cluster"]["resources"]["CPU"] >= 1
    assert data["failures"] == [] and len(data["meta"]["tasks"]) == 12


@pytest.mark.slow
def test_ray_engine_terminated_cleans_up_as_the_local_engine(tmp_path):
    """`campaign --engine ray` + SIGTERM: Ray's own handlers (installed by ray.init) printed a C++ stack dump
    ("*** SIGTERM received ...") and ended with rc 1 or 134; the local engine's clean 143 and its line never came.
    Now as the local engine: rc 143, one line, no output folder, no Ray worker left."""
    import signal
    import time

    pytest.importorskip("ray", reason="the Ray engine needs the cluster extra")
    (tmp_path / "long.toml").write_text('scenarios = ["S8"]\nseeds = 1\n[overrides]\nduration_s = 240.0\n')
    code = "import sys; sys.path.pop(0); from warptan.cli import main; sys.exit(main())"
    err = tmp_path / "err.txt"
    with open(err, "w") as stderr:
        proc = subprocess.Popen([sys.executable, "-c", code, "campaign", "long.toml", "--engine", "ray", "--out",
                                 "o"], cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=stderr)
        deadline = time.monotonic() + 120
        while "0/1" not in err.read_text() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)  # (the bar: Ray is up and the task submitted)
        time.sleep(3.0)
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=120)
    text = err.read_text()
    assert rc == 128 + signal.SIGTERM, text[-3000:]
    assert "SIGTERM received" not in text and "Traceback" not in text, text[-3000:]
    assert text.rstrip().splitlines()[-1] == ("warptan: terminated (SIGTERM); the output folder is as it was before "
                                              "this run")
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_ray_engine_retries_once_and_keeps_the_other_rows(tmp_path, small_local):
    pytest.importorskip("ray", reason="the Ray engine needs the cluster extra")
    c = Campaign.from_dict(SMALL)
    result = run_campaign(c, engine="ray", progress=False, task=_flaky_task(tmp_path))
    _assert_flaky_outcome(result, small_local, tmp_path)
    assert "injected failure of particles=300" in result.failures[0]["traceback"]


@pytest.mark.slow
def test_ray_gpu_tasks_run_on_the_gpu_ray_assigned(tmp_path):
    """With ``--device cuda`` each task asks Ray for one GPU and runs on the Warp device of the GPU Ray assigned
    (workers see every GPU and are reused). A cluster told it has two GPUs (this CPU machine's stand-in): tasks that
    run at the same time were given different devices, and only those two. The stand-in task records the device it
    was given and runs the batch on the CPU; its time on the GPU counts from the task's start (counted from its
    batch's start, the batch being short, two tasks whose workers started apart did not overlap in a clean-clone
    run)."""
    ray = pytest.importorskip("ray", reason="the Ray engine needs the cluster extra")

    def task(spec, device, cpu_threads=None):
        import time as _time

        held = _time.time()  # the task holds its GPU from here: the interval compared includes the sleep
        _time.sleep(2.0)  # long enough for the first two tasks to overlap (their workers start a second apart)
        return {**run_batch(spec, "cpu"), "device_given": device, "start_unix": held}

    ray.init(num_cpus=2, num_gpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"working_dir": str(tmp_path)})
    try:
        result = run_campaign(Campaign.from_dict(SMALL), engine="ray", device="cuda", progress=False, task=task)
    finally:
        ray.shutdown()
    tasks = result.tasks
    assert not result.failures and len(tasks) == 3
    assert {t["device_given"] for t in tasks} <= {"cuda:0", "cuda:1"}
    assert all(t["device_given"] == f"cuda:{t['ray_gpu_ids'][0]}" for t in tasks)
    overlapping = [(a, b) for i, a in enumerate(tasks) for b in tasks[i + 1:]
                   if a["start_unix"] < b["end_unix"] and b["start_unix"] < a["end_unix"]]
    assert overlapping and all(a["device_given"] != b["device_given"] for a, b in overlapping)
    with pytest.raises(CampaignError, match="not 'cuda:1'"):
        run_campaign(Campaign.from_dict(SMALL), engine="ray", device="cuda:1")


@pytest.mark.parametrize("batched", [True, False], ids=["batched", "seed-by-seed"])
def test_a_batch_reports_its_own_progress(batched):
    """A campaign's bar moved only per batch (issue 67): a batch now reports its steps, ``k`` of ``n`` rising to
    ``n`` whether its seeds run as one filter or one after another."""
    seen = []
    spec = {"scenario": "S8", "seeds": [0, 1], "batched": batched,
            "overrides": {"duration_s": 0.5, "particles": 32, "bound": False}}
    out = run_batch(spec, "cpu", progress=lambda k, n: seen.append((k, n)))
    assert len(out["summaries"]) == 2 and seen
    fractions = [k / n for k, n in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and len({n for _, n in seen}) == 1
