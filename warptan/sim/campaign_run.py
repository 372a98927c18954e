"""Running a campaign (:class:`~warptan.sim.campaign.Campaign`): one batch as a task (:func:`run_batch`), its row
(:func:`make_row`), and the engines that run the batches, in this process or on a Ray cluster
(:func:`run_campaign`; see :mod:`warptan.sim.campaign` for what the engines promise)."""

from __future__ import annotations

import logging
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from warptan.progress import compile_notice, progress_bar
from warptan.sim.campaign import ENGINES, RETRIES, Batch, Campaign, CampaignError
from warptan.sim.report import ci95


# ---------------------------------------------------------------------- one batch (a task)
def run_batch(spec: dict, device: str = "cpu", cpu_threads: int | None = None, progress=None) -> dict:
    """Run one batch (``Batch.spec()``) on ``device``; the function a task runs, here or on a Ray worker.

    Returns the per-seed summaries (:meth:`~warptan.sim.scenarios.ScenarioResult.summary`) and where and how long it
    ran. ``cpu_threads`` sets ``WARPTAN_CPU_THREADS`` first (the CPUs the task was given); ``progress(k, n)`` is
    called at every update, ``k`` of ``n`` the batch's steps done (seeds one by one: theirs in turn)."""
    if cpu_threads:
        os.environ["WARPTAN_CPU_THREADS"] = str(int(cpu_threads))
    from warptan.device import quiet_warp, resolve_device
    from warptan.meta import cpu_model
    from warptan.sim.scenarios import run_scenario, run_scenario_batch

    quiet_warp()
    start, t0 = time.time(), time.perf_counter()
    seeds, overrides = list(spec["seeds"]), dict(spec["overrides"])
    if spec.get("batched", True):
        results = run_scenario_batch(spec["scenario"], seeds, device=device, progress=progress, **overrides)
    else:
        results = []
        for i, s in enumerate(seeds):
            each = None if progress is None else (lambda k, n, i=i: progress(i * n + k, len(seeds) * n))
            results.append(run_scenario(spec["scenario"], seed=s, device=device, progress=each, **overrides))
    wall = time.perf_counter() - t0
    dev = resolve_device(device)
    return {"summaries": [r.summary() for r in results], "wall_s": wall, "device": dev.alias,
            "device_name": dev.name if dev.is_cuda else cpu_model(), "host": socket.gethostname(), "pid": os.getpid(),
            "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES"), "start_unix": start,
            "end_unix": time.time()}


def estimate_batch_s(batch: Batch, duration_s: float, device: str = "cpu", pilot_s: float = 1.0) -> float:
    """The wall time (s) one batch will take on ``device``, from a pilot: the batch's own runs (its seeds, batched or
    seed by seed as it will run) over the first ``pilot_s`` of the flight, timed after a first pilot that compiles
    what the batch needs; the filter's time scales with the flight (``duration_s``), the setup (world, map, flight,
    bound) is counted once per run. A local estimate: on a cluster the batches run side by side."""
    from warptan.sim.scenarios import run_scenario_batch

    short = min(float(pilot_s), float(duration_s))
    kw = {**batch.overrides, "duration_s": short}
    seeds = list(batch.seeds if batch.batched else batch.seeds[:1])  # (seed by seed: one, times their number)
    run_scenario_batch(batch.scenario, seeds, device=device, **kw)  # compiles; the next is timed
    t0 = time.perf_counter()
    results = run_scenario_batch(batch.scenario, seeds, device=device, **kw)
    call = time.perf_counter() - t0
    loop = results[0].wall_s
    one = max(call - loop, 0.0) + loop * (float(duration_s) / short)
    return one if batch.batched else one * len(batch.seeds)


def make_row(batch: Batch, summaries: list[dict]) -> dict:
    """The campaign row of a finished batch: RMSE (whole run and after convergence) mean ± 95 % interval over the
    seeds, mean 3σ coverage after convergence, and the per-seed values. Only numbers that the scenario, combination,
    seeds and kind of device determine (no timings): the same from either engine."""
    def col(key):
        return np.array([s[key] for s in summaries], dtype=np.float64)

    rm, rh = ci95(col("rmse_m"))
    cm, ch = ci95(col("rmse_converged_m"))
    return {
        "scenario": summaries[0]["scenario"], "params": dict(batch.params), "seeds": [s["seed"] for s in summaries],
        "rmse_converged_m": cm.tolist(), "rmse_converged_ci95_m": ch.tolist(),
        "rmse_m": rm.tolist(), "rmse_ci95_m": rh.tolist(),
        "coverage_3sigma": col("coverage_3sigma").mean(axis=0).tolist(),
        "skipped_updates": int(sum(s["skipped_updates"] for s in summaries)),
        "seeds_without_any_update": [s["seed"] for s in summaries if s["updates"] and not s["updates_used"]],
        "seeds_declared_unconverged": [s["seed"] for s in summaries if s["declared_unconverged"]],
        "per_seed": [{k: s[k] for k in ("seed", "rmse_m", "rmse_converged_m", "coverage_3sigma", "min_ess",
                                        "respreads", "declared_unconverged", "updates", "skipped_updates",
                                        "updates_used")}
                     for s in summaries],
    }


# ---------------------------------------------------------------------- engines
@dataclass
class CampaignResult:
    """What a campaign produced: a row per finished batch (in batch order), the failed batches, and per task where
    and how long it ran."""

    campaign: Campaign
    engine: str
    device: str
    rows: list[dict]
    failures: list[dict]
    tasks: list[dict]
    wall_s: float
    cluster: dict | None = None


def check_options(engine: str, device, address: str | None = None, cpus_per_task: int = 1) -> str:
    """Refuse (:class:`CampaignError`, or ValueError for an absent local device) engine options that cannot run;
    returns the device the batches' memory is checked against (Ray workers may have other devices than this
    process: this host's memory)."""
    if engine not in ENGINES:
        raise CampaignError(f"unknown engine {engine!r}; use one of {', '.join(ENGINES)}")
    if address is not None and engine != "ray":
        raise CampaignError("--address names a Ray cluster; it needs --engine ray")
    if not isinstance(cpus_per_task, int) or cpus_per_task < 1:
        raise CampaignError(f"cpus_per_task must be a whole number ≥ 1, got {cpus_per_task!r}")
    if engine == "local":
        from warptan.device import resolve_device

        resolve_device(device)
        return device
    if str(device).startswith("cuda") and str(device) != "cuda":
        raise CampaignError(f"with the ray engine give --device cuda (each task gets one GPU of the cluster), "
                            f"not {device!r}")
    return "cpu"


def run_campaign(campaign: Campaign, engine: str = "local", device: str = "auto", address: str | None = None,
                 cpus_per_task: int = 1, progress: bool = True, task: Callable | None = None,
                 checked: bool = False) -> CampaignResult:
    """Run every batch of ``campaign``.

    Args:
        engine: ``local`` (in this process, one batch after another) or ``ray`` (one Ray task per batch).
        device: ``auto`` (the default: a CUDA GPU when Warp sees one here, else ``cpu``), ``cpu`` or a CUDA device;
            with Ray, ``cuda`` (each task gets one GPU of the cluster and runs on it).
        address: Ray cluster address (default: a local cluster started for the campaign, or the one this process
            is already connected to).
        cpus_per_task: CPUs a Ray task asks for on a CPU device (its CPU launch threads).
        progress: A tqdm progress bar over the batches (stderr).
        task: The function that runs a batch (default :func:`run_batch`; for instrumentation and tests).
        checked: :meth:`Campaign.check` was already called (with the device :func:`check_options` returns).

    A batch that raises is run once more, then reported in ``failures``; the other batches are kept.
    """
    from warptan.device import auto_device

    device = auto_device(device, cluster=engine == "ray")
    memory_device = check_options(engine, device, address, cpus_per_task)
    if not checked:
        campaign.check(memory_device)
    task = task or run_batch
    t0 = time.perf_counter()
    if engine == "local":
        outcomes, cluster = _run_local(campaign, device, task, progress), None
    else:
        outcomes, cluster = _run_ray(campaign, str(device).startswith("cuda"), address, cpus_per_task, task,
                                     progress)
    wall = time.perf_counter() - t0
    rows, failures, tasks = [], [], []
    for b in campaign.batches:
        out = outcomes[b.index]
        if "error" in out:
            failures.append({"scenario": b.name, "params": dict(b.params), "seeds": list(b.seeds),
                             "error": out["error"], "attempts": out["attempts"], "traceback": out["traceback"]})
            continue
        rows.append(make_row(b, out["summaries"]))
        tasks.append({"batch": b.label, **{k: v for k, v in out.items() if k != "summaries"}})
    return CampaignResult(campaign, engine, str(device), rows, failures, tasks, wall, cluster)


def _describe_error(err: BaseException) -> str:
    """One line for a failed batch: the original exception (unwrapped from Ray's task error)."""
    cause = getattr(err, "cause", None) or err
    text = " ".join(str(cause).split()) or type(cause).__name__
    return f"{type(cause).__name__}: {text}"


def _bar(total: int, progress: bool):
    return progress_bar(total, "batch", disable=not progress)


def _run_local(campaign: Campaign, device: str, task: Callable, progress: bool) -> dict[int, dict]:
    outcomes = {}
    with _bar(len(campaign.batches), progress) as bar, compile_notice(bar.write if progress else lambda text: None):
        shown = [0.0]

        def within(k: int, n: int) -> None:  # how far the batch is, beside the bar over batches
            now = time.monotonic()
            if now - shown[0] >= 0.2 or k >= n:
                shown[0] = now
                bar.set_postfix_str(f"this batch {100.0 * min(k, n) / max(n, 1):.0f} %", refresh=True)

        extra = {"progress": within} if progress and task is run_batch else {}
        for b in campaign.batches:
            bar.set_description(b.label)
            for attempt in range(1, RETRIES + 2):
                try:
                    outcomes[b.index] = task(b.spec(), device, **extra)
                    break
                except Exception as err:  # a failed batch is reported, the campaign goes on
                    outcomes[b.index] = {"error": _describe_error(err), "attempts": attempt,
                                         "traceback": _traceback_text(err)}
            bar.update(1)
    return outcomes


def _traceback_text(err: BaseException) -> str:
    import traceback

    return "".join(traceback.format_exception(type(err), err, err.__traceback__))[-4000:]


def _on_ray_worker(task: Callable, spec: dict, cuda: bool, cpu_threads: int | None) -> dict:
    """A batch on a Ray worker: on the GPU Ray assigned to this task (its Warp ordinal among the GPUs the worker
    sees), else on the CPU with ``cpu_threads`` launch threads."""
    device, ids = "cpu", []
    if cuda:
        import ray

        ids = [str(i) for i in ray.get_gpu_ids()]
        visible = os.environ.get("CUDA_VISIBLE_DEVICES")
        order = [v.strip() for v in visible.split(",")] if visible else None
        if not ids or (order is not None and ids[0] not in order):
            raise RuntimeError(f"Ray assigned GPU(s) {ids} but the worker sees CUDA_VISIBLE_DEVICES={visible}")
        device = f"cuda:{order.index(ids[0]) if order is not None else int(ids[0])}"
    return {**task(spec, device, cpu_threads), "ray_gpu_ids": ids}


def _signal_handlers(restore: dict | None = None) -> dict:
    """The Python handlers of SIGINT and SIGTERM (main thread only), or with ``restore`` those put back. ``ray.init``
    replaces them with its own (a C++ crash handler that printed a stack dump on SIGTERM, rc 1 or 134), so the
    command's own clean-up (the output folder as it was, rc 143) never ran."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}
    if restore is not None:
        for sig, handler in restore.items():
            if handler is not None:
                signal.signal(sig, handler)
        return restore
    return {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}


def _run_ray(campaign: Campaign, cuda: bool, address: str | None, cpus_per_task: int, task: Callable,
             progress: bool) -> tuple[dict[int, dict], dict]:
    try:
        import ray
    except ModuleNotFoundError:
        raise CampaignError("the ray engine needs Ray: pip install 'warptan[cluster]'") from None
    started = not ray.is_initialized()
    workdir = None
    if started:
        # The workers' working folder: an empty one, so that a checkout's source folder in the current directory
        # never shadows the installed package on a worker (Ray puts the driver's directory on the workers' path
        # unless a working_dir is given). File names in the campaign were made absolute when it was read.
        workdir = tempfile.mkdtemp(prefix="warptan-ray-")
        held = _signal_handlers()
        try:
            ray.init(address=address, include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False,
                     runtime_env={"working_dir": workdir})
        except Exception as err:  # Ray raises ConnectionError, RuntimeError, ValueError …
            shutil.rmtree(workdir, ignore_errors=True)
            raise CampaignError(f"cannot start or reach the Ray cluster{f' at {address}' if address else ''}: "
                                f"{_describe_error(err)}") from None
        finally:
            _signal_handlers(held)
    refs: dict = {}
    try:
        resources = ray.cluster_resources()
        cluster = {"address": address or "local", "resources": {k: v for k, v in resources.items()
                                                                if k in ("CPU", "GPU", "memory")},
                   "nodes": len([n for n in ray.nodes() if n.get("Alive")])}
        if cuda and resources.get("GPU", 0) < 1:
            raise CampaignError(f"--device cuda: the Ray cluster ({cluster['address']}) has no GPU "
                                f"(resources {cluster['resources']})")
        if not cuda and resources.get("CPU", 0) < cpus_per_task:
            raise CampaignError(f"--cpus-per-task {cpus_per_task}: the Ray cluster has {resources.get('CPU', 0):g} "
                                "CPUs")
        if cuda:
            # Workers are reused between GPU tasks (a fresh worker costs seconds: Python, Warp, CUDA context,
            # kernel modules). Ray would pin each worker's CUDA_VISIBLE_DEVICES to its first task's GPU, which a
            # CUDA process cannot change later; so the workers see every GPU and each task runs on the one Ray
            # assigned to it (:func:`_on_ray_worker`).
            options = {"num_gpus": 1, "num_cpus": 1, "max_calls": 0,
                       "runtime_env": {"env_vars": {"RAY_EXPERIMENTAL_NOSET_CUDA_VISIBLE_DEVICES": "1"}}}
        else:
            options = {"num_cpus": cpus_per_task}
        remote = ray.remote(max_retries=RETRIES, retry_exceptions=True, **options)(_on_ray_worker)
        refs = {remote.remote(task, b.spec(), cuda, None if cuda else cpus_per_task): b for b in campaign.batches}
        outcomes = {}
        with _bar(len(refs), progress) as bar:
            while refs:
                done, _ = ray.wait(list(refs), num_returns=1)
                for ref in done:
                    b = refs.pop(ref)
                    try:
                        outcomes[b.index] = ray.get(ref)
                    except Exception as err:  # reported; the others are kept
                        outcomes[b.index] = {"error": _describe_error(err), "attempts": RETRIES + 1,
                                             "traceback": str(err)[-4000:]}
                    bar.set_description(b.label)
                    bar.update(1)
        return outcomes, cluster
    finally:
        for ref in refs:  # interrupted: nothing left running on the cluster
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()
            shutil.rmtree(workdir, ignore_errors=True)
