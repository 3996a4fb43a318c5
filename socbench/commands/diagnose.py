"""``socbench diagnose --fit PATH [PATH] --eval PATH [PATH ...] --model NAME --out DIR``.

Fits ``NAME`` on the fit data (one dynamic record, plus optionally a slow OCV test; the fit setting chosen by
validation on the evaluation data), finds from its residual on the evaluation data which effect of ECM_SPEC §9 it
lacks, adds it, refits, and repeats while the held-out voltage RMSE (blocked cross-validation over every evaluation
record) falls by ≥ 10 %. Writes ``diagnosis.json`` (DESIGN.md keys), ``diagnosis.md`` and figures to ``DIR``.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..checks import check_current_against_reference, check_same_cell
from ..datasets import load
from ..diagnose import diagnose
from ..diagnose.core import COARSE_OCV_GAP, SOC_WORSE
from ..diagnose.report import alike_sentence, write_report
from ..domain import warn_outside
from ..errors import ConfigError, SocbenchWarning
from ..identify.hppc import NO_KNEE
from ..io import output_dir
from ..models import model_names
from ..models.effects import effect_names

#: ``--refine-ocv`` → the diagnosis' ``refine_ocv`` (socbench.diagnose.core.fit_base); the benchmarks that run the
#: diagnosis in-process read the option the same way
REFINE_OCV_OPTION = {"coarse": "coarse", "always": True, "never": False}


def add_arguments(parser) -> None:
    parser.add_argument("--fit", required=True, nargs="+", metavar="PATH",
                        help="fit data: one dynamic record (HPPC, drive cycle), optionally plus a slow OCV test")
    parser.add_argument("--eval", required=True, nargs="+", metavar="PATH",
                        help="evaluation data: every record is cut into --folds blocks for the held-out scoring")
    parser.add_argument("--model", required=True, help="base model name (see `socbench models`)")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--format", default="auto", help="data format of every file (default auto)")
    parser.add_argument("--mode", default="auto", choices=("auto", "constant", "paper", "lookup"),
                        help="identification mode of the base model (default auto: chosen by validation)")
    parser.add_argument("--dt", type=float, default=1.0, help="average the evaluation data to bins of DT s")
    parser.add_argument("--folds", type=int, default=4,
                        help="blocks per evaluation record for the blocked cross-validation (default 4)")
    parser.add_argument("--no-base-refit", action="store_true",
                        help="never refit the base model's own parameters on the evaluation data")
    parser.add_argument("--effects", help="comma-separated candidate effects (default: all)")
    parser.add_argument("--slow-ocv", default="mean", choices=("mean", "discharge"),
                        help="OCV from a slow test in the fit data: mean of both branches, or the discharge branch")
    parser.add_argument("--refine-ocv", default="always", choices=tuple(REFINE_OCV_OPTION),
                        help="refine an HPPC's rest-point OCV between its points from its step segments (kept "
                             "when the evaluation data validate it): where two points lie more than "
                             f"{100 * COARSE_OCV_GAP:g} %% of SOC apart (coarse), always (default), or never")
    parser.add_argument("--capacity", type=float, default=None,
                        help="capacity [Ah] of the dynamic fit record's SOC axis (default: the slow OCV test's, else "
                             "the record's declared one, else the HPPC's own: the charge it moves from full to its "
                             "most discharged point, or over its reference SOC's span where that is less)")
    parser.add_argument("--soc0", type=float, default=None,
                        help="SOC of the dynamic fit record's first sample (default: counted back from the HPPC's "
                             "full point, or where its own reference SOC puts it)")
    parser.add_argument("--no-soc", action="store_true", help="skip the EKF SOC comparison")
    parser.add_argument("--no-figures", action="store_true", help="skip the figures")


#: evaluation records that never draw more than this C-rate are at rest throughout (a warning says so)
NO_LOAD_C = 0.05


def _resolved(path: str) -> str:
    """``path`` as one file on disk (``builtin:`` names as given)."""
    return path if ":" in path and not Path(path).exists() else str(Path(path).resolve())


def _warn_what_the_records_cannot_test(args, evals) -> None:
    """One warning each (after a diagnosis that ran: a refused one says only why) where the evaluation records are at
    rest throughout (at most :data:`NO_LOAD_C`) or include a fit record (the held-out errors are then in sample)."""
    loads = [float(np.max(np.abs(e.current_a))) / q for e in evals if (q := e.meta.capacity_ah or args.capacity)]
    if loads and max(loads) < NO_LOAD_C:  # rests only: nothing under load for the held-out scores to test
        warnings.warn(f"{', '.join(args.eval)}: the evaluation records draw at most {max(loads):.2g}C: at rest "
                      "throughout, they test the OCV and the relaxation, not what the model predicts under load",
                      SocbenchWarning, stacklevel=3)
    for path in sorted(set(map(_resolved, args.eval)) & set(map(_resolved, args.fit))):  # scored where it was fitted
        warnings.warn(f"{path}: given as --fit and as --eval: the held-out errors are measured on the record the base "
                      "model was fitted on, so they say how well it fits, not how well it predicts", SocbenchWarning,
                      stacklevel=3)


def run(args) -> int:
    if args.model not in model_names():
        raise ConfigError(f"unknown model '{args.model}'; known: {', '.join(model_names())}")
    candidates = None
    if args.effects is not None:
        candidates = [e.strip() for e in args.effects.split(",") if e.strip()]
        if not candidates:  # an empty list would be read as "all" by the search and as "none" by the fit test
            raise ConfigError(f"--effects is empty; known: {', '.join(effect_names())}")
        bad = [e for e in candidates if e not in effect_names()]
        if bad:
            raise ConfigError(f"unknown effect '{bad[0]}'; known: {', '.join(effect_names())}")
    if not 2 <= args.folds <= 20:
        raise ConfigError(f"--folds must be in [2, 20], got {args.folds}")
    if not 0 < args.dt < float("inf"):
        raise ConfigError(f"--dt must be a positive, finite number of seconds, got {args.dt}")
    if args.capacity is not None and not 0 < args.capacity < float("inf"):
        raise ConfigError(f"--capacity must be a positive, finite number of Ah, got {args.capacity}")
    if args.soc0 is not None and not 0.0 <= args.soc0 <= 1.0:
        raise ConfigError(f"--soc0 must be a fraction in [0, 1], got {args.soc0}")
    output_dir(args.out, "--out")
    fit = [load(p, args.format) for p in args.fit]
    evals = [load(p, args.format) for p in args.eval]
    for e in evals:
        check_same_cell(e, fit, "an --eval record")
    diag = diagnose(args.model, fit, evals, mode=args.mode, dt=args.dt, folds=args.folds, candidates=candidates,
                    slow_ocv=args.slow_ocv, soc=not args.no_soc, base_refit=not args.no_base_refit,
                    refine_ocv=REFINE_OCV_OPTION[args.refine_ocv],
                    capacity_ah=args.capacity, soc0=args.soc0)
    write_report(diag, args.out, with_figures=not args.no_figures)
    _warn_what_the_records_cannot_test(args, evals)
    b, a = diag.before, diag.after
    print(f"{args.model}: effects added: {', '.join(diag.effects_added) or 'none'}")
    print(f"  held-out voltage RMSE {1000 * b['rmse_v']:.2f} -> {1000 * a['rmse_v']:.2f} mV")
    for name, r in (b.get("soc") or {}).items():
        after = a["soc"][name]["soc_rmse"]
        print(f"  held-out SOC RMSE ({name.upper()}) {100 * r['soc_rmse']:.2f} -> {100 * after:.2f} %")
    for s in diag.steps:
        print(f"  + {s.effect}: {s.evidence}")
    print(f"  wrote {args.out}/diagnosis.json, diagnosis.md ({diag.seconds['total']:.1f} s)")
    if diag.fit.get("capacity_note"):
        print(f"  note: {diag.fit['capacity_note']}")
    for note in diag.fit.get("evaluation_records_cut", ()):
        print(f"  note: {note}")
    for name in diag.soc.get("worse", ()):  # the diagnosis gives "attribution" wherever a filter got worse
        grew = a["soc"][name]["soc_rmse"] - b["soc"][name]["soc_rmse"]
        counted = diag.soc["attribution"]["after"]["voltage_ignored"][name]
        print(f"  note: the {name.upper()}'s held-out SOC error grew by {100 * grew:.2f} points with what the search "
              f"added (more than {100 * SOC_WORSE:.1f}); with the voltage ignored (the current counted) its filter "
              f"reaches {100 * counted:.2f} %; diagnosis.md says where it comes from")
    for s in diag.steps:
        alike = diag.alike(s)
        if alike:
            print(f"  note: {alike_sentence(s.effect, alike)}")
    for p in evals:
        check_current_against_reference(p, p.meta.capacity_ah or diag.base_model.capacity_ah,
                                        "the voltage and SOC errors")
    for note in (n for n in diag.base_model.params.notes if n.startswith(NO_KNEE)):
        warnings.warn(f"{diag.fit.get('fitted_on', 'fit record')}: {note}", SocbenchWarning, stacklevel=2)
    for when, model in (("before", args.model), ("after", "+".join([args.model, *diag.effects_added]))):
        report = diag.domain.get(when)
        if report:
            warn_outside(report, f"{model} on the evaluation records")
    return 0
