"""The diagnosis report: ``diagnosis.json`` (DESIGN.md keys), ``diagnosis.md`` and figures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..io import atomic_write_text
from .search import initial_soc


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)


def _mv(v):
    return "–" if v is None else f"{1000 * v:.2f}"


def _pct(v):
    return "–" if v is None else f"{100 * v:.2f}"


def markdown_table(header, rows) -> list:
    """A Markdown table as lines: ``header`` the column titles, ``rows`` lists of cells (formatted by ``str``)."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + \
        ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]


def markdown(diag, figures=()) -> str:
    """``diagnosis.md``: the before/after table and one sentence of evidence per step."""
    b, a = diag.before, diag.after
    lines = [f"# Diagnosis of `{diag.model}`", ""]
    lines.append(f"Fitted on {', '.join(diag.fit['records'])} ({diag.fit['mode']} mode, fit RMSE "
                 f"{_mv(diag.fit['rmse_v'])} mV; OCV: {diag.fit.get('ocv', '?')}). "
                 f"Effects added: {', '.join(diag.effects_added) or 'none'}.")
    sp = diag.split.describe()
    held = ", ".join(f"{h['profile']} from sample {h['first_index']}" for h in sp["held_out"])
    lines += ["", f"Split ({sp['method']}): effect parameters fitted on {sp['train']['profile']} "
              f"({sp['train']['n']} samples), judged on {held}.", ""]
    added = " + ".join(diag.effects_added) or "no change"
    lines += markdown_table(["", "held-out voltage RMSE [mV]", "held-out SOC RMSE (EKF) [%]"],
                            [[label, _mv(d["rmse_v"]), _pct(d.get("soc_rmse"))]
                             for label, d in (("before (base model)", b), (f"after ({added})", a))])
    if diag.soc.get("note"):
        lines += ["", f"SOC: {diag.soc['note']}."]
    if diag.steps:
        lines += ["", "## Steps", ""]
        for k, s in enumerate(diag.steps, 1):
            lines.append(f"{k}. **{s.effect}** — {_mv(s.rmse_before)} → {_mv(s.rmse_after)} mV held-out; {s.evidence}.")
    fitted = [(c, np.isfinite(c.score)) for c in (diag.rounds[0]["candidates"] if diag.rounds else [])]
    lines += ["", "## Candidates (first round)", ""]
    lines += markdown_table(["effect", "score", "signature R²", "held-out RMSE after [mV]", "evidence"],
                            [[c.effect, f"{c.score:.3f}" if ok else "–", f"{c.signature_r2:.2f}",
                              _mv(c.rmse_after) if ok else "–", c.evidence] for c, ok in fitted])
    lines += ["", "Score: ln(MSE_before/MSE_after) on the held-out part − 2·(parameters added)/n_eff (AIC per "
              "effective sample).", ""]
    for f in figures:
        lines.append(f"![{Path(f).stem}]({Path(f).name})")
    return "\n".join(lines) + "\n"


def figures(diag, out_dir, prefix: str = "") -> list:
    """Residual vs the winning signature (per step) and held-out voltage / error before and after."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, step in enumerate(diag.steps):
        rnd = diag.rounds[k]
        sig = rnd["signatures"].get(step.effect)
        traj = rnd["trajectory"]
        if sig is None:
            continue
        r = traj.residual
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
        ax[0].plot(sig.prediction * 1000, (r - r.mean()) * 1000, ".", ms=2, alpha=0.5)
        lim = np.nanmax(np.abs(np.r_[sig.prediction - sig.prediction.mean(), r - r.mean()])) * 1000
        ax[0].plot([-lim, lim], [-lim, lim], "k--", lw=0.8)
        ax[0].set_xlabel(f"signature {sig.regressor} (first-order Δy) [mV]")
        ax[0].set_ylabel("residual − mean [mV]")
        ax[0].set_title(f"step {k + 1}: {step.effect} (R² = {sig.r2:.2f})")
        t = (traj.profile.time_s - traj.profile.time_s[0]) / 60
        ax[1].plot(t, (r - r.mean()) * 1000, lw=0.8, label="residual")
        ax[1].plot(t, (sig.prediction - sig.prediction.mean()) * 1000, lw=0.8, label="signature fit")
        ax[1].set_xlabel("time [min] (training part)")
        ax[1].set_ylabel("mV")
        ax[1].legend(fontsize=8)
        fig.tight_layout()
        p = out_dir / f"{prefix}signature_{k + 1}_{step.effect}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    prof, k0 = diag.split.held[0]
    fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    t = (prof.time_s - prof.time_s[0]) / 60
    ax[0].plot(t, prof.voltage_v, "k", lw=0.8, label="measured")
    for label, m in (("before", diag.base_model), ("after", diag.final_model)):
        y = m.simulate(prof, soc0=initial_soc(m, prof)).voltage_v
        ax[0].plot(t, y, lw=0.8, label=f"{label}: {m.name}")
        ax[1].plot(t, (prof.voltage_v - y) * 1000, lw=0.8, label=label)
    for a in ax:
        a.axvspan(t[0], t[k0], color="0.9", lw=0)
    ax[0].set_ylabel("voltage [V]")
    ax[0].legend(fontsize=8)
    ax[1].set_ylabel("error [mV]")
    ax[1].set_xlabel(f"time [min] — {prof.name} (shaded: training part)")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    p = out_dir / f"{prefix}voltage.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths


def write_report(diag, out_dir, prefix: str = "", with_figures: bool = True) -> dict:
    """Write ``diagnosis.json``, ``diagnosis.md`` and the figures to ``out_dir``; returns the JSON dict."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    figs = figures(diag, out_dir, prefix) if with_figures else []
    d = diag.to_dict()
    atomic_write_text(out_dir / "diagnosis.json", json.dumps(d, indent=2, default=_json_default))
    atomic_write_text(out_dir / "diagnosis.md", markdown(diag, figs))
    return d
