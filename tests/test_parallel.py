"""Multi-core CPU launches give bit-identical results to one launch."""

import numpy as np
import pytest

import warptan as wt
from warptan.parallel import cpu_threads


def _sliding_and_raycast(terrain, monkeypatch, threads):
    monkeypatch.setenv("WARPTAN_CPU_THREADS", str(threads))
    import warp as wp

    rng = np.random.default_rng(0)
    n = 1000
    pos = np.stack([rng.normal(0, 200, n), rng.normal(0, 200, n), np.full(n, -(terrain.h_max + 500))], 1)
    quat = np.tile([1.0, 0, 0, 0], (n, 1))
    p = wp.array(pos.astype(np.float32), dtype=wp.vec3, device="cpu")
    q = wp.array(quat.astype(np.float32), dtype=wp.vec4, device="cpu")
    cloud = wt.PointCloudSensor(wt.ScanPattern.grid(6, 6)).measure(terrain, [0, 0, -(terrain.h_max + 500)],
                                                                     [1.0, 0, 0, 0])
    outs = []
    for model in (wt.SlidingModel(terrain, wt.Likelihood("student_t")), wt.RaycastModel(terrain)):
        o = model.evaluate(p, q, cloud)
        outs += [o.residual_m.numpy().copy(), o.loglik.numpy().copy(), o.n_valid.numpy().copy()]
    return outs


def test_chunked_models_are_identical(monkeypatch):
    """Sliding and ray-cast models on 4 CPU threads equal the single-thread launch bit for bit."""
    terrain = wt.Terrain.synthetic("rugged", size_m=4000.0, spacing=30.0, seed=3)
    one = _sliding_and_raycast(terrain, monkeypatch, 1)
    four = _sliding_and_raycast(terrain, monkeypatch, 4)
    for a, b in zip(one, four, strict=True):
        np.testing.assert_array_equal(a, b)


def test_chunked_filter_is_identical(monkeypatch):
    """A whole scenario run (time updates, models, reductions) is identical with 1 and 3 CPU threads."""
    runs = []
    for threads in (1, 3):
        monkeypatch.setenv("WARPTAN_CPU_THREADS", str(threads))
        r = wt.run_scenario("S8", seed=2, terrain="synthetic:rugged,size_m=12000,spacing=40,seed=2",
                                      particles=700, duration_s=5.0)
        runs.append(r.run)
    np.testing.assert_array_equal(runs[0].est_pos, runs[1].est_pos)
    np.testing.assert_array_equal(runs[0].ess, runs[1].ess)


def test_bad_thread_setting(monkeypatch):
    """A non-numeric WARPTAN_CPU_THREADS is a clear error."""
    monkeypatch.setenv("WARPTAN_CPU_THREADS", "many")
    with pytest.raises(ValueError, match="WARPTAN_CPU_THREADS"):
        cpu_threads()


@pytest.mark.parametrize("scenario, overrides", [
    ("S8", {"likelihood": "gaussian"}),
    ("S1", {"likelihood": "paper", "closed_loop": True}),
    ("S9", {}),
])
def test_replayed_launches_are_identical(monkeypatch, scenario, overrides):
    """An eager CPU run whose fixed pieces replay recorded launches (:class:`warptan.parallel.Recorder`; chunks on 3
    threads) equals one that launches every kernel anew, bit for bit: estimates, ESS, tempering stages, resampling
    and the closed loop's injections. The replay was used (recordings exist and outnumber nothing)."""
    import warptan.filter.mpf as mpf_module

    monkeypatch.setenv("WARPTAN_CPU_THREADS", "3")
    made = []

    class Counting(mpf_module.Recorder):
        def __init__(self):
            super().__init__()
            made.append(self)

    runs = []
    for recorder in (Counting, lambda: None):
        monkeypatch.setattr(mpf_module, "Recorder", recorder)
        r = wt.run_scenario(scenario, seed=3, terrain="synthetic:rugged,size_m=12000,spacing=40,seed=2",
                                      particles=700, duration_s=6.0, **overrides)
        runs.append(r.run)
    assert made and len(made[0]) >= 4, [len(m) for m in made]
    assert runs[0].stages.max() >= 2 or scenario != "S8", runs[0].stages  # tempered stages were replayed too
    for name in ("est_pos", "sigma3_pos", "ess", "stages", "resampled", "lin_err", "sigma3_lin", "nis_avg"):
        np.testing.assert_array_equal(getattr(runs[0], name), getattr(runs[1], name), err_msg=name)
    if overrides.get("closed_loop"):
        assert runs[0].info == runs[1].info
