"""The device a run picks by itself (issue 67): ``auto``, the default of the CLI and the API, is a CUDA GPU when Warp
sees one and the CPU otherwise; ``--device cpu`` forces the CPU; the run says what it chose."""

import inspect
import json

import pytest
import warp as wp

from warptan import cli
from warptan.device import auto_device, device_words, resolve_device
from warptan.sim.campaign_run import run_campaign
from warptan.sim.replay import replay
from warptan.sim.scenarios import run_scenario, run_scenario_batch


def test_auto_is_a_gpu_only_when_warp_sees_one(monkeypatch):
    monkeypatch.setattr(wp, "is_cuda_available", lambda: False)
    assert auto_device() == auto_device("auto") == "cpu" and resolve_device("auto").is_cpu
    monkeypatch.setattr(wp, "is_cuda_available", lambda: True)
    assert auto_device("auto") == "cuda:0" and auto_device("auto", cluster=True) == "cuda"
    assert auto_device("cpu") == "cpu" and auto_device("cuda:1") == "cuda:1"  # (what the user names is kept)
    assert device_words("auto", "cuda:0") == "cuda:0 (auto: a CUDA GPU was found; --device cpu forces the CPU)"
    assert device_words("auto", "cpu") == "cpu (auto: no CUDA GPU)" and device_words("cpu", "cpu") == "cpu"


def test_the_cli_and_the_api_default_to_auto(capsys, tmp_path):
    parser = cli.build_parser()
    for argv in (["run"], ["replay", "flight.h5"], ["campaign", "campaign.toml"]):
        assert parser.parse_args(argv).device == "auto", argv
    for fn in (run_scenario, run_scenario_batch, replay, run_campaign):
        assert inspect.signature(fn).parameters["device"].default == "auto", fn.__name__
    out = tmp_path / "r"
    status = cli.main(["run", "S8", "--duration-s", "0.1", "--particles", "16", "--no-plots", "--out", str(out)])
    _, err = capsys.readouterr()
    chosen = "cuda:0" if wp.is_cuda_available() else "cpu"
    assert status == 0 and f"warptan run: S8, 1 seed(s), device {chosen} (auto: " in err.splitlines()[0]
    assert list(json.loads((out / "results.json").read_text())["meta"]["devices"]) == [chosen]
    status = cli.main(["run", "S8", "--duration-s", "0.1", "--particles", "16", "--no-plots", "--out", str(out),
                       "--device", "cpu"])
    _, err = capsys.readouterr()
    assert status == 0 and "device cpu\n" in err.splitlines(keepends=True)[0]
    assert list(json.loads((out / "results.json").read_text())["meta"]["devices"]) == ["cpu"]


def test_auto_runs_on_cuda_when_warp_sees_a_gpu():
    if not wp.is_cuda_available():
        pytest.skip("no CUDA device visible to Warp")
    r = run_scenario("S8", duration_s=2.0, particles=64, bound=False)
    assert str(r.device) == "cuda:0"


def test_the_modes_tables_are_built_on_one_blas_thread(monkeypatch):
    """``one_blas_thread``: NumPy's BLAS runs one thread inside (whatever it ran before, restored after), and the
    map-error mode table's eigenproblem is solved inside it (``Likelihood.error_modes``)."""
    import numpy as np
    from threadpoolctl import threadpool_info

    import warptan.sensing.likelihood as lk
    from warptan.device import one_blas_thread

    def blas_threads():
        return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]

    before = blas_threads()
    assert before, "NumPy's BLAS is not visible to threadpoolctl"
    with one_blas_thread():
        assert blas_threads() == [1] * len(before)
    assert blas_threads() == before
    seen = []
    eigh = np.linalg.eigh
    monkeypatch.setattr(lk.np.linalg, "eigh", lambda a: (seen.append(blas_threads()), eigh(a))[1])
    likelihood = lk.Likelihood(kind="gaussian", map_error_sigma_m=5.0, map_error_corr_m=1000.0, track_step_m=10.0)
    xy = np.stack(np.meshgrid(np.linspace(-200, 200, 6), np.linspace(-200, 200, 6)), axis=-1).reshape(-1, 2)
    table, info = likelihood.error_modes(xy, np.ones(len(xy)), 1.0, np.array([1.0, 0.0]), True, 0.01)
    assert seen == [[1] * len(before)] and info["n_modes"] > 0 and np.isfinite(table).all()
    assert blas_threads() == before
