"""Robustness sweep: every model × every estimator × every catalog scenario × 100 seeds, and docs/reliability.md.

    python benchmarks/robustness.py [--seeds 100] [--models a,b] [--estimators a,b] [--scenarios a,b]
                                    [--backend process] [--jobs N] [--out robustness-out]
                                    [--doc docs/reliability.md | --no-doc] [--recompute-stale] [--report-only]

One command: runs the study (socbench.study, the leaderboard's machinery) into ``--out/store`` — rerun the same
command after an interrupt and it resumes, recomputing nothing that finished — then analyses every cell record and
writes ``--out/robustness.json`` and the Markdown report (``--doc``, default docs/reliability.md). Defaults: every
registered model, every registered estimator, every catalog scenario, seeds 0 … 99. The options slice the grid.

What it reports (the numbers of the doc all come from here):

* NaN/inf: non-finite values in any estimator output (SOC, its SD, predicted voltage, innovation and its variance;
  ``nonfinite.outputs`` of a cell record) and metrics that came out non-finite (``nonfinite.metrics``). Must be 0;
* failed runs (``Estimate.failed``: the divergence detection of socbench.estimators.safety) per cell, per estimator
  × scenario, per model, and the worst cells; cells that threw as a whole;
* for every cell with failed runs: why (the divergence reason of each run), where (sample, time) and what the run
  looked like there (last good SOC and SD, true SOC, current, voltage, predicted voltage), and whether the model
  itself is undefined where the filter's ±3σ spread reaches (``model_nonfinite_soc``);
* the share of samples each cell's estimate spent outside the model's domain (``out_of_domain``, socbench.domain).

``--report-only`` computes nothing: it reports the cells already in the store (a sweep still running in another
process, or interrupted), and the report says how many of the grid's cells it covers.

Exit status: 0 when there is no NaN/inf, 1 otherwise (a failed run is a result, not an error).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(REPO))

from socbench.io import atomic_write_text  # noqa: E402
from socbench.study import Store, StudyConfig, Toolkit, parse_names, run_study  # noqa: E402

DEFAULT_SEEDS = 100
DEFAULT_OUT = "robustness-out"
DEFAULT_DOC = REPO / "docs" / "reliability.md"
#: cells listed as "worst" in the report
WORST = 15
#: a cell whose estimate spent at least this share of samples out of the model's domain is listed
DOMAIN_LIST = 0.01


def build_config(args, toolkit: Toolkit) -> StudyConfig:
    models = parse_names(args.models, toolkit.model_names(), "model", toolkit.model_names())
    estimators = parse_names(args.estimators, toolkit.estimator_names(), "estimator", toolkit.estimator_names())
    scenarios = parse_names(args.scenarios, toolkit.scenario_names(), "scenario", toolkit.scenario_names())
    return StudyConfig(models=models, estimators=estimators, scenarios=scenarios, seeds=tuple(range(args.seeds)))


# ------------------------------------------------------------------------------------------------ analysis
def _rate(failed: int, runs: int) -> float:
    return failed / runs if runs else 0.0


def cell_summary(rec: dict, stale: set = frozenset()) -> dict:
    """One cell record reduced to what the report shows (``stale``: keys of records computed by other code)."""
    row = rec["row"]
    nonfinite = rec.get("nonfinite") or {}
    failures = rec.get("failures") or []
    domain = rec.get("domain") or {}
    return {
        "model": row["model"], "estimator": row["estimator"], "scenario": row["scenario"],
        "n_runs": row["n_runs"], "failed_runs": row["failed_runs"],
        "failed_rate": _rate(row["failed_runs"], row["n_runs"]),
        "error": rec.get("error"),
        "reasons": dict(Counter(f["reason"] for f in failures)),
        "failures_listed": len(failures),
        "first_failure": min(failures, key=lambda f: f["step"]) if failures else None,
        "nonfinite_outputs": int(nonfinite.get("outputs", 0) or 0),
        "nonfinite_metrics": list(nonfinite.get("metrics", []) or []),
        "out_of_domain": row.get("out_of_domain"),
        "domain_guards": domain.get("guards", {}),
        "domain_counts": {k: domain[k] for k in ("soc_pinned", "ocv_held", "soc_below_0", "soc_above_1",
                                                 "voltage_implausible") if domain.get(k)},
        "soc_rmse": row.get("soc_rmse"),
        "seconds": rec.get("seconds"),
        "stale": rec.get("key") in stale,
    }


def _group(cells: list[dict], keys: tuple) -> dict:
    out: dict = {}
    for c in cells:
        k = tuple(c[x] for x in keys)
        g = out.setdefault(k, {"runs": 0, "failed": 0})
        g["runs"] += c["n_runs"]
        g["failed"] += c["failed_runs"]
    return out


def analyse(result, store: Store) -> dict:
    """The sweep's findings from a finished :class:`~socbench.study.StudyResult` (module docstring)."""
    cfg = result.config
    stale = set(result.stale)
    cells = [cell_summary(rec, stale) for rec in result.cells]
    frame = result.frame()
    metric_values = frame.drop(columns=["model", "estimator", "scenario"]).to_numpy(dtype=float)
    import numpy as np

    nonfinite_table = int(np.count_nonzero(np.isinf(metric_values)))  # None (empty) is NaN here and allowed
    logs = store.run_logs()
    fit_seconds = sum(float(f.get("seconds") or 0.0) for f in result.fits.values() if f)
    runs = sum(c["n_runs"] for c in cells)
    failed = sum(c["failed_runs"] for c in cells)
    worst = sorted((c for c in cells if c["failed_runs"]),
                   key=lambda c: (-c["failed_rate"], c["model"], c["estimator"], c["scenario"]))
    return {
        "config": cfg.to_dict(),
        "grid_cells": cfg.n_cells,
        "missing_cells": len(result.missing),
        "cells": len(cells),
        "runs": runs,
        "failed_runs": failed,
        "failed_rate": _rate(failed, runs),
        "cells_with_failures": sum(1 for c in cells if c["failed_runs"]),
        "cells_that_threw": [c for c in cells if c["error"]],
        "nan_inf": {"outputs": sum(c["nonfinite_outputs"] for c in cells),
                    "metrics": sum(len(c["nonfinite_metrics"]) for c in cells),
                    "table": nonfinite_table},
        "by_estimator_scenario": {f"{e}|{s}": v for (e, s), v in _group(cells, ("estimator", "scenario")).items()},
        "by_model": {m: v for (m,), v in _group(cells, ("model",)).items()},
        "by_estimator": {e: v for (e,), v in _group(cells, ("estimator",)).items()},
        "worst": worst[:WORST],
        "failed_cells": worst,
        "out_of_domain": sorted((c for c in cells if (c["out_of_domain"] or 0) >= DOMAIN_LIST),
                                key=lambda c: -(c["out_of_domain"] or 0)),
        "seconds": {"worker_cells": sum(float(c["seconds"] or 0.0) for c in cells), "worker_fits": fit_seconds,
                    "wall_all_invocations": sum(float(g.get("seconds") or 0.0) for g in logs),
                    "invocations": len(logs), "this_invocation": result.seconds},
        "stale": len(result.stale),
        "stale_cells": sum(c["stale"] for c in cells),
        # of the invocations that computed cells (a --report-only one computes none and has no workers)
        "backend": next((g.get("backend") for g in reversed(logs) if g.get("computed")), result.backend),
        "jobs": max([int(g.get("jobs") or 0) for g in logs if g.get("computed")] or [result.jobs]),
        "cells_detail": cells,
    }


# ------------------------------------------------------------------------------------------------ the report
def _pct(x, digits=1) -> str:
    return "—" if x is None else f"{100.0 * x:.{digits}f}"


def _dagger(c: dict) -> str:
    return " †" if c.get("stale") else ""


def _group_pct(g: dict) -> str:
    """Failed-run rate of a group in %, "—" for a group with no finished run."""
    return _pct(_rate(g["failed"], g["runs"]), 2) if g["runs"] else "—"


def _num(x, fmt="{:.3f}") -> str:
    return "—" if x is None else fmt.format(x)


def explain(c: dict) -> str:
    """One sentence: why, where and with what state the cell's runs failed."""
    if c["error"]:
        return f"the cell threw as a whole: {c['error']}"
    f = c["first_failure"]
    reasons = ", ".join(f"{n}× {r}" for r, n in sorted(c["reasons"].items(), key=lambda kv: -kv[1]))
    more = "" if c["failures_listed"] >= c["failed_runs"] else f" (first {c['failures_listed']} runs described)"
    text = f"{reasons}{more}"
    if f is None:
        return text
    text += (f"; earliest at sample {f['step']} (t = {f['time_s']:.0f} s, seed {f.get('seed', f['run'])}): "
             f"SOC {_num(f['soc'])} ± {_num(f['soc_std'])} (true {_num(f['soc_true'])}), "
             f"I = {_num(f['current_a'], '{:.2f}')} A, V = {_num(f['voltage_v'], '{:.3f}')} V measured, "
             f"{_num(f['v_pred'], '{:.3f}')} V predicted")
    probe = f.get("model_nonfinite_soc")
    if isinstance(probe, list):
        text += (f"; the model itself is not finite for SOC in [{probe[0]:.3f}, {probe[1]:.3f}], inside the filter's "
                 "±3σ: a sigma point or particle left the model's domain")
    elif isinstance(probe, dict):
        text += f"; the model raises within the filter's ±3σ ({probe.get('error')})"
    else:
        text += "; the model is finite across the filter's ±3σ: the filter diverged on its own"
    return text


def markdown(an: dict, command: str) -> str:
    cfg = an["config"]
    nan = an["nan_inf"]
    total_nan = nan["outputs"] + nan["metrics"] + nan["table"]
    sec = an["seconds"]
    lines = [
        "# Reliability: the robustness sweep",
        "",
        f"Generated by `{command}` (benchmarks/robustness.py) on {datetime.now(timezone.utc):%Y-%m-%d}; every number "
        "on this page comes from that run. Rerun the same command to regenerate it (it resumes from its store).",
        "",
        f"Grid: {len(cfg['models'])} models × {len(cfg['estimators'])} estimators × {len(cfg['scenarios'])} catalog "
        f"scenarios × {len(cfg['seeds'])} seeds (seeds {cfg['seeds'][0]}–{cfg['seeds'][-1]}) = **{an['grid_cells']} "
        f"cells, {an['grid_cells'] * len(cfg['seeds'])} runs**; "
        f"models fitted on each scenario's own characterisation test (mode '{cfg['fit_mode']}'). "
        f"Models: {', '.join(cfg['models'])}. Estimators: {', '.join(cfg['estimators'])}. "
        f"Scenarios: {', '.join(cfg['scenarios'])}.",
        "",
        f"Time: {sec['wall_all_invocations'] / 60:.1f} min wall over {sec['invocations']} invocation(s) "
        f"({an['backend']} backend, {an['jobs']} jobs, {os.cpu_count()} CPUs, shared machine); worker time "
        f"{sec['worker_cells'] / 60:.1f} min in cells and {sec['worker_fits'] / 60:.1f} min in fits."
        + (f" {an['stale']} stored fits/cells were computed by other code than the rest ({an['stale_cells']} cells, "
           "marked † below; `--recompute-stale` recomputes them)." if an["stale"] else ""),
        "",
        *([f"**Partial: {an['cells']} of the grid's {an['grid_cells']} cells had finished when this report was "
           "written (`--report-only` on a sweep still running); every number below covers those cells only.**", ""]
          if an.get("missing_cells") else []),
        "## Summary",
        "",
        f"- **NaN/inf: {total_nan}** ({nan['outputs']} non-finite estimator outputs, {nan['metrics']} non-finite "
        f"metrics, {nan['table']} in the table). A failed run's outputs repeat its last finite values "
        "(socbench.estimators.base.Recorder), so none ever carries a NaN.",
        f"- **Failed runs: {an['failed_runs']} of {an['runs']} runs ({_pct(an['failed_rate'], 2)} %)** in "
        f"{an['cells_with_failures']} of {an['cells']} cells; {len(an['cells_that_threw'])} cells threw as a whole.",
        f"- Cells whose estimate spent ≥ {100 * DOMAIN_LIST:.0f} % of samples outside the model's domain "
        f"(socbench.domain): {len(an['out_of_domain'])}.",
        "",
        "A run *fails* when the divergence detection of socbench.estimators.safety flags it: a non-finite state, "
        "covariance or NIS, a SOC variance above `var_max` (1.0), or a NIS above `nis_max` (1e10). It is counted in "
        "`failed_runs` and left out of every aggregate.",
        "",
        "## Failed-run rate per estimator and scenario (%)",
        "",
    ]
    scen = cfg["scenarios"]
    lines += ["| estimator | " + " | ".join(scen) + " | all |", "|---|" + "---|" * (len(scen) + 1)]
    for e in cfg["estimators"]:
        cells = [an["by_estimator_scenario"].get(f"{e}|{s}", {"runs": 0, "failed": 0}) for s in scen]
        tot = an["by_estimator"].get(e, {"runs": 0, "failed": 0})
        lines.append(f"| {e} | " + " | ".join(_group_pct(c) for c in cells) + f" | {_group_pct(tot)} |")
    lines += ["", "## Failed-run rate per model (%)", "", "| model | failed / runs | rate % |", "|---|---|---|"]
    for m in cfg["models"]:
        g = an["by_model"].get(m, {"runs": 0, "failed": 0})
        lines.append(f"| {m} | {g['failed']} / {g['runs']} | {_group_pct(g)} |")
    lines += ["", f"## Worst cells (up to {WORST}, by failed-run rate)", ""]
    if an["worst"]:
        lines += ["| model | estimator | scenario | failed / runs | out of domain % | reasons |",
                  "|---|---|---|---|---|---|"]
        for c in an["worst"]:
            reasons = ", ".join(f"{r} ({n})" for r, n in c["reasons"].items()) or (c["error"] or "—")
            lines.append(f"| {c['model']}{_dagger(c)} | {c['estimator']} | {c['scenario']} "
                         f"| {c['failed_runs']} / {c['n_runs']} "
                         f"| {_pct(c['out_of_domain'])} | {reasons} |")
    else:
        lines.append("No cell has a failed run.")
    lines += ["", "## Every failed run explained, per cell", ""]
    if an["failed_cells"]:
        lines += [f"- **{c['model']} + {c['estimator']} on {c['scenario']}**{_dagger(c)} "
                  f"({c['failed_runs']}/{c['n_runs']}): "
                  f"{explain(c)}." for c in an["failed_cells"]]
    else:
        lines.append("No failed runs.")
    lines += ["", f"## Estimates outside the model's domain (≥ {100 * DOMAIN_LIST:.0f} % of samples)", ""]
    if an["out_of_domain"]:
        lines += ["| model | estimator | scenario | out of domain % | why (samples) | guards acting (samples) |",
                  "|---|---|---|---|---|---|"]
        for c in an["out_of_domain"]:
            why = ", ".join(f"{k} {n}" for k, n in c.get("domain_counts", {}).items()) or "SOC clamp at 0 (old rule)"
            guards = ", ".join(f"{g} {n}" for g, n in c["domain_guards"].items()) or "—"
            lines.append(f"| {c['model']}{_dagger(c)} | {c['estimator']} | {c['scenario']} "
                         f"| {_pct(c['out_of_domain'])} | {why} | {guards} |")
    else:
        lines.append("None.")
    lines += [
        "",
        "Out of domain (socbench.domain): the SOC clamp holding the estimate at 0 (1) while the record went on to "
        "discharge (charge) more than 0.05 of the capacity (`soc_pinned`), the OCV curve held beyond its 0.05 "
        "extrapolation band (`ocv_held`), or a predicted voltage outside [½·U_oc(empty), 1.5·U_oc(full)] "
        "(`voltage_implausible`). Cells marked † were computed before the `soc_pinned` rule, when every sample "
        "the clamp held at 0 counted (the end of a test to empty included).",
        "",
        "## Causes found and fixed",
        "",
        "- **fang + ukf, every run of every scenario (30 of the default study's 1920 runs before this sweep "
        "existed).** The fit takes Fang's τ2 to a few thousandths, so `ln(τ2 + 1 − z)` is undefined above "
        "z = 1 + τ2 ≈ 1.007. A flight starts near full; the UKF's sigma points at z ± σ0 (σ0 = 0.1) reached "
        "z ≈ 1.1, the model returned NaN and every run failed at sample 0 with a non-finite state. Fixed in "
        "socbench/models/static_terms.py: both logarithms go through the shared floor `floored_log` "
        "(socbench/models/blocks.py, B6: argument floored at ε = 1e-3, derivative 0 there, counted as "
        "`singular_eps`), as the other singular terms already did.",
        "- **Every fit on the five scenarios with on-board BMS sensors (nominal, cold, current-bias, dropout, harsh), "
        "hence all their cells, in the first run of this sweep.** Their characterisation HPPC is measured by the "
        "scenario's own current sensor (0.3–1 A noise, 0.2–0.8 A offset); the HPPC analysis took a rest to be "
        "|I| ≤ 0.5 % of the peak current (0.12 A), found none, and every fit stopped with \"the record has no HPPC "
        "rest points\". Fixed by the HPPC analysis that sets its rest level from the record's own noise and offset "
        "(socbench/identify/hppc.py, issue 13).",
        "- **hinf, above all on harsh (94 failed runs, every failed run of the sweep of 2026-11-25: SOC variance "
        "above `var_max`).** The feasibility margin let each capped update double the SOC's Riccati term, "
        "`P⁺_zz = P_K,zz/(1 − ρ)`, however little the sample said about the SOC; where one sample shrinks `P_zz` by "
        "less than half (noisy sensors, a flat OCV, a fast rate) it grew until the run failed (on the measured "
        "Panasonic US06 at 10 Hz: 30 of 30 runs, docs/measured_starts.md). Fixed by the prior cap "
        "(socbench/estimators/hinf.py): `θ_k ≤ 1/P_K,zz − 1/P⁻_zz`, so that no update widens the SOC beyond its "
        "prior.",
        "- **improved_rc on harsh, every filter's cell (found by the rerun for the prior cap).** Fitted on the harsh "
        "scenario's noisy HPPC, its R2 polynomial dipped to −2.4e-5 Ω near SOC 0.013 between two positive nodes "
        "(the positivity term is soft), and the noise recipe's open loop refused the model (`R1 + R2 ≤ 0`); the "
        "dp, gnl, thevenin and pngv fits of that HPPC also had a resistance below zero there, on a part of the SOC "
        "axis their runs did not reach. Fixed in socbench/identify/fit.py: a finished fit with a positive SOC "
        "polynomial at or below zero is refitted with the term 1000× heavier, and says so.",
        "",
        "## Reproduce",
        "",
        f"    {command}",
        "",
        "`--seeds`, `--models`, `--estimators`, `--scenarios` slice the grid; the study store under `--out` makes an "
        "interrupted sweep resume. tests/test_robustness.py runs a small slice of it in CI and asserts 0 NaN/inf.",
    ]
    return "\n".join(lines) + "\n"


def _jsonable(o):
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


def _terminate(signum, frame):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=DEFAULT_SEEDS, help=f"seeds 0..N-1 per cell (default {DEFAULT_SEEDS})")
    ap.add_argument("--models", help="comma-separated models (default: every registered model)")
    ap.add_argument("--estimators", help="comma-separated estimators (default: every registered estimator)")
    ap.add_argument("--scenarios", help="comma-separated scenarios (default: the whole catalog)")
    ap.add_argument("--backend", default="process", help="serial, process or dask (default process)")
    ap.add_argument("--jobs", type=int, default=None, help="worker processes (default: every core)")
    ap.add_argument("--out", default=DEFAULT_OUT, help=f"study store and robustness.json (default ./{DEFAULT_OUT})")
    ap.add_argument("--doc", default=str(DEFAULT_DOC),
                    help="write the Markdown report here (default docs/reliability.md)")
    ap.add_argument("--no-doc", action="store_true", help="do not write the Markdown report")
    ap.add_argument("--recompute-stale", action="store_true", help="recompute cells computed by older code")
    ap.add_argument("--report-only", action="store_true",
                    help="compute nothing: report the cells already in the store (a sweep running elsewhere)")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error("--seeds must be at least 1")

    toolkit = Toolkit()
    config = build_config(args, toolkit)
    out = Path(args.out)
    store = Store(out / "store")
    print(f"robustness sweep: {len(config.models)} models × {len(config.estimators)} estimators × "
          f"{len(config.scenarios)} scenarios × {len(config.seeds)} seeds = {config.n_cells} cells → {out}",
          flush=True)
    t0 = time.perf_counter()
    previous = signal.signal(signal.SIGTERM, _terminate)  # `kill PID` stops the sweep as cleanly as Ctrl-C
    try:
        result = run_study(config, store, backend=args.backend, jobs=args.jobs, toolkit=toolkit,
                           log=lambda msg: print(f"  {msg}", file=sys.stderr, flush=True),
                           recompute_stale=args.recompute_stale, compute=not args.report_only)
    except KeyboardInterrupt:
        print("interrupted: every finished cell is in the store; rerun the same command to resume", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    an = analyse(result, store)
    atomic_write_text(out / "robustness.json", json.dumps(an, indent=1, default=_jsonable))
    nan = an["nan_inf"]
    total_nan = nan["outputs"] + nan["metrics"] + nan["table"]
    partial = f" (of {an['grid_cells']}: report only)" if an["missing_cells"] else ""
    print(f"{an['cells']} cells{partial}, {an['runs']} runs in {time.perf_counter() - t0:.0f} s: NaN/inf {total_nan}; "
          f"failed runs {an['failed_runs']} ({100 * an['failed_rate']:.2f} %) in {an['cells_with_failures']} cells; "
          f"{len(an['cells_that_threw'])} cells threw; {len(an['out_of_domain'])} cells ≥ 1 % out of domain")
    for c in an["worst"][:5]:
        print(f"  {c['model']} + {c['estimator']} on {c['scenario']}: {c['failed_runs']}/{c['n_runs']} failed — "
              f"{explain(c)}")
    if not args.no_doc:
        cmd = "python benchmarks/robustness.py" + "".join(
            f" --{k} {v}" for k, v in (("seeds", args.seeds if args.seeds != DEFAULT_SEEDS else None),
                                       ("models", args.models), ("estimators", args.estimators),
                                       ("scenarios", args.scenarios)) if v is not None)
        atomic_write_text(args.doc, markdown(an, cmd))
        print(f"wrote {out / 'robustness.json'} and {args.doc}")
    return 0 if total_nan == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
