"""The paper's claims (design notes §7), decided from per-seed numbers by stated tests.

Every claim is evaluated from the per-run summaries a scenario run writes (``results.json`` → ``runs``), so a
committed results file re-derives its verdicts. Each comparison is one of:

* "A is better than B" — one-sided Welch t test on the per-seed converged horizontal RMSE
  (``hypot(north, east)`` after ``filter.converged_after_s``): :func:`warptan.sim.report.compare_less`;
* "A and B are close" — the 95 % bootstrap interval of the ratio of their mean horizontal RMSEs inside
  [1/1.5, 1.5]: :func:`warptan.sim.report.ratio_within`.

A claim with several pairs holds when every pair holds, does not hold when any pair does not, and is
inconclusive otherwise (:func:`warptan.sim.report.combine`); α = :data:`warptan.sim.report.ALPHA` (one-sided).
"""

from __future__ import annotations

import numpy as np

from warptan.sim.report import ALPHA, FAILS, HOLDS, INCONCLUSIVE, ci95, combine, compare_less, ratio_within

NOT_RUN = "not run"
CLOSE_FACTOR = 1.5
"""Raycast and sliding are "close" when their mean horizontal RMSEs are within this factor."""
NO_BARO_RATIO = 0.5
"""Altitude is observable without a barometer when the point cloud's vertical RMSE is below this fraction of the
altimeter's (both without a barometer) and its 95 % upper bound below :data:`NO_BARO_LIMIT_M`."""
NO_BARO_LIMIT_M = 5.0


def _values(runs: list[dict], sid: str, key: str = "rmse_converged_m", axes=(0, 1)) -> np.ndarray:
    vals = [np.atleast_1d(np.asarray(r[key], dtype=np.float64)) for r in runs if r["scenario"] == sid]
    if not vals:
        return np.empty(0)
    v = np.array(vals)[:, list(axes)]
    return np.hypot(v[:, 0], v[:, 1]) if len(axes) == 2 else v[:, 0]


def _fmt(v: np.ndarray) -> str:
    m, h = ci95(v[:, None])
    return f"{m[0]:.2f}±{h[0]:.2f} m" if np.isfinite(h[0]) else f"{m[0]:.2f} m"


def _judge_pairs(runs, pairs, judge) -> tuple[str, str]:
    """Every pair (a, b) of scenarios judged on their per-seed converged horizontal RMSE by ``judge(a, va, b, vb)
    -> (verdict, evidence)``; the verdicts combined, the evidence joined; not run when a pair lacks 2 seeds."""
    verdicts, parts = [], []
    for a, b in pairs:
        va, vb = _values(runs, a), _values(runs, b)
        if len(va) < 2 or len(vb) < 2 or not (np.isfinite(va).all() and np.isfinite(vb).all()):
            return NOT_RUN, f"{a} or {b} has fewer than 2 seeds with a converged RMSE"
        verdict, text = judge(a, va, b, vb)
        verdicts.append(verdict)
        parts.append(text)
    return combine(verdicts), "; ".join(parts)


def _better(runs, pairs, label_a="", label_b="") -> tuple[str, str]:
    def judge(a, va, b, vb):
        verdict, p = compare_less(va, vb)
        return verdict, f"{label_a}{a} {_fmt(va)} vs {label_b}{b} {_fmt(vb)} (Welch p = {p:.2g}: {verdict})"

    return _judge_pairs(runs, pairs, judge)


def _close(runs, pairs) -> tuple[str, str]:
    def judge(a, va, b, vb):
        verdict, (r, lo, hi) = ratio_within(va, vb, CLOSE_FACTOR)
        return verdict, f"{a} {_fmt(va)} vs {b} {_fmt(vb)}: ratio {r:.2f}, 95 % interval {lo:.2f}–{hi:.2f} ({verdict})"

    return _judge_pairs(runs, pairs, judge)


def evaluate(runs: list[dict], no_baro_runs: list[dict] | None = None) -> list[dict]:
    """design notes §7's claims from run summaries (``ScenarioResult.summary()`` dicts, any seeds and scenarios).

    Returns a list of {claim, scenarios, verdict, test, evidence}; ``verdict`` is ``holds``, ``does not hold``,
    ``inconclusive`` or ``not run`` (a scenario it needs is missing)."""
    out = []
    welch = f"one-sided Welch t test on per-seed converged horizontal RMSE, α = {ALPHA:g}"

    def add(claim, ids, verdict_evidence, test=welch):
        verdict, evidence = verdict_evidence
        out.append({"claim": claim, "scenarios": ids, "verdict": verdict, "test": test, "evidence": evidence})

    add("point cloud beats the altimeter horizontally on rugged and flat terrain", ["S7", "S8", "S9", "S10", "S11",
        "S12"], _better(runs, [("S7", "S9"), ("S8", "S9"), ("S10", "S12"), ("S11", "S12")]))
    add("flat terrain is worse than rugged (same model)", ["S7", "S8", "S9", "S10", "S11", "S12"],
        _better(runs, [("S7", "S10"), ("S8", "S11"), ("S9", "S12")], "rugged ", "flat "))
    add("the navigation IMU is better than the low-end tactical one (S1 vs S2)", ["S1", "S2"],
        _better(runs, [("S1", "S2")]))
    add(f"raycast and sliding are close at high altitude (mean horizontal RMSE within a factor {CLOSE_FACTOR:g})",
        ["S3", "S4", "S7", "S8"], _close(runs, [("S3", "S4"), ("S7", "S8")]),
        f"95 % bootstrap interval (10 000 resamples) of the ratio of mean converged horizontal RMSE inside "
        f"[1/{CLOSE_FACTOR:g}, {CLOSE_FACTOR:g}]")
    add("raycast is better than sliding at low altitude / 60° bank (S5 vs S6)", ["S5", "S6"],
        _better(runs, [("S5", "S6")]))
    if no_baro_runs:
        z8 = _values(no_baro_runs, "S8", "rmse_m", axes=(2,))
        z9 = _values(no_baro_runs, "S9", "rmse_m", axes=(2,))
        if len(z8) >= 2 and len(z9) >= 2:
            ratio_verdict, p = compare_less(z8, NO_BARO_RATIO * z9)
            m, h = ci95(z8[:, None])
            upper = float(m[0] + h[0])
            bound = HOLDS if upper < NO_BARO_LIMIT_M else (FAILS if m[0] - h[0] > NO_BARO_LIMIT_M else INCONCLUSIVE)
            verdict = combine([ratio_verdict, bound])
            evidence = (f"vertical RMSE (whole run) without a barometer: S8 {_fmt(z8)} vs S9 {_fmt(z9)}; S8 < "
                        f"{NO_BARO_RATIO:g} × S9: Welch p = {p:.2g}; S8's 95 % upper bound {upper:.2f} m "
                        f"(< {NO_BARO_LIMIT_M:g} m needed)")
        else:
            verdict, evidence = NOT_RUN, "S8 and S9 without a barometer need 2 seeds each"
        add("altitude is observable from the point cloud without a barometer (S8 vs S9, no baro)", ["S8", "S9"],
            (verdict, evidence), f"one-sided Welch t test of S8 < {NO_BARO_RATIO:g} × S9 on per-seed vertical RMSE, "
            f"and S8's upper 95 % bound < {NO_BARO_LIMIT_M:g} m")
    ray, slide = _values(runs, "S7", "update_ms_median", axes=(0,)), _values(runs, "S8", "update_ms_median",
                                                                             axes=(0,))
    if len(ray) >= 2 and len(slide) >= 2:
        verdict, p = compare_less(2.0 * slide, ray)
        evidence = (f"median update per run: raycast (S7) {np.mean(ray):.2f} ms vs sliding (S8) {np.mean(slide):.2f} "
                    f"ms (whole update incl. weights and resampling, this device); sliding < raycast / 2: Welch p = "
                    f"{p:.2g}")
    else:
        verdict, evidence = NOT_RUN, "S7 and S8 need 2 seeds each"
    add("sliding is much cheaper than raycasting (at least 2× per measurement update, S7 vs S8)", ["S7", "S8"],
        (verdict, evidence), "one-sided Welch t test of 2 × sliding < raycast on per-run median update times")
    return out


def markdown(found: list[dict]) -> str:
    """The claims as a Markdown list (verdict, claim, evidence, test)."""
    return "\n".join(f"- **{c['verdict']}** — {c['claim']}: {c['evidence']} [{c['test']}]" for c in found)
