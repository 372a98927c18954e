"""Campaigns: parameter sweeps × seeds × scenarios, in-process or spread over a Ray cluster.

A campaign file (TOML) names scenarios, seeds, keywords every run gets and keywords to sweep::

    scenarios = ["S7", "S8"]
    seeds = 20                 # per combination (0 … 19), or a list of seeds
    [overrides]                # every run: run_scenario keywords
    duration_s = 60.0
    [sweep]                    # cartesian product of run_scenario keywords
    particles = [250, 500, 1000]
    likelihood = ["paper", "gaussian"]

Each (scenario, combination) is one *batch*: its seeds run as one batched filter on one device (seed by seed
where the scenario cannot be batched: a map with per-seed noise). The batches are independent, so they can run
anywhere: ``engine="local"`` runs them in this process one after another; ``engine="ray"`` makes each a Ray task
(one GPU per task for a CUDA device, else ``cpus_per_task`` CPUs), streams results back as tasks finish and
retries a failed task once. A batch's numbers depend only on the scenario, the combination, the seeds and the kind
of device, so both engines give identical rows (the filter's reductions are deterministic and its CPU thread
split is bit-identical; every batch's randomness comes from its seeds).

Everything is validated before any batch runs (the file, every combination's scenario, the seeds, the memory, the
terrain and the flight); a failing batch is reported in ``failures`` and the others are kept.

Ray is imported only by the Ray engine (``pip install "warptan[cluster]"``): ``import warptan`` never imports it.
"""

from __future__ import annotations

import collections
import difflib
import itertools
import logging
import math
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from warptan.progress import progress_bar
from warptan.sim.report import ci95
from warptan.sim.scenario_config import MAX_SEED, RUN_KEYWORDS, SCENARIO_IDS, load_config, scenario_path
from warptan.sim.scenarios import per_seed_maps, prepare

ENGINES = ("local", "ray")
CAMPAIGN_KEYS = ("title", "scenarios", "seeds", "overrides", "sweep")
MAX_CAMPAIGN_SEEDS = 1_000_000
"""Most seeds a campaign runs per batch (a count beyond it is refused before a list of seeds is made)."""
PATH_KEYWORDS = ("terrain", "map_path")
"""Keywords whose string values may be files, resolved relative to the campaign file's folder."""
RETRIES = 1
"""A failed batch is run once more before it is reported as failed."""
MAX_BATCHES = 100_000
"""More (scenario, combination) pairs than this is a typo in the sweep, not a campaign."""


class CampaignError(ValueError):
    """A campaign file or campaign option that cannot run (every problem listed)."""


@dataclass(frozen=True)
class Batch:
    """One (scenario, combination) of a campaign: its seeds run together on one device."""

    index: int
    scenario: str
    """A scenario id (S1…S12) or the absolute path of a scenario file."""
    params: dict
    """The swept keywords' values of this combination."""
    overrides: dict
    """Every run_scenario keyword of its runs (the campaign's overrides and ``params``)."""
    seeds: tuple[int, ...]
    batched: bool = True
    """The seeds run as one batched filter (False: a map with per-seed noise, seed by seed)."""

    @property
    def name(self) -> str:
        """The scenario's id, or its file's name."""
        return self.scenario if self.scenario in SCENARIO_IDS else Path(self.scenario).stem

    @property
    def label(self) -> str:
        """``S8 particles=500 likelihood=paper``."""
        return self.name + "".join(f" {k}={v}" for k, v in self.params.items())

    def spec(self) -> dict:
        """What a task needs to run the batch (plain data: picklable, JSON-ready)."""
        return {"scenario": self.scenario, "seeds": list(self.seeds), "overrides": dict(self.overrides),
                "batched": self.batched}


@dataclass
class Campaign:
    """A parsed and validated campaign file."""

    source: str
    title: str
    scenarios: list[str]
    seeds: list[int]
    overrides: dict
    sweep: dict
    batches: list[Batch] = field(default_factory=list)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Campaign:
        """Read a campaign file; raises :class:`CampaignError` naming the file and every problem in it."""
        path = Path(path)
        try:
            with open(path, "rb") as f:
                data = tomllib.load(f)
        except FileNotFoundError:
            raise CampaignError(f"campaign file not found: {path}") from None
        except IsADirectoryError:
            raise CampaignError(f"campaign file {path} is a folder; give a .toml file") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
            raise CampaignError(f"{path}: not a valid TOML file ({err})") from None
        return cls.from_dict(data, source=str(path), base=path.resolve().parent)

    @classmethod
    def from_dict(cls, data: dict, source: str = "campaign", base: str | os.PathLike | None = None) -> Campaign:
        """A campaign from its parsed TOML (``base``: the folder relative file names are resolved from)."""
        base = Path(base) if base is not None else Path.cwd()
        problems: list[str] = []
        for key in data:
            if key not in CAMPAIGN_KEYS:
                hint = difflib.get_close_matches(key, CAMPAIGN_KEYS, n=1)
                problems.append(f"unknown key {key!r}" + (f" (did you mean {hint[0]!r}?)" if hint else "") +
                                f"; a campaign has {', '.join(CAMPAIGN_KEYS)}")
        title = data.get("title", Path(source).stem)
        if not isinstance(title, str):
            problems.append(f"title must be text, got {title!r}")
        scenarios = _scenarios(data.get("scenarios"), base, problems)
        seeds = _seeds(data.get("seeds"), problems)
        overrides = _keywords(data.get("overrides", {}), "overrides", base, problems)
        sweep = _keywords(data.get("sweep", {}), "sweep", base, problems)
        for key in sorted(set(overrides) & set(sweep)):
            problems.append(f"{key!r} is both in [overrides] and in [sweep]; give it in one of them")
        n_batches = len(scenarios) * math.prod(len(v) for v in sweep.values() if isinstance(v, list))
        if n_batches > MAX_BATCHES:
            problems.append(f"{n_batches} (scenario, combination) batches is more than {MAX_BATCHES}")
        if problems:
            raise CampaignError(f"{len(problems)} problem(s) in campaign {source}:\n  " + "\n  ".join(problems))
        campaign = cls(source=source, title=title, scenarios=scenarios, seeds=seeds, overrides=overrides,
                       sweep=sweep)
        combos = [dict(zip(sweep, values, strict=True)) for values in itertools.product(*sweep.values())]
        campaign.batches = [Batch(i, s, params, {**overrides, **params}, tuple(seeds))
                            for i, (s, params) in enumerate(itertools.product(scenarios, combos))]
        return campaign

    def check(self, device="cpu") -> list[tuple]:
        """Validate every batch as a run would (its scenario with the overrides, the seeds, the memory on
        ``device``, the terrain, the flight, the map) and decide which can be batched; returns each batch's
        (config, truth terrain, flight). Raises :class:`CampaignError` listing every failing batch."""
        problems, plans = [], []
        for i, b in enumerate(self.batches):
            try:
                source = f"campaign {self.source} [overrides]/[sweep]"
                config = load_config(b.scenario, overrides_from=source, **b.overrides)
                self.batches[i] = b = replace(b, batched=not per_seed_maps(config))
                plans.append(prepare(b.scenario, seeds=list(b.seeds), device=device, batched=b.batched,
                                     overrides_from=source, **b.overrides))
            except (ValueError, OSError) as err:
                problems.append(f"{b.label}: " + " ".join(str(err).split()))
        if problems:
            shown = problems[:20] + ([f"… and {len(problems) - 20} more"] if len(problems) > 20 else [])
            raise CampaignError(f"{len(problems)} of {len(self.batches)} batch(es) of campaign {self.source} cannot "
                                "run:\n  " + "\n  ".join(shown))
        ids = {}
        for b, (config, _, _) in zip(self.batches, plans, strict=True):
            ids.setdefault(config["id"], set()).add(b.scenario)
        clash = sorted(i for i, names in ids.items() if len(names) > 1)
        if clash:
            raise CampaignError(f"campaign {self.source}: two scenarios have the id {', '.join(clash)} (rows are kept "
                                "by id); give one of the files another id")
        return plans

    def inputs(self) -> list[str]:
        """The files the campaign reads besides itself: scenario files and DEMs named in [overrides] or [sweep]."""
        files = [s for s in self.scenarios if s not in SCENARIO_IDS]
        for key in PATH_KEYWORDS:
            values = [self.overrides.get(key), *self.sweep.get(key, [])]
            files += [v for v in values if isinstance(v, str) and v and os.path.exists(v)]
        return files

    def describe(self) -> dict:
        """The campaign as JSON-ready data (campaign.json's ``meta.campaign``)."""
        return {"source": self.source, "title": self.title, "scenarios": self.scenarios, "seeds": self.seeds,
                "overrides": self.overrides, "sweep": self.sweep, "batches": len(self.batches)}


def _scenarios(value, base: Path, problems: list[str]) -> list[str]:
    if value is None:
        problems.append('scenarios is missing: a list such as ["S7", "S8"], "all", or scenario .toml files')
        return []
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        problems.append(f"scenarios must be a non-empty list of scenario ids or .toml files, got {value!r}")
        return []
    if [v.lower() for v in value] == ["all"]:
        return list(SCENARIO_IDS)
    out = []
    for v in value:
        if v.lower() == "all":
            problems.append("'all' runs every scenario; give it alone, not with other scenarios")
            continue
        if v.upper() in SCENARIO_IDS:
            out.append(v.upper())
            continue
        path = base / v if v.endswith(".toml") else v  # a file relative to the campaign's folder; else the id
        try:
            out.append(str(scenario_path(path).resolve()))
        except ValueError as err:
            problems.append(str(err))
    repeated = sorted({v for v in out if out.count(v) > 1})
    if repeated:
        problems.append(f"scenario(s) {', '.join(repeated)} given more than once")
    return out


def _seeds(value, problems: list[str]) -> list[int]:
    if value is None:
        problems.append("seeds is missing: a count (seeds = 20 runs seeds 0 … 19) or a list of seeds")
        return []
    if isinstance(value, int) and not isinstance(value, bool):
        if value < 1:
            problems.append(f"seeds must be ≥ 1, got {value}")
            return []
        if value > MAX_CAMPAIGN_SEEDS:  # arithmetic, before any list of seeds is made
            problems.append(f"seeds = {value} is more than {MAX_CAMPAIGN_SEEDS} runs per batch"
                            + (f" (and beyond the largest seed {MAX_SEED})" if value > MAX_SEED + 1 else ""))
            return []
        return list(range(value))
    if isinstance(value, list) and value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        negative, beyond = [v for v in value if v < 0], [v for v in value if v > MAX_SEED]
        if negative:
            problems.append(f"seeds must be ≥ 0, got {negative[:10]}")
        if beyond:
            problems.append(f"seeds must be ≤ {MAX_SEED} (the generators' range), got {beyond[:10]}")
        repeated = sorted(v for v, n in collections.Counter(value).items() if n > 1)
        if repeated:
            problems.append(f"seed(s) {repeated[:10]}{' …' if len(repeated) > 10 else ''} given more than once; each "
                            "seed is one run")
        return list(value)
    problems.append(f"seeds must be a count ≥ 1 or a non-empty list of whole numbers, got {value!r}")
    return []


def _keywords(table, section: str, base: Path, problems: list[str]) -> dict:
    """[overrides] or [sweep]: run_scenario keywords (sweep values are non-empty lists without repeats)."""
    if not isinstance(table, dict):
        problems.append(f"[{section}] must be a table of run_scenario keywords, got {table!r}")
        return {}
    out = {}
    for key, value in table.items():
        if key not in RUN_KEYWORDS:
            hint = difflib.get_close_matches(key, RUN_KEYWORDS, n=1)
            problems.append(f"[{section}] {key!r} is not a run_scenario keyword" +
                            (f" (did you mean {hint[0]!r}?)" if hint else ""))
            continue
        if section == "sweep":
            if not isinstance(value, list) or not value:
                problems.append(f"[sweep] {key} must be a non-empty list of values, got {value!r}")
                continue
            repeated = [v for i, v in enumerate(value) if v in value[:i]]
            if repeated:
                problems.append(f"[sweep] {key} repeats {repeated}; each value is one row")
                continue
            out[key] = [_resolve(key, v, base) for v in value]
        else:
            if isinstance(value, (list, dict)):
                problems.append(f"[overrides] {key} must be one value (sweep lists go in [sweep]), got {value!r}")
                continue
            out[key] = _resolve(key, value, base)
    return out


def _resolve(key: str, value, base: Path):
    """A file name in ``terrain`` or ``map_path`` relative to the campaign file's folder, made absolute (tasks run
    elsewhere); names and specs (``rugged``, ``synthetic:…``) are kept."""
    if key in PATH_KEYWORDS and isinstance(value, str) and value and not Path(value).is_absolute():
        candidate = base / value
        if candidate.exists():
            return str(candidate.resolve())
    return value


# ---------------------------------------------------------------------- one batch (a task)
def run_batch(spec: dict, device: str = "cpu", cpu_threads: int | None = None) -> dict:
    """Run one batch (``Batch.spec()``) on ``device``; the function a task runs, here or on a Ray worker.

    Returns the per-seed summaries (:meth:`~warptan.sim.scenarios.ScenarioResult.summary`) and where and how long it
    ran. ``cpu_threads`` sets ``WARPTAN_CPU_THREADS`` first (the CPUs the task was given)."""
    if cpu_threads:
        os.environ["WARPTAN_CPU_THREADS"] = str(int(cpu_threads))
    from warptan.device import quiet_warp, resolve_device
    from warptan.meta import cpu_model
    from warptan.sim.scenarios import run_scenario, run_scenario_batch

    quiet_warp()
    start, t0 = time.time(), time.perf_counter()
    seeds, overrides = list(spec["seeds"]), dict(spec["overrides"])
    if spec.get("batched", True):
        results = run_scenario_batch(spec["scenario"], seeds, device=device, **overrides)
    else:
        results = [run_scenario(spec["scenario"], seed=s, device=device, **overrides) for s in seeds]
    wall = time.perf_counter() - t0
    dev = resolve_device(device)
    return {"summaries": [r.summary() for r in results], "wall_s": wall, "device": dev.alias,
            "device_name": dev.name if dev.is_cuda else cpu_model(), "host": socket.gethostname(), "pid": os.getpid(),
            "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES"), "start_unix": start,
            "end_unix": time.time()}


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


def run_campaign(campaign: Campaign, engine: str = "local", device: str = "cpu", address: str | None = None,
                 cpus_per_task: int = 1, progress: bool = True, task: Callable | None = None,
                 checked: bool = False) -> CampaignResult:
    """Run every batch of ``campaign``.

    Args:
        engine: ``local`` (in this process, one batch after another) or ``ray`` (one Ray task per batch).
        device: ``cpu`` or a CUDA device; with Ray, ``cuda`` (each task gets one GPU of the cluster and runs on it).
        address: Ray cluster address (default: a local cluster started for the campaign, or the one this process
            is already connected to).
        cpus_per_task: CPUs a Ray task asks for on a CPU device (its CPU launch threads).
        progress: A tqdm progress bar over the batches (stderr).
        task: The function that runs a batch (default :func:`run_batch`; for instrumentation and tests).
        checked: :meth:`Campaign.check` was already called (with the device :func:`check_options` returns).

    A batch that raises is run once more, then reported in ``failures``; the other batches are kept.
    """
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
    with _bar(len(campaign.batches), progress) as bar:
        for b in campaign.batches:
            bar.set_description(b.label)
            for attempt in range(1, RETRIES + 2):
                try:
                    outcomes[b.index] = task(b.spec(), device)
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
        try:
            ray.init(address=address, include_dashboard=False, logging_level=logging.WARNING, log_to_driver=False,
                     runtime_env={"working_dir": workdir})
        except Exception as err:  # Ray raises ConnectionError, RuntimeError, ValueError …
            shutil.rmtree(workdir, ignore_errors=True)
            raise CampaignError(f"cannot start or reach the Ray cluster{f' at {address}' if address else ''}: "
                                f"{_describe_error(err)}") from None
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


# ---------------------------------------------------------------------- outputs
def campaign_meta(result: CampaignResult) -> dict:
    """campaign.json's ``meta``: provenance (:func:`~warptan.meta.run_meta`), engine, the devices the tasks ran on,
    the cluster, wall time, the campaign, and per task where and when it ran."""
    from warptan.meta import run_meta

    local_cuda = result.engine == "local" and result.device.startswith("cuda")
    meta = run_meta([result.device] if local_cuda else ["cpu"], engine=result.engine, wall_s=result.wall_s,
                    campaign=result.campaign.describe(), cluster=result.cluster,
                    batches={"done": len(result.rows), "failed": len(result.failures)}, tasks=result.tasks)
    if result.tasks:  # where the batches really ran (Ray workers, possibly other hosts)
        meta["devices"] = {f"{t['host']} {t['device']}" + (f" (CUDA_VISIBLE_DEVICES={t['cuda_visible_devices']})"
                                                           if t["device"].startswith("cuda") and
                                                           t.get("cuda_visible_devices") else ""): t["device_name"]
                           for t in result.tasks}
        gpus = sorted({t["device_name"] for t in result.tasks if t["device"].startswith("cuda")})
        if gpus:
            meta.setdefault("gpu", {})["names"] = gpus
    return meta


def markdown(result: CampaignResult) -> str:
    """The rows (and failures) as Markdown."""
    from warptan.sim.report import _fmt, _pct

    params = list(result.campaign.sweep)
    lines = [f"# {result.campaign.title}", "",
             f"{len(result.rows)} batch(es) of {len(result.campaign.batches)} done, engine {result.engine}, device "
             f"{result.device}, wall time {result.wall_s:.1f} s. RMSE x / y / z = north / east / down in metres, mean "
             "± 95 % interval over the seeds; \"after convergence\" counts from `filter.converged_after_s` "
             "(– when the flight is shorter); 3σ coverage after convergence.", ""]
    if result.campaign.overrides:
        lines += ["Every run: " + ", ".join(f"`{k} = {v}`" for k, v in result.campaign.overrides.items()), ""]
    lines += ["| scenario | " + "".join(f"{p} | " for p in params) + "seeds | RMSE x / y / z (m), whole run | "
              "after convergence | 3σ coverage N/E/D |",
              "|---|" + "---|" * len(params) + "---|---|---|---|"]
    for r in result.rows:
        lines.append(f"| {r['scenario']} | " + "".join(f"{r['params'][p]} | " for p in params) +
                     f"{len(r['seeds'])} | {_fmt(r['rmse_m'], r['rmse_ci95_m'])} | "
                     f"{_fmt(r['rmse_converged_m'], r['rmse_converged_ci95_m'])} | {_pct(r['coverage_3sigma'])} |")
    if result.failures:
        lines += ["", f"## Failed batches ({len(result.failures)})", ""]
        lines += [f"- {f['scenario']} " + " ".join(f"{k}={v}" for k, v in f["params"].items()) +
                  f" (seeds {f['seeds'][0]}…{f['seeds'][-1]}, {f['attempts']} attempts): {f['error']}"
                  for f in result.failures]
    return "\n".join(lines) + "\n"


def _rmse_3d(row: dict, key: str) -> tuple[float, float]:
    """Mean and 95 % half-width over the seeds of the 3-D RMSE √(x² + y² + z²) of ``key``."""
    per_seed = np.array([np.sqrt(np.sum(np.square(s[key]))) for s in row["per_seed"]], dtype=np.float64)
    mean, half = ci95(per_seed)
    return float(mean), float(half)


def plot_parameter(result: CampaignResult, param: str, path: str | os.PathLike) -> str:
    """One PNG for one swept parameter: 3-D RMSE (after convergence; whole run when no flight was long enough)
    with its 95 % interval against the parameter's values, one line per scenario and combination of the other
    swept parameters. A numeric parameter is on a numeric axis (logarithmic when its values span ≥ 10×)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = result.campaign.sweep[param]
    numeric = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
    key = "rmse_converged_m" if any(np.isfinite(_rmse_3d(r, "rmse_converged_m")[0]) for r in result.rows) \
        else "rmse_m"
    groups: dict[tuple, list] = {}
    for r in result.rows:
        rest = tuple((k, v) for k, v in r["params"].items() if k != param)
        groups.setdefault((r["scenario"], rest), []).append(r)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for (scenario, rest), rows in groups.items():
        rows = sorted(rows, key=lambda r: values.index(r["params"][param]))
        x = [r["params"][param] if numeric else values.index(r["params"][param]) for r in rows]
        stats = [_rmse_3d(r, key) for r in rows]
        label = scenario + "".join(f", {k}={v}" for k, v in rest)
        ax.errorbar(x, [m for m, _ in stats], yerr=[0.0 if not np.isfinite(h) else h for _, h in stats],
                    marker="o", capsize=3, label=label)
    if numeric and min(values) > 0 and max(values) >= 10 * min(values):
        ax.set_xscale("log")
    if not numeric:
        ax.set_xticks(range(len(values)), [str(v) for v in values])
    ax.set_xlabel(param)
    ax.set_ylabel("3-D RMSE" + (" after convergence" if key == "rmse_converged_m" else ", whole run") +
                  " (m), 95 % interval")
    ax.set_title(f"{result.campaign.title}: {param}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return os.fspath(path)


def write_campaign(result: CampaignResult, out_dir, plots: bool = True) -> dict:
    """Write ``campaign.json`` (strict JSON: ``meta``, ``rows``, ``failures``), ``campaign.md`` and one plot per swept
    parameter (``campaign_<param>.png``, with matplotlib) into ``out_dir`` as one whole (see
    :class:`~warptan.outputs.OutputFolder`). Returns the Markdown and the files written."""
    from warptan.outputs import OutputFolder, write_json

    folder = out_dir if isinstance(out_dir, OutputFolder) else OutputFolder(out_dir)
    if plots:
        try:
            import matplotlib  # noqa: F401
        except ModuleNotFoundError:
            plots = False
    table = markdown(result)
    names = ["campaign.json", "campaign.md"]
    with folder as out:
        write_json(out / "campaign.json", {"meta": campaign_meta(result), "rows": result.rows,
                                           "failures": result.failures})
        (out / "campaign.md").write_text(table)
        if plots and result.rows:
            for param in result.campaign.sweep:
                name = f"campaign_{param}.png"
                plot_parameter(result, param, out / name)
                names.append(name)
    return {"table": table, "files": [str(folder.path / n) for n in names], "plots": plots}
