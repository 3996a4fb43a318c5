"""``socbench fit --data PATH [PATH …] --model NAME --out PARAMS.json [--validation PATH …] [--mode …]``.

Fits a registered model to an identification record (normally an HPPC test) with
:func:`socbench.identify.fit_model` and writes a self-contained parameter file (model, capacity, OCV curve, parameter
functions) with a ``"fit"`` block (mode, RMSE, standard errors, warnings, seconds, and for a single record ``domain``:
:func:`socbench.domain.domain_report` of the fitted model along the fitted record, with its segment count) that
``socbench simulate --params`` reads back. Without ``--ocv`` the OCV curve comes from the record's HPPC rest points. A
record of several discharges (battery swaps, recharges) is fitted segment by segment (:mod:`socbench.segments`;
``--no-segments`` fits it as one piece). ``--refine-ocv`` refines that curve between the rest points from the record's
step segments (its charge steps in an HPPC run in the charge direction) and fits again
(:func:`socbench.identify.pseudo_ocv.refit_on_refined_ocv`: the refit is kept when
no RC branch is slower than the record, it fits the record 10 % better and, with ``--validation`` records, it predicts
them no worse).

Several ``--data`` records (one per temperature: Panasonic HPPCs at 25, 10, 0, −10, −20 °C) are fitted each and
assembled into one temperature-aware set (:func:`socbench.identify.temperature.fit_temperatures`): parameter tables over
SOC × temperature, an OCV per temperature on one SOC axis, and the capacity per temperature
(``capacity_by_temperature``). Each record's temperature is the median of its temperature column (else the ambient
temperature of its file name); the command says which. ``--charge-transfer`` adds the Butler–Volmer charge-transfer
term with an Arrhenius exchange current ``I0(T)``, fitted with the base model on each record (``fit_temperatures(...,
charge_transfer=True)``); the file carries it as an ``"effects"`` entry, which every command that reads the file runs.

``--mode auto`` chooses how to fit by validation on the ``--validation`` records (needed then): every SOC form and
sample weighting of :data:`socbench.identify.FIT_SETTINGS`, and over several records also a setting per temperature
and the charge-transfer term, each kept when it predicts the validation records better
(:func:`socbench.identify.select_temperature_fit`; :func:`~socbench.identify.select_fit` for one record). The command
prints every candidate's validation RMSE and the one kept.

The noise recipe (:mod:`socbench.estimators.model_error`) measures the fitted model's voltage error on the
``--validation`` records (other drive cycles of the same cell, never one you will score), else on the identification
records as the fit saw them (their current less the sensor offset their rests read), and stores it as
``"model_error"`` (with ``measured_on``: which of the two); ``socbench estimate`` builds the filter covariances from it
by default. Measured on the identification records it is too small for a drive cycle (an
HPPC shows no sustained load; docs/real_data.md section 4g): both commands say so. Measured on ``--validation``
records, its size is then calibrated there (:mod:`socbench.estimators.nis_calibration`): the EKF and the particle
filter, run on those records with the recipe and ``socbench estimate``'s default sensor noise, should average a NIS of
1; the factor each needed is stored as ``model_error.nis_scale`` and the command prints it.
"""

from __future__ import annotations

import json
import warnings as _warnings
from pathlib import Path

import numpy as np

from ..checks import check_current_against_reference, check_same_cell
from ..datasets import load
from ..domain import warn_outside
from ..errors import ConfigError, DataError, SocbenchWarning
from ..estimators import DEFAULT_NOISE, model_error, nis_calibration
from ..identify import FIT_SETTINGS, MODES, fit_model, select_fit, select_temperature_fit
from ..identify.hppc import COUNTED_ALIKE, NO_KNEE, analyze_hppc, declared_capacity
from ..identify.pseudo_ocv import refit_on_refined_ocv
from ..identify.start_soc import place_start
from ..identify.temperature import fit_temperatures
from ..io import output_file
from ..models import make_model, model_class, save_params
from ..ocv import OCVCurve

#: the --mode that chooses the fit setting by validation
AUTO = "auto"


def add_arguments(parser) -> None:
    parser.add_argument("--data", required=True, nargs="+",
                        help="identification record(s) (HPPC), or builtin:hppc; several records = one per temperature")
    parser.add_argument("--model", required=True, help="model name (see `socbench models`)")
    parser.add_argument("--out", required=True, help="write the fitted PARAMS.json here")
    parser.add_argument("--format", default="auto", help="data format (default auto)")
    parser.add_argument("--mode", default="paper", choices=MODES + (AUTO,),
                        help="paper: SOC polynomials for models 1-6, constants otherwise (default); "
                             "constant; lookup: piecewise linear in SOC; auto: the setting that predicts the "
                             "--validation records best (SOC form, sample weighting; over several records also a "
                             "setting per temperature and the charge-transfer term)")
    parser.add_argument("--capacity", type=float, default=None,
                        help="capacity [Ah] of the SOC axis (default: the one a canonical CSV's sidecar declares, "
                             "where the HPPC stops above empty; else the charge the HPPC moves between full and its "
                             "most discharged point, down from full or, run in the charge direction, up to it, or, "
                             "where the record's own reference SOC (soc_ref column) says the test spans less, that "
                             "charge over the reference's span; with several records the largest of them)")
    parser.add_argument("--soc0", type=float, default=None,
                        help="initial SOC of the record (default: counted back from the HPPC's full point: 1 for "
                             "one that starts full; where the record's own reference SOC says its top lies below "
                             "full, there; an HPPC without one that starts part charged is placed by the "
                             "--validation records' reference SOC where they read it 2 points or more lower)")
    parser.add_argument("--ocv", default=None,
                        help="OCV curve JSON ({soc, voltage}) or a PARAMS.json whose curve to use "
                             "(default: the record's HPPC rest points)")
    parser.add_argument("--no-segments", action="store_true",
                        help="fit the record as one piece, through its gaps (default: restart each segment)")
    parser.add_argument("--charge-transfer", action="store_true",
                        help="with records at several temperatures: fit the Butler-Volmer charge-transfer term "
                             "(an Arrhenius exchange current I0(T)) together with the model")
    parser.add_argument("--refine-ocv", action="store_true",
                        help="one HPPC record, OCV from its rest points: refine the curve between the points from "
                             "its step segments (discharge, or charge in the charge direction) and fit again; the "
                             "refit is kept when no RC branch is slower "
                             "than the record, it fits the record 10%% better and, with --validation records, it "
                             "predicts them no worse")
    parser.add_argument("--validation", nargs="+", default=(),
                        help="records (with a reference SOC) on which the noise recipe measures the model error "
                             "(default: the identification records)")


def _read_ocv(path: str) -> OCVCurve:
    p = Path(path)
    try:
        d = json.loads(p.read_text())
    except FileNotFoundError:
        raise DataError("file not found", file=path) from None
    except json.JSONDecodeError as exc:
        raise DataError(f"not valid JSON ({exc.msg} at line {exc.lineno})", file=path) from None
    if isinstance(d, dict) and "ocv" in d:
        d = d["ocv"]
    if not isinstance(d, dict):
        raise ConfigError(f"{path}: expected an OCV object with 'soc' and 'voltage'")
    try:
        return OCVCurve.from_dict(d)
    except DataError as exc:
        raise exc.with_file(path) from None


def _load_single(path: str, fmt: str):
    profile = load(path, fmt)
    if profile.batched:
        raise DataError("fit needs a single record, not a batch of runs", file=str(path))
    return profile


def run(args) -> int:
    if args.capacity is not None and not 0 < args.capacity < float("inf"):
        raise ConfigError(f"--capacity must be a positive, finite number of Ah, got {args.capacity}")
    if args.soc0 is not None and not 0.0 <= args.soc0 <= 1.0:
        raise ConfigError(f"--soc0 must be in [0, 1], got {args.soc0}")
    several = len(args.data) > 1
    if several and (args.soc0 is not None or args.ocv):
        raise ConfigError("--soc0 and --ocv apply to a single record; with several --data records each record's HPPC "
                          "gives its own start and OCV")
    if args.refine_ocv and (several or args.ocv):
        raise ConfigError("--refine-ocv refines the OCV of one HPPC record's rest points: not with --ocv or several "
                          "--data records")
    auto = args.mode == AUTO
    if auto and not args.validation:
        raise ConfigError("--mode auto chooses the fit setting on --validation records: give at least one")
    if auto and (args.charge_transfer or args.refine_ocv):
        raise ConfigError("--mode auto tries the charge-transfer term itself and does not refine the OCV: drop "
                          "--charge-transfer / --refine-ocv")
    if args.charge_transfer and not several:
        raise ConfigError("--charge-transfer fits the exchange current's temperature law: give one HPPC record per "
                          "temperature, at least two")
    model_class(args.model)  # an unknown model fails before the data is read
    output_file(args.out, "--out")
    ocv = _read_ocv(args.ocv) if args.ocv else None
    records = [_load_single(p, args.format) for p in args.data]
    validation = [_load_single(p, args.format) for p in args.validation]
    for v in validation:
        if v.get("soc_ref") is None:  # a reference given but refused raises its own error
            raise DataError("a validation record needs a reference SOC (the model error is measured at the true "
                            "SOC)", file=v.meta.source or v.name, column="soc_ref")
        check_same_cell(v, records, "a --validation record")
    if several:
        if auto:
            sel = select_temperature_fit(args.model, records, validation, capacity_ah=args.capacity)
            _print_choice(sel.tried, sel.chosen)
            res = sel.fit
        else:
            res = fit_temperatures(args.model, records, mode=args.mode, capacity_ah=args.capacity,
                                   charge_transfer=args.charge_transfer)
        params, summary = res.params, res.fit_summary()
        print(f"{args.model} fitted at {len(res.temps)} temperatures ({res.mode} mode) on one SOC axis "
              f"(Q_ref {res.capacity_ref:.4g} Ah) in {res.seconds:.1f} s:")
        for t, name, how, q, f in zip(res.temps, res.sources, res.temperature_notes, res.capacities, res.fits):
            print(f"  {t:6.1f} °C  {name}: RMS {1000 * f.rmse_v:.1f} mV over {f.n_samples} samples, "
                  f"capacity {q:.4g} Ah; temperature = {how}")
            for note in _left_out(f):
                print(f"            note: {note}")
        for note in res.notes[1:]:
            print(f"  note: {note}")
        warnings = res.warnings
    else:
        profile = records[0]
        capacity = args.capacity
        if capacity is None and profile.meta.extra.get("format") == "canonical":  # the user's sidecar declares it
            capacity, why_not = declared_capacity(profile, profile.meta.capacity_ah, full_to_empty="count")
            if capacity is not None:
                print(f"capacity {capacity:.4g} Ah as the record's sidecar declares it (--capacity overrides)")
            elif why_not:
                print(f"note: {why_not}")
        # a capacity the reference SOC contradicts (given in mAh, say): said before the fit counts with it
        check_current_against_reference(profile, capacity or profile.meta.capacity_ah, "the fitted parameters")
        soc0 = args.soc0
        if soc0 is None and ocv is None and validation:  # an HPPC without a reference placed by the records' one
            soc0, capacity, placed = place_start(args.model, profile, capacity, validation)
            if soc0 is not None:
                print(f"start SOC {soc0:.3f}, capacity {placed['capacity_ah']:.4g} Ah ({placed['capacity_from']}), "
                      f"read off the --validation records' reference SOC: their open-loop RMS "
                      f"{1000 * placed['rmse_v'][0]:.1f} → {1000 * placed['rmse_v'][1]:.1f} mV (--soc0 overrides)")
            elif placed is not None and placed.get("capacity_kept"):
                print(f"capacity {capacity:.4g} Ah read off the --validation records' reference SOC: "
                      f"{placed['capacity_note']} (--capacity overrides)")
        kw = {"ocv": ocv, "capacity_ah": capacity, "soc0": soc0,
              "segments": False if args.no_segments else None}
        if auto:
            sel = select_fit(args.model, profile, validation, candidates=FIT_SETTINGS, **kw)
            _print_choice({k: {"mean_rmse_v": float(np.mean(v))} for k, v in sel.scores.items()}, sel.chosen)
            res = sel.fit
        else:
            res = fit_model(args.model, profile, mode=args.mode, **kw)
        params, summary = res.params, res.fit_summary()
        print(f"{args.model} fitted on {profile.name} ({res.mode} mode): RMS {1000 * res.rmse_v:.1f} mV over "
              f"{res.n_samples} samples in {res.seconds:.1f} s")
        for note in _left_out(res) + _axis_notes(res):
            print(f"  note: {note}")
        for note in (n for n in res.params.notes if n.startswith(NO_KNEE)):
            _warnings.warn(f"{profile.name}: {note}", SocbenchWarning, stacklevel=2)
        if args.refine_ocv:
            res = _refine(res, profile, validation, mode=args.mode, soc0=soc0,
                          segments=False if args.no_segments else None)
            params, summary = res.params, res.fit_summary()
        if res.lsq is not None and res.lsq.domain.get("samples"):
            warn_outside(res.lsq.domain, f"{args.model} fitted on {profile.name}")
        if profile.temperature_c is not None:  # a set without temperature tables is valid where it was measured
            summary = {**summary, "temperature_c": float(np.median(profile.temperature_c))}
        warnings = res.warnings
    model = make_model(args.model, params)
    stats, used = _model_error(model, records, validation)
    save_params(args.out, args.model, params, fit=summary,
                **({"model_error": stats.to_dict()} if stats is not None else {}))
    if stats is not None:
        sm = stats.summary()
        print(f"noise recipe on {used}: model error (RMS over SOC) slow {_mv(sm['slow'])} mV "
              f"(τ {stats.tau_slow_s:.0f} s and {stats.tau_mid_s:.0f} s), fast {_mv(sm['fast'])} mV "
              f"(τ {stats.tau_fast_s:.1f} s), resistive {_mv(sm['r'])} mΩ (τ {stats.tau_r_s:.0f} s), "
              f"white {_mv(sm['white'])} mV at "
              f"{', '.join(f'{t:.1f}' for t in stats.temps)} °C")
        if stats.nis_scale:
            loads = dict(stats.nis_load)
            print("NIS calibration on the validation records: model-error variances × " + ", ".join(
                f"{a:.2f} ({nis_calibration.CALIBRATED_WITH[f]}, {f}"
                + (f"; × (I_rms/{np.sqrt(loads[f][1]):.3g} A)^{2 * loads[f][0]:.2f} between "
                   f"{np.sqrt(loads[f][2]):.3g} and {np.sqrt(loads[f][3]):.3g} A" if f in loads else "") + ")"
                for f, a in stats.nis_scale))
    for note in _validation_notes(args, stats):
        print(f"note: {note}")
    print(f"{len(warnings)} fit warning(s); wrote {args.out}")
    for w in warnings[:5]:
        print(f"  warning: {w}")
    if len(warnings) > 5:
        print(f"  ... {len(warnings) - 5} more in {args.out} (fit.warnings)")
    return 0


def _print_choice(tried: dict, chosen: str) -> None:
    """One line per candidate setting of ``--mode auto``: its mean validation RMSE (or why it failed), the kept one
    marked."""
    print("fit setting chosen by validation (mean open-loop RMSE on the --validation records):")
    for label, out in tried.items():
        text = f"{1000 * out['mean_rmse_v']:.1f} mV" if "mean_rmse_v" in out else f"failed ({out['error']})"
        print(f"  {'*' if label == chosen else ' '} {label}: {text}")


def _refine(res, profile, validation, **fit_kwargs):
    """``res``, or its refit on the OCV refined between the rest points when that is kept
    (:func:`socbench.identify.pseudo_ocv.refit_on_refined_ocv`); one line says what was measured."""
    refit, report = refit_on_refined_ocv(res, profile, validation, **fit_kwargs)
    if not report["refined"]:
        print("OCV not refined: the record has no discharge between two of its rest points")
        return res
    line = (f"OCV refined between its {report['ocv_points'][0]} rest points ({report['ocv_points'][1]} points): fit "
            f"RMS {1000 * report['fit_rmse_v'][0]:.1f} → {1000 * report['fit_rmse_v'][1]:.1f} mV")
    if "validation_rmse_v" in report:
        line += (f", validation RMS {1000 * report['validation_rmse_v'][0]:.1f} → "
                 f"{1000 * report['validation_rmse_v'][1]:.1f} mV")
    if refit is not None:
        print(line + "; kept")
        return refit
    print(line + f"; not kept ({report['why_not']})")
    return res


def _mv(values) -> str:
    return "/".join(f"{1000 * v:.1f}" for v in values)


def _axis_notes(fit) -> list[str]:
    """The notes of a fit that say where its record's reference SOC placed the HPPC on the SOC axis
    (:func:`socbench.identify.hppc.reference_placement`), or that its pulses were counted alike
    (:func:`socbench.identify.hppc.pulse_count_correction`)."""
    return [n for n in fit.params.notes if "reference SOC places the test" in n or COUNTED_ALIKE in n]


def _left_out(fit) -> list[str]:
    """The notes of a fit that say which part of its record it left out (``socbench.identify.fit``: the charge before
    an HPPC reaches full, samples beyond the OCV's rest points): the RMS printed is over the rest."""
    return [n for n in fit.params.notes if "left out of the fit" in n]


def _validation_notes(args, stats) -> list[str]:
    """What the fit and its noise recipe did not validate (measured on the Panasonic US06 runs: docs/real_data.md
    section 4g, the HPPC-only campaign's filters against the validated one's)."""
    notes = []
    if stats is not None and stats.measured_on == "identification":
        notes.append("the model error was measured on the identification records only (an HPPC shows no sustained "
                     "load): on a drive cycle the error is larger and the filters' ±3σ band too narrow; give "
                     "--validation DRIVE... (records of the same cell with a reference SOC) for an honest band")
    if args.validation and args.mode != AUTO:
        notes.append(f"fitted in the {args.mode} mode as asked: --mode auto would choose the setting that predicts "
                     "the --validation records best")
    return notes


def _model_error(model, records, validation):
    """The noise recipe's statistics and which records it used (None when no record has a known SOC).

    Without ``--validation`` it measures on the identification records as the fit saw them (:func:`_as_fitted`): the
    current less the sensor offset their rests read, and where a record has no reference SOC its HPPC SOC axis
    (counted from full with the model's capacity, :func:`~socbench.identify.hppc.analyze_hppc`), the axis the fit
    itself placed it on."""
    if validation:
        stats = model_error.estimate(model, validation, measured_on="validation")
        return (nis_calibration.calibrate_forms(model, DEFAULT_NOISE, stats, validation),
                f"{len(validation)} validation record(s)")
    usable = [_as_fitted(r, model.capacity_ah) for r in records]
    usable = [r for r in usable if r is not None]
    if not usable:
        print("note: no identification record has a reference SOC or an HPPC SOC axis: no model_error block (the "
              "noise recipe needs a known SOC)")
        return None, ""
    counted = sum(r.soc_ref is None for r in records)
    how = f", {counted} on its HPPC SOC axis" if counted else ""
    return (model_error.estimate(model, usable, measured_on="identification"),
            f"the {len(usable)} identification record(s) (no --validation{how})")


def _as_fitted(record, capacity_ah: float):
    """``record`` as the fit saw it, or None when it has no reference SOC and is not an HPPC.

    The fit runs the model on the current less the offset the current sensor reads on the HPPC's rests
    (:attr:`~socbench.identify.hppc.HPPCAnalysis.current_offset_a`); the recipe measures the model's error on that
    same current. On the raw current the offset's charge would run the open-loop SOC off the axis (0.2 % of 1C over a
    10 h HPPC: 2 points), and that drift, the lab sensor's and not the model's, would be read as a slow model error
    (20 mV on an NMC cell) that widens every filter built from the recipe. A record without a reference SOC gets its
    HPPC SOC axis as the reference."""
    try:
        analysis = analyze_hppc(record, capacity_ah=capacity_ah)
    except (ConfigError, DataError):
        return record if record.soc_ref is not None else None
    soc = record.soc_ref if record.soc_ref is not None else np.clip(analysis.soc, 0.0, 1.0)
    return record.with_(current_a=record.current_a - analysis.current_offset_a, soc_ref=soc)
