"""Monte-Carlo summaries of scenario runs: results.json, a Markdown table next to the paper, and PNG plots.

RMSE per axis is reported as mean ± 95 % interval over seeds (Student t, ``t_{0.975, n-1} s / √n``),
over the whole run and after convergence (``filter.converged_after_s``). Comparisons between scenarios are
decided by :func:`compare_less` (one-sided Welch t tests on per-seed values) and :func:`ratio_within`
(a seeded bootstrap interval of the ratio of means): each verdict is ``holds``, ``does not hold`` or
``inconclusive``, with the p-value or interval behind it. matplotlib is imported only by the plotting
functions; no SciPy (the Student t distribution is computed here, checked in the tests against tabulated
values).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from warptan.meta import run_meta
from warptan.outputs import OutputFolder, write_json

HOLDS, FAILS, INCONCLUSIVE = "holds", "does not hold", "inconclusive"
"""Verdicts of a statistical claim."""
ALPHA = 0.05
"""Significance level of every verdict (one-sided tests; 95 % intervals)."""


def _betacf(a: float, b: float, x: float) -> float:
    """Continued fraction of the regularised incomplete beta function (modified Lentz)."""
    tiny, qab, qap, qam = 1e-300, a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 400):
        m2 = 2 * m
        for num in (m * (b - m) * x / ((qam + m2) * (a + m2)), -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))):
            d = 1.0 + num * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + num / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def _betainc(a: float, b: float, x: float) -> float:
    """Regularised incomplete beta function I_x(a, b), 0 ≤ x ≤ 1."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _betacf(a, b, x) / a
    return 1.0 - front * _betacf(b, a, 1.0 - x) / b


def t_sf(t: float, dof: float) -> float:
    """P(T > t) for Student's t with ``dof`` degrees of freedom (real dof > 0, as Welch's)."""
    if not math.isfinite(t):
        return 0.0 if t > 0 else 1.0
    tail = 0.5 * _betainc(0.5 * dof, 0.5, dof / (dof + t * t))
    return tail if t >= 0 else 1.0 - tail


def t_ppf(q: float, dof: float) -> float:
    """The q-quantile of Student's t (bisection on :func:`t_sf`, 1e-10 relative)."""
    if not 0.0 < q < 1.0:
        raise ValueError(f"quantile must be in (0, 1), got {q}")
    if q < 0.5:
        return -t_ppf(1.0 - q, dof)
    lo, hi = 0.0, 1.0
    while t_sf(hi, dof) > 1.0 - q:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if t_sf(mid, dof) > 1.0 - q else (lo, mid)
        if hi - lo < 1e-10 * hi:
            break
    return 0.5 * (lo + hi)


def ci95(values) -> tuple[np.ndarray, np.ndarray]:
    """Mean and half-width of the 95 % interval of the mean over the first axis (NaN width for one value)."""
    v = np.asarray(values, dtype=np.float64)
    mean = v.mean(axis=0)
    n = len(v)
    if n < 2:
        return mean, np.full_like(mean, np.nan)
    return mean, t_ppf(0.975, n - 1) * v.std(axis=0, ddof=1) / math.sqrt(n)


def welch_less(a, b) -> float:
    """One-sided Welch t test of mean(a) < mean(b) on independent samples: the p-value (small: a is smaller).
    Needs ≥ 2 values in each; equal constant samples give 0.5."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if len(a) < 2 or len(b) < 2:
        raise ValueError(f"Welch's t test needs at least 2 values per sample, got {len(a)} and {len(b)}")
    va, vb = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    diff = b.mean() - a.mean()
    if va + vb == 0.0:
        return 0.5 if diff == 0 else (0.0 if diff > 0 else 1.0)
    dof = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
    return float(t_sf(diff / math.sqrt(va + vb), dof))


def compare_less(a, b, alpha: float = ALPHA) -> tuple[str, float]:
    """Verdict on "mean(a) < mean(b)": holds when the one-sided Welch p-value is < alpha, does not hold when the
    opposite one-sided test is, else inconclusive. Returns (verdict, p-value of a < b)."""
    p = welch_less(a, b)
    if p < alpha:
        return HOLDS, p
    if 1.0 - p < alpha:
        return FAILS, p
    return INCONCLUSIVE, p


def bootstrap_ratio(a, b, resamples: int = 10_000, seed: int = 0) -> tuple[float, float, float]:
    """mean(a) / mean(b) and its 95 % percentile-bootstrap interval (seeds resampled independently per sample,
    seeded: the same inputs give the same interval)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    rng = np.random.default_rng(seed)
    ra = a[rng.integers(0, len(a), (resamples, len(a)))].mean(axis=1)
    rb = b[rng.integers(0, len(b), (resamples, len(b)))].mean(axis=1)
    lo, hi = np.percentile(ra / rb, [2.5, 97.5])
    return float(a.mean() / b.mean()), float(lo), float(hi)


def ratio_within(a, b, factor: float) -> tuple[str, tuple[float, float, float]]:
    """Verdict on "mean(a) and mean(b) are within ``factor`` of each other": holds when the bootstrap 95 % interval
    of the ratio lies inside [1/factor, factor], does not hold when it lies wholly outside, else inconclusive."""
    r, lo, hi = bootstrap_ratio(a, b)
    if 1.0 / factor <= lo and hi <= factor:
        return HOLDS, (r, lo, hi)
    if hi < 1.0 / factor or lo > factor:
        return FAILS, (r, lo, hi)
    return INCONCLUSIVE, (r, lo, hi)


def combine(verdicts) -> str:
    """All parts hold → holds; any part fails → does not hold; else inconclusive."""
    verdicts = list(verdicts)
    if verdicts and all(v == HOLDS for v in verdicts):
        return HOLDS
    return FAILS if FAILS in verdicts else INCONCLUSIVE


def aggregate(results) -> dict[str, dict]:
    """Per scenario: seeds, RMSE mean ± CI (whole and converged), the paper's values, coverage, timings."""
    by_id: dict[str, list] = {}
    for r in results:
        by_id.setdefault(r.scenario, []).append(r)
    out = {}
    for sid, runs in by_id.items():
        rm, rh = ci95([r.rmse for r in runs])
        cm, ch = ci95([r.rmse_converged for r in runs])
        cfg = runs[0].config
        out[sid] = {
            "seeds": [r.seed for r in runs], "terrain": runs[0].terrain, "device": runs[0].device,
            "model": cfg.sensor.model, "backend": cfg.sensor.backend, "surface": cfg.sensor.surface,
            "likelihood": cfg.likelihood.kind, "imu": cfg.imu.grade, "bank_deg": cfg.flight.bank_deg,
            "altitude_rule": cfg.flight.altitude_rule, "particles": cfg.filter.particles,
            "meas_rate_hz": cfg.sensor.rate_hz, "use_baro": cfg.sensor.use_baro,
            "rmse_mean_m": rm.tolist(), "rmse_ci95_m": rh.tolist(),
            "rmse_converged_mean_m": cm.tolist(), "rmse_converged_ci95_m": ch.tolist(),
            "paper_rmse_m": list(cfg.paper_rmse_m),
            "rmse_horizontal_converged_mean_m": float(np.mean([np.hypot(*r.rmse_converged[:2]) for r in runs])),
            "pcrb_converged_mean_m": float(np.mean([getattr(r, "pcrb_converged_m", np.nan) for r in runs])),
            "coverage_3sigma_mean": np.mean([r.run.coverage(cfg.filter.converged_after_s) for r in runs],
                                            axis=0).tolist(),
            **_linear_aggregate([r.linear_summary() for r in runs]),
            **_update_counts(runs),
            "runs_declared_unconverged": sum(declared_unconverged(r.run, cfg.filter.converged_after_s)
                                             for r in runs),
            "update_ms_median": 1e3 * float(np.median(np.concatenate([r.run.update_time_s[1:] for r in runs]))),
            "wall_s_mean": float(np.mean([r.wall_s for r in runs])),
        }
    return out


def _update_counts(runs) -> dict:
    """Updates over the seeds, those skipped (the map could not predict the scan), and the runs that used none."""
    counts = [update_counts(r.run) for r in runs]
    return {"updates": sum(c[0] for c in counts), "skipped_updates": sum(c[1] for c in counts),
            "runs_without_any_update": sum(c[0] > 0 and c[2] == 0 for c in counts)}


UNCONVERGED_3SIGMA_M = 50.0
"""A run whose reported horizontal 3σ (the larger of north and east), RMS over the epochs after the convergence
time, exceeds this many metres has declared itself unconverged: it does not claim to know its position to the
accuracy a lost seed misses (the studies call a seed lost at a horizontal RMSE over 50 m). An altimeter over
mismatched or flat ground is the usual case (its bounds stay honest, hundreds of metres wide)."""


def declared_unconverged(run, after_s: float, limit_m: float = UNCONVERGED_3SIGMA_M) -> bool:
    """True when the run's own horizontal 3σ, RMS over ``t ≥ after_s``, exceeds ``limit_m`` (see
    :data:`UNCONVERGED_3SIGMA_M`); False for a run that ended before ``after_s``."""
    sel = np.asarray(run.t_s) >= after_s
    if not sel.any():
        return False
    horizontal = np.max(np.asarray(run.sigma3_pos)[sel, :2], axis=1)
    return bool(np.sqrt(np.mean(horizontal**2)) > limit_m)


def update_counts(run) -> tuple[int, int, int]:
    """(updates, skipped, used) of a :class:`~warptan.sim.runner.FilterRun`: used = neither skipped nor without a valid
    received point. A run without the flags (no history of them) counts every update as used."""
    skipped = np.asarray(getattr(run, "skipped", np.zeros(len(run.t_s), dtype=bool)), dtype=bool)[1:]
    empty = np.asarray(getattr(run, "all_points_invalid", np.zeros(len(run.t_s), dtype=bool)), dtype=bool)[1:]
    return len(skipped), int(skipped.sum()), int((~skipped & ~empty).sum())


def _linear_aggregate(summaries: list[dict]) -> dict:
    """Attitude and bias numbers over seeds: RMS over seeds of the per-run RMSE (attitude, deg; gyro bias after
    60 s, deg/h), pooled 3σ coverage of the attitude, mean σ/RMSE ratios (position and attitude)."""
    def col(key):
        return np.array([s[key] for s in summaries], dtype=np.float64)

    def nanmean(values):  # an axis with no finite value (no error to divide by) stays NaN, without a warning
        finite = np.isfinite(values)
        total = np.where(finite, values, 0.0).sum(axis=0)
        count = finite.sum(axis=0)
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)

    return {
        "attitude_rmse_deg": np.sqrt(np.mean(col("attitude_rmse_converged_deg") ** 2, axis=0)).tolist(),
        "coverage_3sigma_attitude_mean": np.mean(col("coverage_3sigma_attitude"), axis=0).tolist(),
        "gyro_bias_rmse_after_60s_dph": np.sqrt(np.mean(col("gyro_bias_rmse_after_60s_dph") ** 2, axis=0)).tolist(),
        "sigma_over_rmse_pos_mean": nanmean(col("sigma_over_rmse_pos")).tolist(),
        "sigma_over_rmse_attitude_mean": nanmean(col("sigma_over_rmse_attitude")).tolist(),
    }


def attitude_table(agg: dict[str, dict]) -> str:
    """Attitude, gyro-bias and bound-honesty numbers as a Markdown table."""
    lines = [
        "| id | seeds | attitude RMSE roll / pitch / yaw (°) | 3σ coverage attitude | gyro-bias RMSE after 60 s (°/h) "
        "| mean σ / RMSE, position N/E/D | mean σ / RMSE, attitude |",
        "|---|---|---|---|---|---|---|",
    ]
    for sid in sorted(agg, key=lambda s: int(s[1:]) if s[1:].isdigit() else 99):
        a = agg[sid]
        lines.append(
            f"| {sid} | {len(a['seeds'])} | {' / '.join(f'{v:.4f}' for v in a['attitude_rmse_deg'])} | "
            f"{_pct(a['coverage_3sigma_attitude_mean'])} | "
            f"{' / '.join(f'{v:.2f}' for v in a['gyro_bias_rmse_after_60s_dph'])} | "
            f"{' / '.join(f'{v:.2f}' for v in a['sigma_over_rmse_pos_mean'])} | "
            f"{' / '.join(f'{v:.2f}' for v in a['sigma_over_rmse_attitude_mean'])} |")
    return "\n".join(lines)


def _fmt(mean, half) -> str:
    """``m±h`` per axis; ``m`` alone without an interval, "–" for an undefined value (e.g. a run shorter than
    ``converged_after_s``)."""
    return " / ".join("–" if not np.isfinite(m) else f"{m:.2f}" if not np.isfinite(h) else f"{m:.2f}±{h:.2f}"
                      for m, h in zip(mean, half, strict=True))


def _pct(values) -> str:
    return " / ".join("–" if not np.isfinite(c) else f"{100 * c:.0f}%" for c in values)


def markdown_table(agg: dict[str, dict]) -> str:
    """The results as a Markdown table (RMSE x / y / z = north / east / down, m)."""
    lines = [
        "| id | terrain | IMU | bank | alt | model | seeds | RMSE x / y / z (m), whole run | after convergence "
        "| horizontal RMSE / bound (m) | paper | 3σ coverage N/E/D |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for sid in sorted(agg, key=lambda s: int(s[1:]) if s[1:].isdigit() else 99):
        a = agg[sid]
        model = a["model"] + (f" ({a['backend']})" if a["model"] == "raycast" else "")
        model += "" if a["model"] != "altimeter" else (" + baro" if a["use_baro"] else ", no baro")
        base, plus, world = a["terrain"].partition(" + ")  # a world made from the DEM: "DEM + world(...)"
        terrain = (Path(base).name if not base.startswith("synthetic") else base) + plus + world
        lines.append(
            f"| {sid} | {terrain} | {a['imu']} | {a['bank_deg']:g}° | {a['altitude_rule']} | {model} | "
            f"{len(a['seeds'])} | {_fmt(a['rmse_mean_m'], a['rmse_ci95_m'])} | "
            f"{_fmt(a['rmse_converged_mean_m'], a['rmse_converged_ci95_m'])} | "
            f"{_bound_cell(a)} | "
            f"{' / '.join(f'{v:g}' for v in a['paper_rmse_m'])} | "
            f"{_pct(a['coverage_3sigma_mean'])} |")
    return "\n".join(lines)


def _bound_cell(a: dict) -> str:
    """The converged horizontal RMSE (mean over the seeds) beside the flight's posterior Cramér–Rao bound."""
    rmse, bound = a.get("rmse_horizontal_converged_mean_m", np.nan), a.get("pcrb_converged_mean_m", np.nan)
    if not np.isfinite(rmse):
        return "–"
    return f"{rmse:.3g} / {bound:.3g}" if np.isfinite(bound) else f"{rmse:.3g} / –"


def hillshade(heights: np.ndarray, dn: float, de: float, azimuth_deg: float = 315.0, altitude_deg: float = 45.0):
    """Lambertian hillshade in [0, 1] of a (rows north, cols east) height grid (NaN stays NaN)."""
    gn, ge = np.gradient(heights, dn, de)
    slope = np.arctan(np.hypot(gn, ge))
    aspect = np.arctan2(-ge, gn)
    az, alt = math.radians(azimuth_deg), math.radians(altitude_deg)
    shade = np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect)
    return np.clip(shade, 0.0, 1.0)


def _p95(values) -> float:
    """95th percentile of |values| over the finite ones (NaN when there is none)."""
    v = np.abs(np.asarray(values, dtype=np.float64))
    v = v[np.isfinite(v)]
    return float(np.percentile(v, 95)) if v.size else float("nan")


def _horizontal_error_panel(ax, run, converged_after_s: float, truth: bool, title: str) -> None:
    """The track's error scale: the horizontal error along the distance flown (at a map's scale the estimate hides
    under the truth), with the filter's horizontal 3σ and the INS's error (clipped); ``title`` its number."""
    dist_km = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(run.truth_pos[:, :2], axis=0), axis=1))] / 1e3 \
        if truth else run.t_s
    sigma = np.hypot(run.sigma3_pos[:, 0], run.sigma3_pos[:, 1])  # 3 DRMS: 3 √(σ_N² + σ_E²)
    ax.fill_between(dist_km, 0.0, sigma, color="b", alpha=0.15, label="3 DRMS the filter reports (3√(σN²+σE²))")
    if truth:
        ax.plot(dist_km, np.hypot(run.error[:, 0], run.error[:, 1]), "c-", lw=1.2, label="estimate error")
        ins = np.hypot(*(run.ins_pos - run.truth_pos)[:, :2].T)
        converged = np.searchsorted(run.t_s, converged_after_s)
        if converged < len(dist_km):
            ax.axvline(dist_km[converged], color="gray", lw=0.8, ls="-.",
                       label=f"convergence ({converged_after_s:g} s)")
        lim = max(2.0, 1.5 * _p95(np.hypot(run.error[:, 0], run.error[:, 1])))
        off = f" (off scale: {np.nanmin(ins):.0f}–{np.nanmax(ins):.0f} m)" if np.nanmax(ins) > lim else ""
        ax.plot(dist_km, ins, "r--", lw=0.8, label="INS only" + off)
    else:
        lim = max(2.0, 1.2 * _p95(sigma))
    ax.set_ylim(0.0, lim)
    ax.set_xlabel("distance flown (km)" if truth else "time (s)")
    ax.set_ylabel("horizontal error (m)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=7)


def plot_run(result, terrain, out_prefix: str | os.PathLike) -> list[str]:
    """Two PNGs for one run: ``_track.png`` (truth, INS only, estimate over a hillshade) and ``_errors.png``
    (error per axis with ±3σ, and ESS). Returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = result.run
    truth = bool(np.isfinite(run.truth_pos).any())  # a recorded flight may have none: estimate and 3σ only
    prefix = os.fspath(out_prefix)
    pad = 2000.0
    pts = np.concatenate([run.truth_pos[:, :2], run.ins_pos[:, :2], run.est_pos[:, :2]])
    n_lo, e_lo = np.nanmin(pts, axis=0) - pad
    n_hi, e_hi = np.nanmax(pts, axis=0) + pad
    grow = 0.5 * max(0.0, 0.75 * (n_hi - n_lo) - (e_hi - e_lo))  # a straight leg's map no narrower than 3/4 its length
    e_lo, e_hi = e_lo - grow, e_hi + grow
    grow = 0.5 * max(0.0, 0.75 * (e_hi - e_lo) - (n_hi - n_lo))
    n_lo, n_hi = n_lo - grow, n_hi + grow
    rows, cols = terrain.shape
    i0 = int(np.clip((n_lo - terrain.n0) / terrain.dn, 0, rows - 1))
    i1 = int(np.clip((n_hi - terrain.n0) / terrain.dn, 0, rows - 1)) + 1
    j0 = int(np.clip((e_lo - terrain.e0) / terrain.de, 0, cols - 1))
    j1 = int(np.clip((e_hi - terrain.e0) / terrain.de, 0, cols - 1)) + 1
    crop = terrain.heights_m[i0:i1, j0:j1]
    extent = [terrain.e0 + j0 * terrain.de, terrain.e0 + (j1 - 1) * terrain.de,
              terrain.n0 + i0 * terrain.dn, terrain.n0 + (i1 - 1) * terrain.dn]
    fig, (ax, along) = plt.subplots(2, 1, figsize=(7, 9.2), gridspec_kw={"height_ratios": [3.2, 1]})
    ax.imshow(hillshade(crop, terrain.dn, terrain.de), origin="lower", extent=extent, cmap="gray", alpha=0.9)
    heights = ax.imshow(crop, origin="lower", extent=extent, cmap="terrain", alpha=0.35)
    fig.colorbar(heights, ax=ax, shrink=0.7, label="terrain height (m)")
    ax.plot(run.truth_pos[:, 1], run.truth_pos[:, 0], "k-", lw=2, label="truth")
    ax.plot(run.ins_pos[:, 1], run.ins_pos[:, 0], "r--", lw=1.2, label="INS only (from the initial error)")
    ax.plot(run.est_pos[:, 1], run.est_pos[:, 0], "c-", lw=1.2, label="estimate")
    ax.plot(run.truth_pos[0, 1], run.truth_pos[0, 0], "ko", label="start")
    if len(run.t_s) > 2:  # the direction of flight, halfway along the truth
        k = len(run.t_s) // 2
        ax.annotate("", xy=(run.truth_pos[k + 1, 1], run.truth_pos[k + 1, 0]),
                    xytext=(run.truth_pos[k - 1, 1], run.truth_pos[k - 1, 0]),
                    arrowprops={"arrowstyle": "-|>", "color": "k", "lw": 1.5, "mutation_scale": 18})
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    where = Path(result.terrain).name if os.path.exists(str(result.terrain)) else str(result.terrain)
    ax.set_title(f"{result.scenario} seed {result.seed}: {where}".replace(" + ", "\n+ "), fontsize=10)
    ax.legend(loc="best", fontsize=8, framealpha=0.85)
    ax.set_aspect("equal")
    after = result.config.filter.converged_after_s
    horizontal = [float(np.hypot(*rmse[:2])) for rmse in (result.rmse_converged, result.rmse)]
    _horizontal_error_panel(along, run, after, truth,
                            f"horizontal RMSE after {after:g} s {horizontal[0]:.2f} m (whole run {horizontal[1]:.2f} m)"
                            if truth else "horizontal 3 DRMS the filter reports (the flight has no truth)")
    fig.tight_layout()
    track = f"{prefix}_track.png"
    fig.savefig(track, dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(5, 1, figsize=(8, 11), sharex=True)
    settled = run.t_s >= after  # (the scales are read after convergence: the first seconds' metres leave them)
    settled = settled if settled.any() else np.ones_like(settled)
    for k, name in enumerate(("north", "east", "down")):
        ax = axes[k]
        ax.plot(run.t_s, run.error[:, k], "b-", lw=1, label="estimate − truth")
        ax.fill_between(run.t_s, -run.sigma3_pos[:, k], run.sigma3_pos[:, k], color="b", alpha=0.15,
                        label="±3σ the filter reports")
        ax.plot(run.t_s, (run.ins_pos - run.truth_pos)[:, k], "r--", lw=0.8, label="INS only (may leave the scale)")
        bound = getattr(result, "pcrb_sigma_m", None)
        if bound is not None:  # the flight's posterior Cramér–Rao bound, ±3σ
            ax.plot(run.t_s, 3 * bound[:, k], "k--", lw=0.9, label="±3σ best possible (PCRB)")
            ax.plot(run.t_s, -3 * bound[:, k], "k--", lw=0.9)
        lim = max(0.5, 1.2 * _p95(run.sigma3_pos[settled, k]), 1.5 * _p95(run.error[settled, k]) if truth else 0.0)
        ax.set_ylim(-lim, lim)
        ax.set_ylabel(f"{name} error (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    for k, (name, colour) in enumerate((("roll", "b"), ("pitch", "m"), ("yaw", "g"))):
        axes[3].plot(run.t_s, np.degrees(run.lin_err[:, 3 + k]), f"{colour}-", lw=1, label=name)
        axes[3].plot(run.t_s, np.degrees(run.sigma3_lin[:, 3 + k]), f"{colour}:", lw=0.8)
        axes[3].plot(run.t_s, -np.degrees(run.sigma3_lin[:, 3 + k]), f"{colour}:", lw=0.8)
    att_lim = (1.5 * _p95(np.degrees(run.lin_err[:, 3:6])) if truth else 1.2 * _p95(np.degrees(run.sigma3_lin[:, 3:6])))
    att_lim = att_lim + 1e-3 if np.isfinite(att_lim) else 1.0
    axes[3].set_ylim(-att_lim, att_lim)
    axes[3].set_ylabel("attitude error (°), ±3σ")
    axes[3].legend(loc="upper right", fontsize=8)
    axes[3].grid(alpha=0.3)
    axes[4].plot(run.t_s, run.ess, "g-", lw=1)
    axes[4].axhline(0.5 * run.n_particles, color="gray", ls=":", lw=1, label=f"N/2 = {0.5 * run.n_particles:g}")
    axes[4].set_ylabel("ESS (particles)")
    axes[4].legend(loc="upper right", fontsize=8, title="effective sample size", title_fontsize=8)
    axes[4].set_xlabel("time (s)")
    axes[0].set_title(f"{result.scenario} seed {result.seed}: RMSE N/E/D after {after:g} s "
                      f"{_fmt(result.rmse_converged, [np.nan] * 3)} m (whole run {_fmt(result.rmse, [np.nan] * 3)} m)",
                      fontsize=10)
    for ax in axes[:4]:
        ax.axvline(after, color="gray", lw=0.8, ls="-.")
    fig.tight_layout()
    errors = f"{prefix}_errors.png"
    fig.savefig(errors, dpi=110)
    plt.close(fig)
    return [track, errors]


def write_outputs(results, out_dir, terrains: dict, plots: bool = True, trajectories: bool = False,
                  title: str = "warptan scenario results") -> dict[str, object]:
    """Write ``results.json`` (strict JSON: an undefined number is null), ``results.md`` and (first seed of each
    scenario) the plots as one whole into ``out_dir`` (a path or a checked :class:`~warptan.outputs.OutputFolder`):
    written beside it and swapped into place when complete, so the folder never mixes two runs. ``trajectories``:
    also each run's trajectory file (:func:`write_trajectory`)."""
    folder = out_dir if isinstance(out_dir, OutputFolder) else OutputFolder(out_dir)
    agg = aggregate(results)
    table = markdown_table(agg)
    if plots:
        try:
            import matplotlib  # noqa: F401
        except ModuleNotFoundError:
            plots = False
    names = ["results.json", "results.md"]
    with folder as out:
        write_json(out / "results.json", {"meta": run_meta(sorted({r.device for r in results}) or ["cpu"]),
                                          "scenarios": agg, "runs": [r.summary() for r in results]})
        (out / "results.md").write_text(
            f"# {title}\n\nRMSE x / y / z = north / east / down in metres, mean ± 95 % interval "
            "over seeds; \"after convergence\" counts from `filter.converged_after_s`.\n\n" + table + "\n\n"
            "## Attitude, gyro bias and the honesty of the bounds (after convergence)\n\nAttitude error = "
            "Log(q_true⁻¹ q_est) in body axes (roll / pitch / yaw); RMSE pooled over seeds as the RMS of the runs' "
            "RMSE; σ / RMSE ≈ 1 means the reported 3σ neither lies nor balloons.\n\n" + attitude_table(agg) + "\n")
        if trajectories:

            for r in results:
                names += write_trajectory(r, terrains[r.scenario], out)
        if plots:
            done = set()
            for r in results:
                if r.scenario not in done:
                    done.add(r.scenario)
                    prefix = out / f"{r.scenario}_seed{r.seed}"
                    names += [Path(p).name for p in plot_run(r, terrains[r.scenario], prefix)]
    written = [str(folder.path / n) for n in names]
    return {"aggregate": agg, "table": table, "files": written, "plots": plots}


def write_trajectory(result, terrain, folder: Path) -> list[str]:
    """``<id>_seed<s>_trajectory.csv`` (time, NED estimate and 3σ, truth when known, and latitude/longitude/altitude
    when the DEM has a CRS) and, with a CRS, ``..._trajectory.geojson`` (a LineString of the estimate, lon/lat/alt:
    QGIS and Google Earth load it). Returns the file names."""
    run = result.run
    stem = f"{result.scenario}_seed{result.seed}_trajectory"
    cols = {"t_s": run.t_s, "north_m": run.est_pos[:, 0], "east_m": run.est_pos[:, 1], "down_m": run.est_pos[:, 2],
            "sigma3_north_m": run.sigma3_pos[:, 0], "sigma3_east_m": run.sigma3_pos[:, 1],
            "sigma3_down_m": run.sigma3_pos[:, 2]}
    lat = lon = None
    if getattr(terrain, "crs_wkt", None):
        lat, lon = terrain.ne_to_latlon(run.est_pos[:, 0], run.est_pos[:, 1])
        cols.update(lat_deg=lat, lon_deg=lon, alt_m=-run.est_pos[:, 2])
    if np.isfinite(run.truth_pos).any():
        cols.update(truth_north_m=run.truth_pos[:, 0], truth_east_m=run.truth_pos[:, 1],
                    truth_down_m=run.truth_pos[:, 2])
    table = np.column_stack(list(cols.values()))
    np.savetxt(folder / f"{stem}.csv", table, delimiter=",", header=",".join(cols), comments="", fmt="%.9g")
    names = [f"{stem}.csv"]
    if lat is not None:
        import json

        feature = {"type": "Feature", "properties": {"name": f"{result.scenario} estimate", "source": "warptan"},
                   "geometry": {"type": "LineString",
                                "coordinates": [[float(a), float(b), float(c)] for a, b, c in
                                                zip(lon, lat, -run.est_pos[:, 2], strict=True)]}}
        (folder / f"{stem}.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [feature]}))
        names.append(f"{stem}.geojson")
    return names
