"""``socbench estimate --data PATH --params PARAMS.json --estimator NAME [--soc0 Z] --out DIR`` (NAME: any registered
estimator, ``socbench.estimators.ESTIMATORS``: coulomb, ekf, ukf, pf, aekf, ckf, srukf, hinf, dual).

Writes ``DIR/estimate.csv`` (``time_s, soc, soc_std, v_pred, innovation``, plus ``innovation_var``) and
``DIR/metrics.json`` (``soc_rmse, soc_max_abs, rmse_v, nis_mean`` and, when the data carries a reference SOC,
``nees_mean, frac_within_3sigma``; the SOC keys are null without one). An estimator that tracks parameters (``dual``)
adds each final estimate and its 3σ half-width: ``capacity_ah, capacity_ah_3sigma, r0_ohm, r0_ohm_3sigma`` (one number
per run: a float for a single record, else a list), and a ``parameters`` list naming them. ``--data builtin:hppc`` and
``--params paper:MODEL`` name the embedded profile and Table 3 sets.
"""

from __future__ import annotations

import json
from pathlib import Path

from ..checks import check_temperature_range
from ..datasets import load
from ..errors import ConfigError, DataError
from ..estimators import SensorNoise, estimator_class, estimator_names, make_estimator
from ..estimators.scoring import score
from ..io import atomic_write_frame, atomic_write_text
from ..models import make_model
from .simulate import resolve_params


def add_arguments(parser) -> None:
    parser.add_argument("--data", required=True, help="profile file, or builtin:hppc / builtin:1c")
    parser.add_argument("--params", required=True, help="PARAMS.json from `socbench fit`, or paper:MODEL")
    parser.add_argument("--estimator", required=True, help=", ".join(estimator_names()))
    parser.add_argument("--format", default="auto", help="data format (default auto)")
    parser.add_argument("--soc0", type=float, default=None,
                        help="initial SOC guess in [0, 1] (default: OCV inverse of the first voltage)")
    parser.add_argument("--soc0-sd", type=float, default=0.1, help="standard deviation of the initial SOC guess")
    parser.add_argument("--voltage-sd", type=float, default=0.01, help="voltage sensor noise SD [V] (default 0.01)")
    parser.add_argument("--current-sd", type=float, default=0.1, help="current sensor noise SD [A] (default 0.1)")
    parser.add_argument("--particles", type=int, default=500, help="particles of the pf (default 500)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the pf (default 0)")
    parser.add_argument("--out", required=True, help="output folder")


def run(args) -> int:
    estimator_class(args.estimator)  # an unknown name fails before any file is read
    if args.soc0 is not None and not 0.0 <= args.soc0 <= 1.0:
        raise DataError(f"--soc0 must be in [0, 1], got {args.soc0}")
    if not args.soc0_sd > 0:
        raise ConfigError(f"--soc0-sd must be > 0, got {args.soc0_sd}")
    noise = SensorNoise(voltage_sd=args.voltage_sd, current_sd=args.current_sd)
    profile = load(args.data, args.format)
    profile.require("voltage_v")
    name, params = resolve_params(args.params)
    temperature = check_temperature_range(profile, params, f"the '{args.params}' parameter set")
    model = make_model(name, params)
    options = {"soc0_sd": args.soc0_sd}
    if args.estimator == "pf":
        options["n_particles"] = args.particles
    est = make_estimator(args.estimator, model, noise, **options).run(profile, soc0=args.soc0, seed=args.seed)
    s = score(est, profile)
    metrics = {k: v for k, v in s.items() if k != "runs"}
    metrics.update({"estimator": args.estimator, "model": name, "data": str(args.data),
                    "noise": {"voltage_sd": args.voltage_sd, "current_sd": args.current_sd}})
    if profile.soc_ref is None:
        metrics.update({"nees_mean": None, "frac_within_3sigma": None})
    if temperature:
        metrics["temperature_range"] = temperature
    for key in est.info.get("parameters", ()):  # parameter estimates (the joint estimator): final value and 3σ
        metrics["parameters"] = list(est.info["parameters"])
        for k in (key, f"{key}_3sigma"):
            v = [float(a) for a in est.info[k]]
            metrics[k] = v[0] if len(v) == 1 else v
    out = Path(args.out)
    frame = est.to_frame(0)[["time_s", "soc", "soc_std", "v_pred", "innovation", "innovation_var"]]
    if est.n_runs > 1:
        import pandas as pd

        frame = pd.concat([est.to_frame(r).assign(run=r) for r in range(est.n_runs)], ignore_index=True)
    atomic_write_frame(out / "estimate.csv", frame)
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2, default=_jsonable))
    soc_part = (f"SOC RMSE {_fmt(s['soc_rmse'], 100)} %  max {_fmt(s['soc_max_abs'], 100)} %  "
                f"NEES {_fmt(s['nees_mean'])}  " if profile.soc_ref is not None else "no reference SOC  ")
    params = "".join(f"  {k} {float(est.info[k][0]):.4g} ± {float(est.info[k + '_3sigma'][0]):.2g} (3σ)"
                     for k in est.info.get("parameters", ()))
    print(f"{args.estimator} on {name}, {profile.name}: n={profile.n}  {soc_part}"
          f"V RMSE {_fmt(s['rmse_v'], 1000, 1)} mV  NIS {_fmt(s['nis_mean'])}{params}  "
          f"failed runs {s['failed_runs']}  -> {out}")
    return 0


def _fmt(v, scale: float = 1.0, digits: int = 2) -> str:
    return "n/a" if v is None else f"{scale * v:.{digits}f}"


def _jsonable(v):
    if hasattr(v, "tolist"):
        return v.tolist()
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")
