"""``socbench simulate --data PATH --params PARAMS.json [--out PRED.csv] [--json METRICS.json] [--no-segments]``.

``--data builtin:hppc`` and ``--params paper:MODEL`` name the embedded paper-pack profile and Table 3 sets. The model
looks its parameters up at the record's measured cell temperature, sample by sample (a temperature-aware set); the
initial SOC (``--soc0``, default the record's reference at its start) and the SOC written follow the data's SOC
definition (:mod:`socbench.socaxis`).

A record of several discharges (battery swaps, recharges) is simulated segment by segment, each restarting at its
reference SOC (:mod:`socbench.segments`); ``--no-segments`` runs it as one piece. Charge the reference SOC says the
cell delivered across a gap that the current column does not carry (the Panasonic HPPC files leave out the step
discharges) is taken as a jump of the SOC there (:func:`socbench.identify.hppc.gap_soc_jumps`), as the fit takes
it on such files, where the simulation starts from the reference (no ``--soc0``, which never reads it) and restarts at
its segments (no ``--no-segments``); the JSON's ``soc_jumps`` says how many and how much. (Where an HPPC file holds a
step of its own, the fit simulates each gap as that step, :mod:`socbench.identify.gap_fill`; the simulation keeps the
jump there too, so the rests after those gaps start from the relaxed state: a parameter set does not carry the step
current.) The JSON holds the DESIGN.md keys,
``segments`` (count and the boundaries), ``domain`` (:func:`socbench.domain.domain_report`: samples with SOC outside
[0, 1], OCV extrapolated, guards, implausible voltage) and ``guard_fractions`` (those counts and the model's guards as
shares of samples). A warning line is printed when ≥ 1 % of the samples lie outside the model's domain.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from ..checks import check_capacity, check_current_against_reference, check_temperature_range, check_voltage_level
from ..datasets import load
from ..domain import warn_outside
from ..errors import ConfigError, DataError, SocbenchWarning
from ..identify.hppc import gap_soc_jumps
from ..io import atomic_write_frame, atomic_write_text, output_file
from ..metrics import voltage_error_stats
from ..models import load_params, make_model, paper_params
from ..segments import pause_message, pause_report
from ..socaxis import soc_axis


def add_arguments(parser) -> None:
    parser.add_argument("--data", required=True, help="profile file, or builtin:hppc / builtin:1c")
    parser.add_argument("--params", required=True, help="PARAMS.json from `socbench fit`, or paper:MODEL")
    parser.add_argument("--format", default="auto", help="data format (default auto)")
    parser.add_argument("--soc0", type=float, default=None, help="initial SOC (default: from the data)")
    parser.add_argument("--out", help="write the prediction CSV here")
    parser.add_argument("--json", help="write the error metrics JSON here")
    parser.add_argument("--no-segments", action="store_true",
                        help="simulate the record as one piece, through its gaps (default: restart each segment)")


def resolve_params(spec: str):
    """``(model_name, ModelParams)`` from a file or ``paper:MODEL``."""
    if spec.startswith("paper:"):
        name = spec.split(":", 1)[1]
        return name, paper_params(name)
    name, params = load_params(spec)
    try:  # an unknown model or a parameter it needs missing, said with the file's name
        model = make_model(name, params)
    except ConfigError as exc:
        raise ConfigError(f"{spec}: {exc}") from None
    unused = sorted(set(params.values) - set(model.required_params()))
    if unused:  # a set of another model under this one's name (a DP's R2, C2 under "thevenin") runs without them
        warnings.warn(f"{spec}: model '{name}' does not use the parameter(s) {', '.join(unused)} the file gives: a "
                      "set fitted for another model?", SocbenchWarning, stacklevel=2)
    return name, params


def params_block(spec: str, key: str):
    """The ``key`` block of a PARAMS.json file (``"fit"``, ``"model_error"``…), or None: a ``paper:`` set, a file
    without it, or one :func:`resolve_params` has already reported as unreadable."""
    if spec.startswith("paper:"):
        return None
    try:
        d = json.loads(Path(spec).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return d.get(key) if isinstance(d, dict) else None


def fitted_at_c(spec: str) -> float | None:
    """The temperature [°C] a single-record fit was made at (``socbench fit`` stores the median of the record's
    temperature column in its ``"fit"`` block), or None."""
    t = (params_block(spec, "fit") or {}).get("temperature_c")
    return float(t) if isinstance(t, (int, float)) else None


def run(args) -> int:
    for option, path in (("--out", args.out), ("--json", args.json)):
        if path:
            output_file(path, option)
    profile = load(args.data, args.format)
    profile.require("voltage_v")
    name, params = resolve_params(args.params)
    if args.soc0 is not None and not 0.0 <= args.soc0 <= 1.0:
        raise DataError(f"--soc0 must be in [0, 1], got {args.soc0}")
    check_voltage_level(profile, params, f"the '{args.params}' parameter set")
    temperature = check_temperature_range(profile, params, f"the '{args.params}' parameter set",
                                          fitted_at_c(args.params))
    capacity_ratio = check_capacity(profile, params, f"the '{args.params}' parameter set")
    check_current_against_reference(profile, params.capacity_ah, "the voltage errors")
    model = make_model(name, params)
    axis = soc_axis(params, profile)
    soc0 = args.soc0 if args.soc0 is not None else (float(profile.soc_ref[0]) if profile.soc_ref is not None
                                                     else None)
    # charge the cell delivered while the logger was off, which the reference SOC holds and the current column does
    # not (the Panasonic HPPC files leave out the step discharges): the fit carried it, so does the simulation that
    # starts from the reference and restarts at its segments (--soc0 never reads the reference; --no-segments holds
    # the current through every gap)
    jumps = gap_soc_jumps(profile, model.capacity_ah) if args.soc0 is None and not args.no_segments else None
    sim = model.simulate(profile, soc0=None if soc0 is None else float(axis.to_model(soc0)),
                         segments=False if args.no_segments else None, soc_jumps=jumps)
    stats = voltage_error_stats(profile.voltage_v, sim.voltage_v)
    pauses = pause_report(profile, params.capacity_ah, sim.segments)
    stats.update({"model": name, "data": str(args.data), "guard_fractions": sim.domain_fractions,
                  "segments": sim.segments.to_dict(), "logger_pauses": pauses, "domain": sim.domain})
    held = "the simulation holds the last current across each"
    if jumps is not None:
        stats["soc_jumps"] = {"steps": int(np.count_nonzero(jumps)),
                              "ah": float(-np.sum(jumps) * model.capacity_ah)}
        held += (f" (across {stats['soc_jumps']['steps']} the SOC takes the {stats['soc_jumps']['ah']:.4g} Ah the "
                 "reference SOC says the current column misses)")
    message = pause_message(pauses, f"{name} on {profile.name}", held)
    if message:
        warnings.warn(message, SocbenchWarning, stacklevel=1)
    if temperature:
        stats["temperature_range"] = temperature
    if capacity_ratio is not None:
        stats["capacity_ratio"] = capacity_ratio  # record / parameter set (check_capacity)
    segs = f"  {sim.segments.count} segments" if sim.segments.count > 1 else ""
    print(
        f"{name} on {profile.name}: n={stats['n']}{segs}  RMS {1000 * stats['rmse_v']:.1f} mV  "
        f"mean {1000 * stats['mean_v']:.1f} mV  SD {1000 * stats['sd_v']:.1f} mV  max {1000 * stats['max_v']:.1f} mV  "
        f"out of domain {100 * sim.domain['outside_fraction']:.1f} %"
    )
    warn_outside(sim.domain, f"{name} on {profile.name}")
    if args.out:
        frame = pd.DataFrame({"time_s": profile.time_s, "current_a": profile.current_a,
                              "voltage_v": profile.voltage_v, "v_model": sim.voltage_v, "soc": axis.to_data(sim.soc)})
        atomic_write_frame(args.out, frame)
    if args.json:
        atomic_write_text(args.json, json.dumps(stats, indent=2))
    return 0
