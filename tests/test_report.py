"""Statistics of the reports and the claim verdicts, against tabulated values and constructed samples."""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from warptan.sim import claims
from warptan.sim.report import (
    FAILS,
    HOLDS,
    INCONCLUSIVE,
    aggregate,
    ci95,
    compare_less,
    ratio_within,
    t_ppf,
    t_sf,
    welch_less,
)
from warptan.sim.scenario_config import load_config

ROOT = Path(__file__).resolve().parents[1]

# Student t quantiles t_{0.975, dof} from standard tables.
T975 = {1: 12.706, 2: 4.303, 5: 2.571, 10: 2.228, 19: 2.093, 30: 2.042, 40: 2.021, 60: 2.000, 120: 1.980}


@pytest.mark.parametrize(("dof", "value"), sorted(T975.items()))
def test_t_quantiles_match_the_tables(dof, value):
    assert t_ppf(0.975, dof) == pytest.approx(value, abs=6e-4)
    assert t_sf(value, dof) == pytest.approx(0.025, abs=2e-5)


def test_t_tail_is_symmetric_and_matches_the_normal_limit():
    assert t_sf(0.0, 7) == pytest.approx(0.5)
    assert t_sf(-1.5, 7) == pytest.approx(1.0 - t_sf(1.5, 7))
    assert 2 * t_sf(2.0, 10) == pytest.approx(0.0734, abs=1e-4)  # two-sided p of t = 2, 10 dof (tables)
    assert t_sf(1.959964, 1e7) == pytest.approx(0.025, abs=1e-6)


def test_ci95_uses_the_t_quantile_for_any_number_of_seeds():
    rng = np.random.default_rng(0)
    for n in (2, 5, 20, 45):
        v = rng.normal(3.0, 2.0, (n, 3))
        mean, half = ci95(v)
        np.testing.assert_allclose(mean, v.mean(axis=0))
        np.testing.assert_allclose(half, t_ppf(0.975, n - 1) * v.std(axis=0, ddof=1) / np.sqrt(n))
    mean, half = ci95([[1.0, 2.0]])
    assert np.isnan(half).all() and mean.tolist() == [1.0, 2.0]


def test_ci95_covers_the_mean_95_percent_of_the_time():
    rng = np.random.default_rng(1)
    hits = [abs(m[0] - 1.0) <= h[0] for m, h in (ci95(rng.normal(1.0, 1.0, (8, 1))) for _ in range(4000))]
    assert 0.94 < np.mean(hits) < 0.96


def test_welch_verdicts():
    rng = np.random.default_rng(2)
    small, large = rng.normal(1.0, 0.1, 20), rng.normal(2.0, 0.5, 20)
    assert compare_less(small, large)[0] == HOLDS
    assert compare_less(large, small)[0] == FAILS
    # S10 vs S12 of an old README: overlapping intervals (53.5±23.4 vs 79.8±48.1) must not be called "holds"
    a, b = rng.normal(53.5, 50.0, 20), rng.normal(79.8, 100.0, 20)
    verdict, p = compare_less(a, b)
    assert verdict == INCONCLUSIVE and 0.05 <= p <= 0.95
    with pytest.raises(ValueError, match="at least 2 values"):
        welch_less([1.0], [1.0, 2.0])


def test_welch_p_values_are_uniform_under_the_null():
    rng = np.random.default_rng(3)
    p = np.array([welch_less(rng.normal(0, 1, 6), rng.normal(0, 3, 11)) for _ in range(3000)])
    assert abs(np.mean(p < 0.05) - 0.05) < 0.012 and abs(np.mean(p < 0.5) - 0.5) < 0.03


def test_ratio_verdicts():
    rng = np.random.default_rng(4)
    a = rng.normal(1.0, 0.05, 20)
    assert ratio_within(a, rng.normal(1.05, 0.05, 20), 1.5)[0] == HOLDS
    assert ratio_within(a, rng.normal(3.0, 0.05, 20), 1.5)[0] == FAILS
    assert ratio_within(rng.normal(1.0, 0.6, 5), rng.normal(1.4, 0.6, 5), 1.5)[0] == INCONCLUSIVE


def _run(sid, seed, horiz, vert=0.1, update_ms=1.0):
    return {"scenario": sid, "seed": seed, "rmse_converged_m": [horiz / np.sqrt(2), horiz / np.sqrt(2), vert],
            "rmse_m": [horiz, horiz, vert], "update_ms_median": update_ms}


def test_claims_from_constructed_runs():
    """Point cloud far better than the altimeter → holds; S5 worse than S6 → does not hold; a missing scenario →
    not run; overlapping S1/S2 → inconclusive."""
    rng = np.random.default_rng(5)
    runs = []
    for s in range(20):
        for sid, h in (("S7", 0.3), ("S8", 0.3), ("S9", 5.0), ("S10", 1.0), ("S11", 1.0), ("S12", 20.0),
                       ("S5", 0.5), ("S6", 0.2)):
            runs.append(_run(sid, s, h * (1 + 0.1 * rng.normal()), update_ms=3.0 if sid == "S7" else 1.0))
        runs += [_run("S1", s, 0.3 + 0.3 * rng.normal()), _run("S2", s, 0.32 + 0.3 * rng.normal())]
    found = {c["claim"].split(" (")[0]: c for c in claims.evaluate(runs)}
    assert found["point cloud beats the altimeter horizontally on rugged and flat terrain"]["verdict"] == HOLDS
    assert found["flat terrain is worse than rugged"]["verdict"] == HOLDS
    assert found["raycast is better than sliding at low altitude / 60° bank"]["verdict"] == FAILS
    assert found["raycast and sliding are close at high altitude"]["verdict"] == claims.NOT_RUN  # no S3/S4
    assert found["the navigation IMU is better than the low-end tactical one"]["verdict"] == INCONCLUSIVE
    assert found["sliding is much cheaper than raycasting"]["verdict"] == HOLDS
    assert all("p = " in c["evidence"] for c in found.values() if c["verdict"] in (HOLDS, FAILS))


def test_committed_claims_rederive_from_their_runs():
    """Each committed claims.json is what warptan.sim.claims gives on the committed results.json (no hand edits)."""
    for folder in sorted((ROOT / "results").glob("*/*/claims.json")):
        data = json.loads(folder.read_text())
        runs = json.loads((folder.parent / "results.json").read_text())["runs"]
        nb = folder.parent / "no_baro" / "results.json"
        no_baro = json.loads(nb.read_text())["runs"] if nb.exists() else []
        assert claims.evaluate(runs, no_baro) == data["claims"], folder


class _Run:
    def __init__(self, errors):
        self.t_s = np.arange(len(errors), dtype=float)
        self.error = errors
        self.sigma3_pos = np.full_like(errors, 3.0)
        self.update_time_s = np.full(len(errors), 1e-3)

    def coverage(self, after):
        sel = self.t_s >= after
        return (np.abs(self.error[sel]) <= self.sigma3_pos[sel]).mean(axis=0)


class _Result:
    def __init__(self, sid, seed, rmse, errors):
        self.scenario, self.seed, self.terrain, self.device = sid, seed, "synthetic:flat", "cpu"
        self.rmse = self.rmse_converged = np.asarray(rmse, dtype=float)
        self.run = _Run(errors)
        self.wall_s = 1.0
        s8 = load_config("S8")
        self.config = s8.replace(sensor={"model": "sliding", "backend": "dda", "surface": "triangles", "rate_hz": 10.0,
                                         "use_baro": True}, likelihood={"kind": "gaussian"},
                                 imu={"grade": "navigation"}, flight={"bank_deg": 0.0, "altitude_rule": "high"},
                                 filter={"particles": 8, "converged_after_s": 1.0})
        self.config = dataclasses.replace(self.config, paper_rmse_m=(1.0, 1.0, 1.0))

    def linear_summary(self):
        return {"attitude_rmse_converged_deg": [1.0, 2.0, 3.0], "coverage_3sigma_attitude": [1.0, 1.0, 0.5],
                "gyro_bias_rmse_after_60s_dph": [3.0, 4.0, 0.0], "sigma_over_rmse_pos": [1.0, 1.0, 1.0],
                "sigma_over_rmse_attitude": [1.0, np.nan, 2.0]}


def test_aggregate_pools_seeds():
    errors = np.array([[0.0, 0.0, 0.0], [1.0, 4.0, 0.0], [1.0, 1.0, 5.0], [2.0, 1.0, 0.0]])
    res = [_Result("S8", 0, [1.0, 2.0, 3.0], errors), _Result("S8", 1, [3.0, 2.0, 1.0], errors)]
    agg = aggregate(res)["S8"]
    assert agg["seeds"] == [0, 1] and agg["rmse_converged_mean_m"] == [2.0, 2.0, 2.0]
    assert agg["rmse_converged_ci95_m"] == pytest.approx([t_ppf(0.975, 1) * np.sqrt(2) / np.sqrt(2), 0.0,
                                                          t_ppf(0.975, 1) * np.sqrt(2) / np.sqrt(2)])
    assert agg["coverage_3sigma_mean"] == pytest.approx([1.0, 2 / 3, 2 / 3])
    assert agg["attitude_rmse_deg"] == pytest.approx([1.0, 2.0, 3.0])
    assert agg["sigma_over_rmse_attitude_mean"] == pytest.approx([1.0, np.nan, 2.0], nan_ok=True)
    assert agg["update_ms_median"] == pytest.approx(1.0)


@pytest.mark.slow
def test_bench_numpy_baseline_runs(tmp_path):
    """The NumPy / trimesh baseline script runs on a tiny case and writes its JSON with meta."""
    out = tmp_path / "b.json"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_numpy_baseline.py"), "--n", "8", "--m-side",
                           "3", "--repeats", "1", "--raycast-repeats", "1", "--terrain",
                           "synthetic:rugged,size_m=4000,spacing=40", "--json", str(out)], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    data = json.loads(out.read_text())
    assert {r["model"] for r in data["results"]} >= {"sliding", "raycast"}
    assert all(r["max_abs_error_difference_m"] < 0.01 for r in data["results"])
    assert "git_commit" in data["meta"] and "command" in data["meta"]


def test_every_artifact_names_its_provenance():
    """Every JSON under benchmarks/ and results/ carries meta: commit, date, CPU, cores and threads, Warp and
    Python versions, devices and the exact command, and the GPU name and driver where CUDA was used."""
    from warptan.meta import REQUIRED

    paths = sorted([*(ROOT / "benchmarks").glob("*.json"), *(ROOT / "results").rglob("*.json")])
    assert len(paths) >= 10
    for path in paths:
        meta = json.loads(path.read_text()).get("meta", {})
        missing = [k for k in REQUIRED if k not in meta]
        assert not missing, (path, missing)
        if any(d.startswith("cuda") for d in meta["devices"]):
            assert meta["gpu"]["names"] and meta["gpu"]["driver"], path


def test_a_run_whose_bounds_stay_wide_declares_itself_unconverged():
    """``declared_unconverged``: the RMS over the converged epochs of the larger horizontal 3σ against 50 m (the
    down axis does not count); a run that ended before the convergence time is not flagged."""
    from types import SimpleNamespace

    from warptan.sim.report import UNCONVERGED_3SIGMA_M, declared_unconverged

    t = np.arange(0.0, 120.0, 0.1)
    sig = np.tile([3.0, 4.0, 500.0], (len(t), 1))
    run = SimpleNamespace(t_s=t, sigma3_pos=sig)
    assert UNCONVERGED_3SIGMA_M == 50.0 and not declared_unconverged(run, 30.0)
    sig[t >= 30.0, 1] = 60.0
    assert declared_unconverged(run, 30.0)
    sig[t >= 30.0, 1] = 4.0
    sig[t < 30.0, 0] = 1e4  # before convergence it does not count
    assert not declared_unconverged(run, 30.0) and not declared_unconverged(run, 200.0)


def test_warptan_run_notes_an_unconverged_run(capsys):
    """The command line names a run that declared itself unconverged (and no other)."""
    from types import SimpleNamespace

    from warptan import cli

    t = np.arange(0.0, 60.0, 0.1)
    wide = SimpleNamespace(t_s=t, sigma3_pos=np.tile([300.0, 200.0, 5.0], (len(t), 1)))
    narrow = SimpleNamespace(t_s=t, sigma3_pos=np.tile([3.0, 2.0, 5.0], (len(t), 1)))
    config = load_config("S8").replace(filter={"converged_after_s": 30.0})
    cli.commands._report_unconverged([SimpleNamespace(scenario="S9", seed=4, run=wide, config=config),
                             SimpleNamespace(scenario="S8", seed=1, run=narrow, config=config)])
    out = capsys.readouterr().out
    assert "S9 seed 4: unconverged" in out and "S8" not in out


def test_the_plots_say_what_they_show(monkeypatch, tmp_path):
    """The errors plot's title gives the RMSE after convergence (the whole run's beside it) and its bands are named
    apart (the filter's ±3σ, the best possible); the ESS threshold is labelled; the track plot has a colour bar of the
    terrain's height and a start in its legend (issue 67)."""
    pytest.importorskip("matplotlib")
    import matplotlib.figure

    from warptan.sim.report import plot_run
    from warptan.sim.scenarios import run_scenario

    seen = []
    save = matplotlib.figure.Figure.savefig

    def spy(fig, *args, **kwargs):
        seen.append([(ax.get_title(), ax.get_ylabel(), [t.get_text() for t in (ax.get_legend().get_texts()
                      if ax.get_legend() else [])], ax.get_ylim()) for ax in fig.axes])
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", spy)
    r = run_scenario("S8", duration_s=35.0, particles=64, device="cpu")
    plot_run(r, r.truth_terrain, tmp_path / "x")
    track, errors = seen
    assert any(label == "terrain height (m)" for _, label, _, _ in track) and "start" in track[0][2]
    # the track's error scale: its panel gives its number (it is under the truth at the map's scale)
    along = next(t for t in track if t[1] == "horizontal error (m)")
    assert along[0].startswith("horizontal RMSE after 30 s") and "3 DRMS" in along[2][0]
    # the axes' scales are read after convergence (a 5 m floor drew 0.25 m errors in a ±5 m panel)
    north = next(t for t in errors if t[1] == "north error (m)")
    assert north[3][1] < 5.0
    title = errors[0][0]
    assert "after 30 s" in title and "whole run" in title
    assert {"±3σ the filter reports", "±3σ best possible (PCRB)"} <= set(errors[0][2])
    assert any(text.startswith("N/2 = 32") for _, _, texts, _ in errors for text in texts)
