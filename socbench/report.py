"""Leaderboard outputs: ``leaderboard.csv`` (DESIGN.md columns), ``leaderboard.md`` (ranked) and figures.

Ranking, within a scenario: cells with fewer failed runs first, then by SOC RMSE, then by voltage RMSE. A cell whose
runs all failed has empty metric fields in the CSV (never NaN), "—" in the Markdown, and ranks last.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from .io import atomic_write_frame, atomic_write_text
from .study.cell import LEADERBOARD_COLUMNS

#: estimator whose predicted voltage stands for "the model's voltage" in the voltage-profile figure (open loop)
PROFILE_ESTIMATOR = "coulomb"


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text)


def rank_key(row: dict):
    soc = row.get("soc_rmse")
    v = row.get("v_rmse")
    return (row["failed_runs"] >= row["n_runs"], row["failed_runs"], math.inf if soc is None else soc,
            math.inf if v is None else v, row["model"], row["estimator"])


def ranked(result, scenario: str) -> list[dict]:
    """The cell records of ``scenario``, best first (see the module docstring)."""
    recs = [r for r in result.cells if r["row"]["scenario"] == scenario]
    return sorted(recs, key=lambda r: rank_key(r["row"]))


def best_sentence(result, scenario: str) -> str:
    recs = ranked(result, scenario)
    best = recs[0]["row"] if recs else None
    if best is None or best["failed_runs"] >= best["n_runs"]:
        return f"On {scenario} no combination completed a run."
    failed = "none failed" if best["failed_runs"] == 0 else f"{best['failed_runs']} failed"
    v = "" if best["v_rmse"] is None else f" and a voltage RMSE of {1000 * best['v_rmse']:.1f} mV"
    return (f"On {scenario} the best combination is {best['model']} + {best['estimator']}: "
            f"SOC RMSE {100 * best['soc_rmse']:.2f} %{v} over {best['n_runs']} runs ({failed}).")


def _n(k: int, noun: str) -> str:
    return f"{k} {noun}" + ("" if k == 1 else "s")


def _fmt(x, scale=1.0, digits=2) -> str:
    return "—" if x is None else f"{scale * x:.{digits}f}"


_NOISE_TEXT = {"model": "the noise recipe (socbench.estimators.model_error: the fitted model's measured voltage error "
                        "as coloured states and R; the coulomb counter keeps the sensor noise)",
               "sensor": "the sensor noise only"}


def nis_text(nis, band) -> str:
    """``"1.02 [0.98, 1.03]"``: the NIS mean and its 95 % χ² band (band omitted when unknown)."""
    if nis is None:
        return "—"
    return f"{nis:.2f}" + (f" [{band[0]:.2f}, {band[1]:.2f}]" if band else "")


def markdown(result, figures: list[str]) -> str:
    cfg = result.config
    lines = [
        "# socbench leaderboard",
        "",
        f"{_n(len(cfg.models), 'model')} × {_n(len(cfg.estimators), 'estimator')} × "
        f"{_n(len(cfg.scenarios), 'scenario')} × {_n(len(cfg.seeds), 'seed')} (seeds {cfg.seeds[0]}–{cfg.seeds[-1]}); "
        f"models fitted on each scenario's own characterisation test (mode '{cfg.fit_mode}'; a measured "
        "scenario's fit setting chosen on its validation records); filter noise: "
        f"{_NOISE_TEXT.get(getattr(cfg, 'noise', 'model'), '?')}. "
        f"Backend {result.backend} ({_n(result.jobs, 'job')}), "
        f"{len(result.computed)} cells computed and {len(result.reused)} reused from the store in "
        f"{result.seconds:.1f} s." + (f" **{len(result.stale)} stored fits/cells were computed by other code** "
                                      "(rerun with `--recompute-stale` to refresh them)." if result.stale else ""),
        "",
        "SOC errors in % of capacity, voltage errors (measured − the filter's predicted voltage before its update) in "
        "mV, pooled over the runs that did not fail. Ranked by failed runs, then SOC RMSE, then voltage RMSE. "
        "\"—\": nothing to average (every run failed, or the estimator defines no such quantity). Consistency beside "
        "every SOC error: the NIS mean with its two-sided 95 % χ² band (a consistent filter's NIS mean lies in it) "
        "and the share of samples whose SOC error lies within the filter's own ±3σ.",
        "",
        "## Best combination per scenario",
        "",
    ]
    lines += [f"- {best_sentence(result, s)}" for s in cfg.scenarios]
    head = ("| rank | model | estimator | SOC RMSE % | SOC max % | within 3σ % | NIS [95 % band] | NEES | V RMSE mV "
            "| V mean mV | V SD mV | V max mV | µs/step | failed/runs |")
    for scen in cfg.scenarios:
        lines += ["", f"## {scen}", "", head, "|" + "---|" * 14]
        for k, rec in enumerate(ranked(result, scen), 1):
            r = rec["row"]
            lines.append(
                f"| {k} | {r['model']} | {r['estimator']} | {_fmt(r['soc_rmse'], 100)} | {_fmt(r['soc_max_abs'], 100)} "
                f"| {_fmt(r['frac_within_3sigma'], 100, 1)} | {nis_text(r['nis_mean'], rec.get('nis_band'))} "
                f"| {_fmt(r['nees_mean'])} | {_fmt(r['v_rmse'], 1000, 1)} | {_fmt(r['v_mean'], 1000, 1)} "
                f"| {_fmt(r['v_sd'], 1000, 1)} | {_fmt(r['v_max'], 1000, 1)} | {_fmt(r['us_per_step'], 1, 1)} "
                f"| {r['failed_runs']}/{r['n_runs']} |")
    fit_rows = []
    for (scen, model), fit in result.fits.items():
        if fit is None:
            continue
        status = fit.get("error") or "ok"
        fit_rows.append(f"| {scen} | {model} | {_fmt(fit.get('rmse_v'), 1000, 1)} | {status} |")
    if fit_rows:
        lines += ["", "## Fits (each model on each scenario's characterisation test)", "",
                  "| scenario | model | fit RMSE mV | status |", "|---|---|---|---|"] + fit_rows
    errors = [rec for rec in result.cells if rec.get("error")]
    if errors:
        lines += ["", "## Cells that failed as a whole", ""]
        lines += [f"- {r['row']['scenario']} / {r['row']['model']} + {r['row']['estimator']}: {r['error']}"
                  for r in errors]
    if figures:
        lines += ["", "## Figures", ""] + [f"- [{f}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


def write_figures(result, out: Path) -> list[str]:
    from . import plots

    cfg = result.config
    names = []
    for scen in cfg.scenarios:
        by = {(r["row"]["model"], r["row"]["estimator"]): r for r in result.cells if r["row"]["scenario"] == scen}
        panels = []
        for col, scale, unit in (("soc_rmse", 100, "SOC RMSE [%]"), ("v_rmse", 1000, "voltage RMSE [mV]")):
            vals = [[None if by[(m, e)]["row"][col] is None else scale * by[(m, e)]["row"][col]
                     for e in cfg.estimators] for m in cfg.models]
            panels.append((vals, f"{unit.split(' [')[0]} on {scen}", unit))
        fig = plots.heatmap_figure(panels, list(cfg.models), list(cfg.estimators))
        name = f"heatmap_{_slug(scen)}.png"
        plots.save(fig, out / name)
        names.append(name)

        order = [r for r in ranked(result, scen) if r.get("trace")]
        if order:
            picks = [("best", order[0])] + ([("worst", order[-1])] if len(order) > 1 else [])
            fig, axes = plots.figure(len(picks), 1, width=8, height=3.0 * len(picks), sharex=True)
            for ax, (what, rec) in zip(axes[:, 0], picks):
                r = rec["row"]
                label = f"{r['model']} + {r['estimator']}"
                plots.soc_error_band(ax, rec["trace"], label)
                ax.set_title(f"{what} on {scen}: {label}, run {rec['trace'].get('run', 0)} "
                             f"(SOC RMSE {_fmt(r['soc_rmse'], 100)} %)", fontsize=10)
                ax.legend(fontsize=7, loc="best")
            name = f"soc_error_{_slug(scen)}.png"
            plots.save(fig, out / name)
            names.append(name)

        est = PROFILE_ESTIMATOR if PROFILE_ESTIMATOR in cfg.estimators else cfg.estimators[0]
        traces = {m: by[(m, est)]["trace"] for m in cfg.models
                  if by[(m, est)].get("trace") and by[(m, est)]["trace"].get("v_pred") is not None
                  and by[(m, est)]["trace"].get("v_meas") is not None}
        if traces:
            fig, axes = plots.figure(2, 1, width=9, height=6.5, sharex=True)
            plots.voltage_profile(axes[0, 0], axes[1, 0], traces,
                                  f"Voltage profile on {scen}: measured vs each model's predicted voltage ({est})")
            name = f"voltage_{_slug(scen)}.png"
            plots.save(fig, out / name)
            names.append(name)
    return names


def write_report(result, out, figures: bool = True) -> dict:
    """Write the CSV, the Markdown and (optionally) the figures to ``out``; returns what was written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    frame = result.frame()
    assert list(frame.columns) == list(LEADERBOARD_COLUMNS)
    atomic_write_frame(out / "leaderboard.csv", frame)
    figs = write_figures(result, out) if figures else []
    atomic_write_text(out / "leaderboard.md", markdown(result, figs))
    return {"csv": out / "leaderboard.csv", "md": out / "leaderboard.md", "figures": figs,
            "best": [best_sentence(result, s) for s in result.config.scenarios]}
