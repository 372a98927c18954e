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
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

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
        (scenario, truth terrain, flight). Raises :class:`CampaignError` listing every failing batch."""
        problems, plans = [], []
        for i, b in enumerate(self.batches):
            try:
                source = f"campaign {self.source} [overrides]/[sweep]"
                scenario = load_config(b.scenario, overrides_from=source, **b.overrides)
                self.batches[i] = b = replace(b, batched=not per_seed_maps(scenario))
                plans.append(prepare(b.scenario, seeds=list(b.seeds), device=device, batched=b.batched,
                                     overrides_from=source, **b.overrides))
            except (ValueError, OSError) as err:
                problems.append(f"{b.label}: " + " ".join(str(err).split()))
        if problems:
            shown = problems[:20] + ([f"… and {len(problems) - 20} more"] if len(problems) > 20 else [])
            raise CampaignError(f"{len(problems)} of {len(self.batches)} batch(es) of campaign {self.source} cannot "
                                "run:\n  " + "\n  ".join(shown))
        ids = {}
        for b, (scenario, _, _) in zip(self.batches, plans, strict=True):
            ids.setdefault(scenario.id, set()).add(b.scenario)
        clash = sorted(i for i, names in ids.items() if len(names) > 1)
        if clash:
            raise CampaignError(f"campaign {self.source}: two scenarios have the id {', '.join(clash)} (rows are kept "
                                "by id); give one of the files another id")
        return plans

    def inputs(self) -> list[str]:
        """What the campaign reads besides itself: scenario files, and the DEMs (terrain specs: a name, a path, a path
        with its #band=N) named in [overrides] or [sweep]."""
        files = [s for s in self.scenarios if s not in SCENARIO_IDS]
        for key in PATH_KEYWORDS:
            values = [self.overrides.get(key), *self.sweep.get(key, [])]
            files += [v for v in values if isinstance(v, str) and v]  # (a DEM with its #band=N too)
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
        head, sep, band = value.rpartition("#band=")
        file = head if sep else value  # (a raster's band: the file is relative, the suffix kept)
        candidate = base / file
        if candidate.exists():
            return str(candidate.resolve()) + (f"#band={band}" if sep else "")
    return value
