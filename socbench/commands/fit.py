"""``socbench fit --data PATH --model NAME --out PARAMS.json [--format F] [--mode paper|constant|lookup]``.

Fits a registered model to a record (normally an HPPC test) with :func:`socbench.identify.fit_model` and writes a
self-contained parameter file (model, capacity, OCV curve, parameter functions) with a ``"fit"`` block (mode, RMSE,
standard errors, warnings, seconds, and ``domain``: :func:`socbench.domain.domain_report` of the fitted model along
the fitted record, with its segment count) that ``socbench simulate --params`` reads back. Without ``--ocv`` the OCV
curve comes from the record's HPPC rest points. A record of several discharges (battery swaps, recharges) is fitted
segment by segment (:mod:`socbench.segments`).
"""

from __future__ import annotations

import json
from pathlib import Path

from ..datasets import load
from ..domain import warn_outside
from ..errors import ConfigError, DataError
from ..identify import MODES, fit_model
from ..io import output_file
from ..models import model_class, save_params
from ..ocv import OCVCurve


def add_arguments(parser) -> None:
    parser.add_argument("--data", required=True, help="identification record (HPPC), or builtin:hppc")
    parser.add_argument("--model", required=True, help="model name (see `socbench models`)")
    parser.add_argument("--out", required=True, help="write the fitted PARAMS.json here")
    parser.add_argument("--format", default="auto", help="data format (default auto)")
    parser.add_argument("--mode", default="paper", choices=MODES,
                        help="paper: SOC polynomials for models 1-6, constants otherwise (default); "
                             "constant; lookup: piecewise linear in SOC")
    parser.add_argument("--capacity", type=float, default=None,
                        help="capacity [Ah] (default: the charge the HPPC discharges from full to empty)")
    parser.add_argument("--soc0", type=float, default=None, help="initial SOC of the record (default: 1 for an HPPC)")
    parser.add_argument("--ocv", default=None,
                        help="OCV curve JSON ({soc, voltage}) or a PARAMS.json whose curve to use "
                             "(default: the record's HPPC rest points)")
    parser.add_argument("--no-segments", action="store_true",
                        help="fit the record as one piece, through its gaps (default: restart each segment)")


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


def run(args) -> int:
    if args.capacity is not None and not args.capacity > 0:
        raise ConfigError(f"--capacity must be positive, got {args.capacity}")
    if args.soc0 is not None and not 0.0 <= args.soc0 <= 1.0:
        raise ConfigError(f"--soc0 must be in [0, 1], got {args.soc0}")
    model_class(args.model)  # an unknown model fails before the data is read
    output_file(args.out, "--out")
    ocv = _read_ocv(args.ocv) if args.ocv else None
    profile = load(args.data, args.format)
    if profile.batched:
        raise DataError("fit needs a single record, not a batch of runs", file=str(args.data))
    res = fit_model(args.model, profile, mode=args.mode, ocv=ocv, capacity_ah=args.capacity, soc0=args.soc0,
                    segments=False if args.no_segments else None)
    save_params(args.out, args.model, res.params, fit=res.fit_summary())
    print(f"{args.model} fitted on {profile.name} ({args.mode} mode): RMS {1000 * res.rmse_v:.1f} mV over "
          f"{res.n_samples} samples in {res.seconds:.1f} s; {len(res.warnings)} warning(s); wrote {args.out}")
    if res.lsq is not None and res.lsq.domain.get("samples"):
        warn_outside(res.lsq.domain, f"{args.model} fitted on {profile.name}")
    for w in res.warnings[:5]:
        print(f"  warning: {w}")
    if len(res.warnings) > 5:
        print(f"  ... {len(res.warnings) - 5} more in {args.out} (fit.warnings)")
    return 0
