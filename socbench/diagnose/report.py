"""The diagnosis report: ``diagnosis.json`` (DESIGN.md keys), ``diagnosis.md``, ``model.json`` (the final model as a
parameter file) and figures."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ..io import atomic_write_text
from ..models.params import save_params
from .core import IGNORE_VOLTAGE, SOC_WORSE
from .leftover import sentence


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


def soc_worse_sentence(name: str, before: float, after: float) -> str:
    """The line that says a filter's held-out SOC error grew by more than
    :data:`~socbench.diagnose.core.SOC_WORSE` (``before``, ``after``: its SOC RMSE)."""
    return (f"**The {name.upper()}'s held-out SOC error grew by more than {100 * SOC_WORSE:.1f} points** "
            f"({_pct(before)} → {_pct(after)} %) with what the search added.")


def alike_sentence(effect: str, alike: list) -> str:
    """What :meth:`~socbench.diagnose.search.Search.alike` found beside the drift ``effect`` named, in one sentence."""
    others = ", ".join(f"{r['effect']} ({_mv(r['rmse_v_after'])} mV)" for r in alike)
    return (f"The records hardly tell {effect} from {others}: fitted alone in the round {effect} was added in, it "
            f"reached {_mv(alike[0]['named_rmse_v_after'])} mV held-out. A rest of hours (a leak goes on, a fade does "
            "not) or a capacity test would tell them apart.")


#: a reference SOC further than this from a count of the records' current (RMS, SOC fraction) is not read as one
COUNT_RESIDUAL_MAX = 0.01
#: the reference's capacity and the model's differ enough to say what it does to the SOC error (a share)
COUNT_GAP = 0.01
#: a current the reference leaves out below this share of 1C is not stated (the 0.05 % of 1C below which the search's
#: rests rule a current-sensor offset out)
COUNT_CURRENT_C = 0.0005


def axis_gap(rc: dict) -> float | None:
    """``Q_final/Q_ref − 1`` of a reference count (``diagnosis.json`` → ``soc.reference_count``): how far the final
    model's capacity lies from the one the reference counts with; None where the reference is no count of the records'
    current (:data:`COUNT_RESIDUAL_MAX`)."""
    if rc["residual_soc_rms"] > COUNT_RESIDUAL_MAX:
        return None
    return rc["model_capacity_ah"]["after"] / rc["capacity_ah"] - 1.0


def reference_count_sentence(rc: dict) -> str:
    """What the evaluation records' reference SOC counts against what the model counts
    (:func:`socbench.socaxis.read_reference_count`, ``diagnosis.json`` → ``soc.reference_count``), in one sentence."""
    gap = axis_gap(rc)
    if gap is None:
        return (f"The evaluation records' reference SOC is no count of their current (it lies "
                f"{_pct(rc['residual_soc_rms'])} points RMS from the nearest one): its SOC axis is not read.")
    q, qb, qa = rc["capacity_ah"], rc["model_capacity_ah"]["before"], rc["model_capacity_ah"]["after"]
    c = rc["uncounted_current_a"]
    text = f"The evaluation records' reference SOC counts {q:.4g} Ah per unit of SOC"
    if c is not None and abs(c) >= COUNT_CURRENT_C * q:
        text += (f", and {abs(1000 * c):.1f} mA {'less' if c > 0 else 'more'} discharge than the records' current "
                 "sensor reads")
    elif c is not None:
        text += ", and the current as the records' sensor reads it"
    text += (f" (within {_pct(rc['residual_soc_rms'])} points RMS); the base model counts {qb:.4g} Ah "
             f"({100 * (qb / q - 1):+.1f} %)")
    if abs(qa / qb - 1.0) > 1e-9:
        text += f", the model after the search {qa:.4g} Ah ({100 * gap:+.1f} %)"
    declared = rc.get("declared_capacity_ah")
    if declared:
        text += (f". The records declare their reference a count on {', '.join(f'{d:.4g}' for d in declared)} Ah: "
                 "the filters' SOC is converted to that axis before it is scored")
    elif abs(gap) > COUNT_GAP:
        text += (f". Against this reference a count on the final model's axis drifts by {100 * abs(gap):.1f} % of "
                 "the charge moved, whatever the filter; the voltage corrects it only where the OCV's slope shows it")
    return text + "."


def attribution_lines(att, name: str) -> list:
    """Where a change of filter ``name``'s SOC error comes from (:func:`socbench.diagnose.core.soc_attribution`):
    a table and what it says, as Markdown lines (ending with an empty one); none without ``att``."""
    if not att:
        return []
    b, a = att["before"], att["after"]
    pct = lambda x: f"{100 * x:.2f}"  # noqa: E731
    grew = a["own"][name] - b["own"][name]
    noise_share = a["own"][name] - a["other"][name]
    L = [f"Where it comes from (`socbench.diagnose.core.soc_attribution`, same filters and folds, {name.upper()} "
         "held-out SOC RMSE [%]):", "",
         "| model | own filter voltage noise | the other model's | voltage ignored (noise × "
         f"{IGNORE_VOLTAGE:g}) |", "|---|---|---|---|",
         f"| before | {pct(b['own'][name])} | {pct(b['other'][name])} | {pct(b['voltage_ignored'][name])} |",
         f"| after | {pct(a['own'][name])} | {pct(a['other'][name])} | {pct(a['voltage_ignored'][name])} |", "",
         f"Of the {100 * grew:.2f} points, {100 * noise_share:.2f} come from the smaller filter voltage noise of the "
         f"better voltage model (the filter trusts the voltage more), {100 * (grew - noise_share):.2f} from the "
         "model at equal filter noise."]
    if b["own"][name] > b["voltage_ignored"][name] and a["own"][name] > a["voltage_ignored"][name]:
        L[-1] += (" Both models' filters do worse than counting the current alone "
                  f"({pct(b['voltage_ignored'][name])} / {pct(a['voltage_ignored'][name])} %): the voltage error "
                  "left in either model misleads the SOC more than it corrects it, so a smaller but still "
                  "SOC-biasing voltage error, trusted a little more, moves the estimate further off.")
    return L + [""]


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
    recs = ", ".join(f"{r['profile']} ({r['n']} samples)" for r in sp["records"])
    lines += ["", f"Held-out scoring ({sp['method']}, {sp['folds']} folds): every evaluation record ({recs}) is cut "
              f"into {sp['folds']} blocks of equal duration; the effect parameters are fitted {sp['folds']} times, "
              "each time without one block, and every block is scored by the fit that did not see it.", ""]
    for note in diag.fit.get("evaluation_records_cut", ()):
        lines[-1:-1] = [f"Cut at gaps: {note}."]
    # what the steps put in the model that is not an effect (the base refit, a base branch put back) is said too
    base = ["refit" if s.effect == "base_refit" else f"{s.effect} as its own branch" for s in diag.steps
            if not s.named]
    added = (" + ".join(diag.effects_added) or ("no effect" if base else "no change")) \
        + (f"; base: {', '.join(base)}" if base else "")
    filters = list(b.get("soc") or {})
    lines += markdown_table(["", "held-out voltage RMSE [mV]"] + [f"held-out SOC RMSE ({k.upper()}) [%]"
                                                                   for k in filters],
                            [[label, _mv(d["rmse_v"])] + [_pct(d["soc"][k]["soc_rmse"]) for k in filters]
                             for label, d in (("before (base model)", b), (f"after ({added})", a))])
    if diag.soc.get("note"):
        lines += ["", f"SOC: {diag.soc['note']}."]
    if diag.soc.get("reference_count"):
        lines += ["", reference_count_sentence(diag.soc["reference_count"])]
    for name in diag.soc.get("worse", ()):
        lines += ["", soc_worse_sentence(name, b["soc"][name]["soc_rmse"], a["soc"][name]["soc_rmse"])]
        lines += [""] + attribution_lines(diag.soc.get("attribution"), name)[:-1]
    if diag.left:
        lines += ["", f"What is left: {sentence(diag.left)}."]
    if diag.steps:
        lines += ["", "## Steps", ""]
        for k, s in enumerate(diag.steps, 1):
            label = ("base refit (not an effect)" if s.effect == "base_refit"
                     else f"{s.effect}: the base's own branch put back (not an effect)" if not s.named else s.effect)
            lines.append(f"{k}. **{label}** — {_mv(s.rmse_before)} → {_mv(s.rmse_after)} mV held-out; {s.evidence}.")
            alike = diag.alike(s)
            if alike:
                lines.append(f"   {alike_sentence(s.effect, alike)}")
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
    """Residual vs the winning signature (per effect step) and, per evaluation record, the measured voltage and the
    held-out error before and after (every block predicted by the fold that did not see it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    seeded = sum(step.fit_test for step in diag.steps)  # steps found on the fit test come before any round
    for k, step in enumerate(diag.steps):
        if step.fit_test:
            continue
        rnd = diag.rounds[k - seeded]
        sig = rnd["signatures"].get(step.effect)
        if sig is None:
            continue
        r = np.concatenate([tr.residual for tr in rnd["trajectory"]])
        t = np.concatenate([tr.profile.time_s - tr.profile.time_s[0] for tr in rnd["trajectory"]]) / 60
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
        ax[0].plot(sig.prediction * 1000, (r - r.mean()) * 1000, ".", ms=2, alpha=0.5)
        lim = np.nanmax(np.abs(np.r_[sig.prediction - sig.prediction.mean(), r - r.mean()])) * 1000
        ax[0].plot([-lim, lim], [-lim, lim], "k--", lw=0.8)
        ax[0].set_xlabel(f"signature {sig.regressor} (first-order Δy) [mV]")
        ax[0].set_ylabel("residual − mean [mV]")
        ax[0].set_title(f"step {k + 1}: {step.effect} (R² = {sig.r2:.2f})")
        ax[1].plot((r - r.mean()) * 1000, lw=0.8, label="residual")
        ax[1].plot((sig.prediction - sig.prediction.mean()) * 1000, lw=0.8, label="signature fit")
        ax[1].set_xlabel(f"sample (records one after another; {t.max():.0f} min the longest)")
        ax[1].set_ylabel("mV")
        ax[1].legend(fontsize=8)
        fig.tight_layout()
        p = out_dir / f"{prefix}signature_{k + 1}_{step.effect}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    recs = diag.split.records
    fig, ax = plt.subplots(2, len(recs), figsize=(10 if len(recs) == 1 else 6 * len(recs), 6), sharex="col",
                           squeeze=False)
    k0 = 0
    for c, (prof, blocks) in enumerate(zip(recs, diag.split.blocks)):
        t = (prof.time_s - prof.time_s[0]) / 60
        ax[0, c].plot(t, prof.voltage_v, "k", lw=0.8, label="measured")
        for label, key in (("before", "before"), ("after (held-out)", "after")):
            e = diag.held_out_residual[key][k0:k0 + prof.n]
            ax[0, c].plot(t, prof.voltage_v - e, lw=0.8, label=label)
            ax[1, c].plot(t, e * 1000, lw=0.8, label=label)
        for j in range(1, diag.split.k):
            edge = t[np.argmax(blocks >= j)]
            for a in ax[:, c]:
                a.axvline(edge, color="0.6", lw=0.6, ls=":")
        ax[0, c].set_ylabel("voltage [V]")
        ax[0, c].set_title(prof.name, fontsize=9)
        ax[1, c].set_ylabel("error [mV]")
        ax[1, c].set_xlabel("time [min] (dotted: block edges of the folds)")
        k0 += prof.n
    ax[0, 0].legend(fontsize=8)
    ax[1, 0].legend(fontsize=8)
    fig.tight_layout()
    p = out_dir / f"{prefix}voltage.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths


def final_params(diag):
    """The final model as a parameter set (:class:`~socbench.models.params.ModelParams`): the base's parameters as the
    all-data fit left them (scaled by the base refit where it was adopted; its per-record voltage offsets are the
    records', not the model's, and are left out) with the added effects and their fitted values in ``effects``, so
    that ``make_model`` builds the augmented model again (``socbench estimate --params``)."""
    final = diag.final_model
    base = getattr(final, "base", final)
    effects = tuple({"name": e.name, "values": {k: float(np.asarray(v).reshape(-1)[0]) for k, v in e.values.items()}}
                    for e in getattr(final, "effects", ()))
    return dataclasses.replace(base.params, effects=effects)


def write_report(diag, out_dir, prefix: str = "", with_figures: bool = True) -> dict:
    """Write ``diagnosis.json``, ``diagnosis.md``, ``model.json`` (:func:`final_params`, a parameter file for
    ``socbench estimate``/``simulate``) and the figures to ``out_dir``; returns the JSON dict."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    figs = figures(diag, out_dir, prefix) if with_figures else []
    d = diag.to_dict()
    atomic_write_text(out_dir / "diagnosis.json", json.dumps(d, indent=2, default=_json_default))
    atomic_write_text(out_dir / "diagnosis.md", markdown(diag, figs))
    params = final_params(diag)
    stats = final_model_error(diag, params)
    save_params(out_dir / "model.json", diag.model, params,
                fit={"from": "socbench diagnose", "effects_added": list(diag.effects_added),
                     "base_refit": any(s.effect == "base_refit" for s in diag.steps)},
                **({"model_error": stats.to_dict()} if stats is not None else {}))
    return d


def final_model_error(diag, params):
    """The noise recipe's statistics of the final model (:func:`socbench.estimators.model_error.estimate`) on the
    evaluation records that carry a reference SOC, as ``socbench fit`` measures them on its identification records
    (``measured_on="identification"``: the effects were fitted on these records, so the error is in sample,
    optimistic); None where none has a reference."""
    from ..errors import ConfigError, DataError
    from ..estimators import model_error
    from ..models import make_model

    records = [p for p in diag.split.records if p.soc_ref is not None]
    if not records:
        return None
    try:
        return model_error.estimate(make_model(diag.model, params), records, measured_on="identification")
    except (ConfigError, DataError):  # a record the model cannot run from its reference: no block, as `fit` does
        return None
