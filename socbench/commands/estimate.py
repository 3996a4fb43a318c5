"""``socbench estimate --data PATH --params PARAMS.json --estimator NAME [--soc0 Z] [--noise model|sensor] --out DIR``
(NAME: any registered estimator, ``socbench.estimators.ESTIMATORS``: coulomb, ekf, ukf, pf, aekf, ckf, srukf, hinf,
dual).

Writes ``DIR/estimate.csv`` (``time_s, soc, soc_std, v_pred, innovation``, plus ``innovation_var``) and
``DIR/metrics.json`` (``soc_rmse, soc_max_abs, rmse_v, nis_mean`` and, when the data carries a reference SOC,
``nees_mean, frac_within_3sigma``; the SOC keys are null without one; ``nis_band`` is the two-sided 95 % χ² band of
the NIS mean). An estimator that tracks parameters (``dual``) adds each final estimate and its 3σ half-width:
``capacity_ah, capacity_ah_3sigma, r0_ohm, r0_ohm_3sigma`` (one number per run: a float for a single record, else a
list), and a ``parameters`` list naming them. ``--data builtin:hppc`` and ``--params paper:MODEL`` name the embedded
profile and Table 3 sets.

Noise (``--noise``): ``model`` (default) builds the filter covariances from the parameter file's ``model_error`` block
(:mod:`socbench.estimators.model_error`: the fitted model's voltage error measured by ``socbench fit``), so that the
±3σ band covers the model's error too; ``sensor`` uses the sensor noise alone. A file without that block (files
from older versions) falls back to ``sensor`` with a warning; a ``paper:`` set (no identification data) silently
(``metrics.json`` says which was used, ``noise.mode``). The coulomb counter never reads the voltage:
it always uses the sensor noise.

SOC axis: the SOC written, scored and given as ``--soc0`` follows the data's own definition when its loader counted the
reference with a capacity (Panasonic, CALCE: :mod:`socbench.socaxis`); the filter runs on the model's axis.

A record of several discharges (battery swaps, recharges) is filtered segment by segment, each restarting the filter
as at the record's start (:mod:`socbench.segments`); ``--no-segments`` filters it as one piece. ``metrics.json``
also holds ``failed_reason`` (why each failed run diverged), ``segments``, ``logger_pauses`` (the steps across which
the band widened for the current the hold misses, :func:`socbench.segments.pause_report`), ``domain``
(:func:`socbench.domain.estimate_domain`) and ``guard_fractions``; a warning line is printed when ≥ 1 % of the
samples lie outside the model's domain.
"""

from __future__ import annotations

import json
import math
import warnings

from ..checks import (
    check_capacity,
    check_current_against_reference,
    check_reference_axis,
    check_temperature_range,
    check_voltage_level,
)
from ..datasets import load
from ..domain import guard_fractions, warn_outside
from ..errors import ConfigError, DataError, SocbenchWarning
from ..estimators import SensorNoise, estimator_class, estimator_names, make_estimator
from ..estimators import model_error as recipe
from ..estimators.scoring import LOST_MIN_S, LOST_SIGMA, error_state_excess, score
from ..identify.hppc import NO_KNEE
from ..io import atomic_write_frame, atomic_write_text, output_dir
from ..models import make_model
from ..segments import pause_message, pause_report
from ..socaxis import run_on_data_axis, soc_axis
from .simulate import fitted_at_c, params_block, resolve_params

#: the fewest particles ``--particles`` takes (2 gave an SD of ~0 and a NEES of 1e15 with exit code 0)
MIN_PARTICLES = 50


def add_arguments(parser) -> None:
    parser.add_argument("--data", required=True, help="profile file, or builtin:hppc / builtin:1c")
    parser.add_argument("--params", required=True, help="PARAMS.json from `socbench fit`, or paper:MODEL")
    parser.add_argument("--estimator", required=True, help=", ".join(estimator_names()))
    parser.add_argument("--format", default="auto", help="data format (default auto)")
    parser.add_argument("--soc0", type=float, default=None,
                        help="initial SOC guess in [0, 1] on the data's SOC axis (default: read off the first "
                             "voltage)")
    parser.add_argument("--soc0-sd", type=float, default=0.1, help="standard deviation of the initial SOC guess")
    parser.add_argument("--voltage-sd", type=float, default=0.01, help="voltage sensor noise SD [V] (default 0.01)")
    parser.add_argument("--current-sd", type=float, default=0.1, help="current sensor noise SD [A] (default 0.1)")
    parser.add_argument("--noise", default="model", choices=recipe.NOISE_MODES,
                        help="model: covariances from the parameter file's measured model error (default); "
                             "sensor: the sensor noise alone")
    parser.add_argument("--particles", type=int, default=500, help="particles of the pf (default 500)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the pf (default 0)")
    parser.add_argument("--gate-widen", action="store_true",
                        help="EKF family: where the innovation gate releases after rejecting the measurement ten "
                             "samples running, widen the SOC variance first so the filter re-acquires (default off)")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--no-segments", action="store_true",
                        help="filter the record as one piece, through its gaps (default: restart each segment)")


def model_error_of(spec: str):
    """The ``model_error`` block of a PARAMS.json file as :class:`~socbench.estimators.model_error.ModelErrorStats`,
    or None (a ``paper:`` set, or a file without one)."""
    block = params_block(spec, "model_error")
    if block is None:
        return None
    try:
        return recipe.ModelErrorStats.from_dict(block)
    except ConfigError as exc:
        raise ConfigError(f"{spec}: {exc}") from None


def run(args) -> int:
    estimator_class(args.estimator)  # an unknown name fails before any file is read
    if args.soc0 is not None and not 0.0 <= args.soc0 <= 1.0:
        raise DataError(f"--soc0 must be in [0, 1], got {args.soc0}")
    if not 0 < args.soc0_sd <= 1:  # an SD wider than the whole SOC range is no prior; the filters' runs fail on it
        raise ConfigError(f"--soc0-sd must be in (0, 1] (a fraction of full charge), got {args.soc0_sd}")
    for option, sd in (("--voltage-sd", args.voltage_sd), ("--current-sd", args.current_sd)):
        if not (math.isfinite(sd) and sd >= 0):
            raise ConfigError(f"{option} must be a finite number >= 0, got {sd}")
    if args.gate_widen and "gate_widen" not in estimator_class(args.estimator).defaults:
        raise ConfigError(f"--gate-widen applies to the EKF family (ekf, iekf, aekf, hinf, dual), not "
                          f"'{args.estimator}'")
    if args.estimator == "pf" and args.particles < MIN_PARTICLES:
        raise ConfigError(f"--particles must be at least {MIN_PARTICLES} (the band is read from the cloud's spread, "
                          f"which a handful of particles collapses), got {args.particles}")
    out = output_dir(args.out, "--out")
    sensor = SensorNoise(voltage_sd=args.voltage_sd, current_sd=args.current_sd)
    profile = load(args.data, args.format)
    profile.require("voltage_v")
    name, params = resolve_params(args.params)
    check_voltage_level(profile, params, f"the '{args.params}' parameter set")
    temperature = check_temperature_range(profile, params, f"the '{args.params}' parameter set",
                                          fitted_at_c(args.params))
    capacity_ratio = check_capacity(profile, params, f"the '{args.params}' parameter set")
    check_current_against_reference(profile, params.capacity_ah, "the SOC errors")
    for note in (n for n in params.notes if n.startswith(NO_KNEE)):  # the SOC it reports rides on that axis
        warnings.warn(f"{args.params}: fitted on an HPPC with {note}", SocbenchWarning, stacklevel=2)
    model = make_model(name, params)
    noise_mode = args.noise if args.estimator != "coulomb" else "sensor"
    stats = model_error_of(args.params) if noise_mode == "model" else None
    if noise_mode == "model" and stats is None:
        if not args.params.startswith("paper:"):  # a reference set has no identification data to measure it on
            warnings.warn(f"{args.params} has no measured model error (`socbench fit` measures it on an HPPC or on "
                          "records with a reference SOC, `--validation`): the filter uses the sensor noise alone",
                          SocbenchWarning, stacklevel=2)
        noise_mode = "sensor"
    if noise_mode == "model" and stats.measured_on == "identification":
        if (params_block(args.params, "fit") or {}).get("from") == "socbench diagnose":
            # the diagnosis measures it on its evaluation records, where its effects were fitted: `fit`'s advice
            # (--validation) is not an option there
            warnings.warn(f"{args.params}: its model error was measured on the records `socbench diagnose` fitted its "
                          f"effects on ({', '.join(stats.records)}), in sample: on other records the ±3σ band is "
                          "likely too narrow", SocbenchWarning, stacklevel=2)
        else:
            warnings.warn(f"{args.params}: its model error was measured on the identification records only "
                          "(`socbench fit` without --validation): on a drive cycle the ±3σ band is likely too narrow; "
                          "refit with --validation DRIVE... for an honest band", SocbenchWarning, stacklevel=2)
    form = estimator_class(args.estimator).model_error_form
    run_model, noise = recipe.apply(model, sensor, stats, profile, noise=noise_mode, form=form)
    # each slow-scale state's share of the measured slow SD on this record (κ; the states form only)
    slow_share = recipe.slow_share(stats, profile) if noise_mode == "model" and form == "states" else None
    options = {"soc0_sd": args.soc0_sd, "store_states": True}  # states: the domain report counts guards along them
    if args.estimator == "pf":
        options["n_particles"] = args.particles
    if args.gate_widen:
        options["gate_widen"] = True
    axis = soc_axis(params, profile)
    check_reference_axis(profile, params, axis, f"the '{args.params}' parameter set")
    est = run_on_data_axis(make_estimator(args.estimator, run_model, noise, **options), profile, axis,
                           soc0=args.soc0, soc0_sd=args.soc0_sd, seed=args.seed,
                           segments=False if args.no_segments else None)
    pauses = pause_report(profile, model.capacity_ah, est.segments)
    message = pause_message(pauses, f"{args.estimator} on {profile.name}", "the last current is held across each and "
                            f"the band widened by up to {100 * pauses['soc_sd_max']:.2g} SOC points (SD)")
    if message:
        warnings.warn(message, SocbenchWarning, stacklevel=1)
    s = score(est, profile)
    metrics = {k: v for k, v in s.items() if k != "runs"}
    metrics.update({"estimator": args.estimator, "model": name, "data": str(args.data),
                    "noise": {"mode": noise_mode, "voltage_sd": args.voltage_sd, "current_sd": args.current_sd,
                              "filter_voltage_sd": noise.voltage_sd,
                              "model_error": stats.to_dict() if stats is not None else None,
                              "slow_share": slow_share},
                    "soc_axis": axis.to_dict(),
                    "failed_reason": est.failure_reasons(), "segments": est.segments.to_dict(),
                    "logger_pauses": pauses,
                    "domain": {k: v for k, v in est.domain.items() if k != "seconds"},
                    "guard_fractions": guard_fractions(est.domain)})
    if profile.soc_ref is None:
        metrics.update({"nees_mean": None, "frac_within_3sigma": None})
    if temperature:
        metrics["temperature_range"] = temperature
    if capacity_ratio is not None:
        metrics["capacity_ratio"] = capacity_ratio  # record / parameter set (check_capacity)
    for key in est.info.get("parameters", ()):  # parameter estimates (the joint estimator): final value and 3σ
        metrics["parameters"] = list(est.info["parameters"])
        for k in (key, f"{key}_3sigma"):
            v = [float(a) for a in est.info[k]]
            metrics[k] = v[0] if len(v) == 1 else v
    moved = est.info.get("soc0_moved_out_of_held_ocv")
    if moved is not None:
        metrics["soc0_moved_out_of_held_ocv"] = moved
    excess = error_state_excess(est)
    metrics["error_state_beyond_s"] = {k: v[0] for k, v in excess.items()}
    frame = est.to_frame(0)[["time_s", "soc", "soc_std", "v_pred", "innovation", "innovation_var"]]
    if est.n_runs > 1:
        import pandas as pd

        frame = pd.concat([est.to_frame(r).assign(run=r) for r in range(est.n_runs)], ignore_index=True)
    atomic_write_frame(out / "estimate.csv", frame)
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2, default=_jsonable))
    soc_part = (f"SOC RMSE {_fmt(s['soc_rmse'], 100)} %  max {_fmt(s['soc_max_abs'], 100)} %  "
                f"within 3σ {_fmt(s['frac_within_3sigma'], 100, 1)} %  NEES {_fmt(s['nees_mean'])}  "
                if profile.soc_ref is not None else "no reference SOC  ")
    band = s.get("nis_band")
    nis_band = f" [{band[0]:.2f}, {band[1]:.2f}]" if band else ""
    params_text = "".join(f"  {k} {float(est.info[k][0]):.4g} ± {float(est.info[k + '_3sigma'][0]):.2g} (3σ)"
                          for k in est.info.get("parameters", ()))
    segs = f"  {est.segments.count} segments" if est.segments.count > 1 else ""
    print(f"{args.estimator} on {model.name}, {profile.name}: n={profile.n}{segs}  {soc_part}"
          f"V RMSE {_fmt(s['rmse_v'], 1000, 1)} mV  NIS {_fmt(s['nis_mean'])}{nis_band}{params_text}  "
          f"noise {noise_mode}  failed runs {s['failed_runs']}  out of domain "
          f"{100 * est.domain['outside_fraction']:.1f} %  -> {out}")
    warn_outside(est.domain, f"{args.estimator} on {model.name}, {profile.name}")
    if moved is not None:
        warnings.warn(f"{args.estimator} on {model.name}, {profile.name}: the initial SOC {moved['from']:.4g} lies "
                      f"where the OCV curve is held flat (no gain on the SOC there); the filter starts at "
                      f"{moved['to']:.4g}, the edge of its extrapolation band, within the initial SOC's SD",
                      SocbenchWarning, stacklevel=2)
    held = {k: v for k, v in excess.items() if v[0] >= LOST_MIN_S}
    if held:
        k, (d, t0) = max(held.items(), key=lambda kv: kv[1][0])
        warnings.warn(f"{args.estimator} on {model.name}, {profile.name}: the model-error state {k} stays beyond "
                      f"{LOST_SIGMA:g} of its unit SD for {d:.0f} s from t = {t0:.0f} s: the model misses this record "
                      "by far more than its identification records showed (noise recipe), and the SOC band is "
                      "narrower than its error there", SocbenchWarning, stacklevel=2)
    if s["lost_s"] >= LOST_MIN_S:
        warnings.warn(f"{args.estimator} on {model.name}, {profile.name}: every innovation lies beyond "
                      f"{LOST_SIGMA:g} σ for {s['lost_s']:.0f} s from t = {s['lost_from_s']:.0f} s: the filter has "
                      "lost the measurement there (the model far from this record: its temperature, capacity or a "
                      "fault; or the SOC held where the OCV curve is flat); its SOC and band from there on are not "
                      "meaningful", SocbenchWarning, stacklevel=2)
    return 0


def _fmt(v, scale: float = 1.0, digits: int = 2) -> str:
    return "n/a" if v is None else f"{scale * v:.{digits}f}"


def _jsonable(v):
    if hasattr(v, "tolist"):
        return v.tolist()
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")
