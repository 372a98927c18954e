"""A campaign's outputs: ``campaign.json`` (rows, failures, provenance), ``campaign.md`` and one plot per swept
parameter (:func:`write_campaign`)."""

from __future__ import annotations

import os

import numpy as np

from warptan.sim.campaign_run import CampaignResult


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


def _rmse_3d(row: dict, key: str) -> tuple[float, float, float]:
    """Mean over the seeds of the 3-D RMSE √(x² + y² + z²) of ``key`` and its 95 % interval: the bootstrap percentile
    interval of the mean (2000 resamples of the seeds, a fixed generator), which stays on the positive side where a
    symmetric t interval of a few skewed seeds reached below zero; NaN without a finite seed, the mean itself for
    one seed."""
    per_seed = np.array([np.sqrt(np.sum(np.square(s[key]))) for s in row["per_seed"]], dtype=np.float64)
    per_seed = per_seed[np.isfinite(per_seed)]
    if per_seed.size == 0:
        return float("nan"), float("nan"), float("nan")
    mean = float(per_seed.mean())
    if per_seed.size == 1:
        return mean, mean, mean
    means = per_seed[np.random.default_rng(0).integers(0, per_seed.size, (2000, per_seed.size))].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return mean, float(lo), float(hi)


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
    points = []
    for (scenario, rest), rows in groups.items():
        rows = sorted(rows, key=lambda r: values.index(r["params"][param]))
        x = [r["params"][param] if numeric else values.index(r["params"][param]) for r in rows]
        stats = [_rmse_3d(r, key) for r in rows]
        label = scenario + "".join(f", {k}={v}" for k, v in rest)
        mean = np.array([m for m, _, _ in stats])
        below = np.nan_to_num(mean - np.array([lo for _, lo, _ in stats]))
        above = np.nan_to_num(np.array([hi for _, _, hi in stats]) - mean)
        line = ax.errorbar(x, mean, yerr=[below, above], marker="o", capsize=3, label=label)[0]
        points += [(xi, m, line.get_color()) for xi, m in zip(x, mean, strict=True) if np.isfinite(m)]
    # the number at each point (a row far below another reads as 0), but not over a number already written there
    top, written = max((m for _, m, _ in points), default=1.0), []
    for xi, m, colour in sorted(points, key=lambda p: -p[1]):
        if all(xi != xw or abs(m - mw) > 0.06 * top for xw, mw in written):
            ax.annotate(f"{m:.3g}", (xi, m), textcoords="offset points", xytext=(5, 4), fontsize=7, color=colour)
            written.append((xi, m))
    if numeric and min(values) > 0 and max(values) >= 10 * min(values):
        ax.set_xscale("log")
    if not numeric:
        ax.set_xticks(range(len(values)), [str(v) for v in values])
    ax.set_xlabel(param)
    ax.set_ylabel("3-D RMSE" + (" after convergence" if key == "rmse_converged_m" else ", whole run") + " (m)")
    seeds = sorted({len(r.get("per_seed", [])) for r in result.rows})
    ax.set_title(f"{result.campaign.title}: {param}\nmean over {'/'.join(map(str, seeds))} seeds, bars: 95 % "
                 "bootstrap interval of the mean", fontsize=10)
    ax.set_ylim(bottom=0.0)
    ax.margins(x=0.08)  # (room for the last point's number)
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
