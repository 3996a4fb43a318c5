"""Domain checks: on how many samples a model was driven outside the region its equations and parameters describe.

One mechanism for every model and every estimator, evaluated post hoc on a trajectory (a simulation's states, an
estimator's posterior path), so any engine that returns a trajectory is checked the same way. Per sample:

* ``soc_below_0`` / ``soc_above_1``  SOC outside [0, 1] by more than ``SOC_OVERSHOOT`` (0.1 % of the capacity: a count
                         that ends a CC-CV charge a few 1e-5 above full is the capacity's uncertainty, not a model
                         driven past full);
* ``soc_clamped``        an estimator's SOC clamp to [0, 1] acted (``Estimate.clamped``; the posterior itself never
                         leaves [0, 1], the clamp is where it would have);
* ``soc_pinned``         the clamp holds the estimate at 0 while the record has discharged more than ``EXCURSION_FLAG``
                         (0.05) of the model's capacity since it got there (or at 1 while it charged that much):
                         where a model's SOC would be beyond the OCV band, the estimator is driven past empty (full);
* ``ocv_extrapolated``   SOC outside the OCV curve's rest points (:meth:`~socbench.ocv.OCVCurve.excursion` > 0): the
                         curve is extended linearly there;
* ``ocv_held``           more than ``EXCURSION_FLAG`` (0.05) outside: the curve is held at its band-edge value
                         (:mod:`socbench.ocv`), the voltage no longer follows the SOC;
* ``voltage_implausible`` the model's voltage outside ``[½·U_oc(z_lo), 1.5·U_oc(z_hi)]`` (half the empty-cell OCV,
                         1.5 × the full-cell OCV): no cell or pack the parameters describe reads that;
* ``guards``             the samples on which each of the model's guards acted
                         (:class:`~socbench.models.blocks.GuardLog`: R/C floors, the singular-term ε, exponent clip …).

``outside`` counts the samples with SOC outside [0, 1], the OCV held, or an implausible voltage, and (estimates) the
pinned samples. A clamp that acts briefly — at 1 at the start of a flight from full, at 0 in the last percent of a
test to empty — is counted in ``soc_clamped`` but is not out of the domain. :func:`warn_outside` issues one
:class:`~socbench.errors.SocbenchWarning` line when ``outside`` reaches ``WARN_FRACTION`` of the samples, or when any
voltage is implausible (a voltage error in kilovolts is never reported without a warning).
"""

from __future__ import annotations

import warnings

import numpy as np

from .errors import SocbenchWarning
from .models.blocks import GuardLog
from .ocv import EXCURSION_FLAG
from .profile import SOC_TOLERANCE

#: SOC beyond [0, 1] by at most this is not counted outside the domain: 0.1 % of the capacity, ten times below the
#: uncertainty of a rated or an HPPC-measured capacity (~1 %). A simulation counted with the fitted capacity from the
#: reference's SOC ends a CC-CV charge a few 1e-5 above full (the fitted and the cycler's capacities differ by that):
#: with the counter's rounding (``SOC_TOLERANCE``, 1e-6) as the bound, the whole CV phase read "outside the domain"
#: and ``simulate`` warned on an ordinary charge
SOC_OVERSHOOT = 1e-3

#: share of samples outside the domain from which the CLI warns
WARN_FRACTION = 0.01
#: the plausible model voltage: [LOW × U_oc(z_lo), HIGH × U_oc(z_hi)]
VOLTAGE_LOW, VOLTAGE_HIGH = 0.5, 1.5

COUNTERS = ("soc_below_0", "soc_above_1", "soc_clamped", "soc_pinned", "ocv_extrapolated", "ocv_held",
            "voltage_implausible")


def _count(mask) -> int:
    return int(np.count_nonzero(mask))


def domain_report(model, *, states=None, soc=None, current=None, temp=None, time_s=None, voltage=None,
                  clamped=None, guards: GuardLog | None = None) -> dict:
    """Counts (module docstring) along a trajectory of ``model``.

    Give ``states (…, T, n)`` or ``soc (…, T)``. ``guards`` is the log collected while the trajectory was computed;
    without one, the guards are evaluated here on ``states`` (``model.output`` with ``current`` and ``temp``, and
    ``model.step`` over ``time_s`` too when it is given). ``voltage (…, T)``: the model's voltage along the path;
    ``clamped (…, T)``: where an estimator's SOC clamp acted (``soc_pinned`` needs ``current`` and ``time_s``).
    """
    if states is not None:
        states = np.asarray(states, dtype=float)
        z = states[..., 0]
    elif soc is not None:
        z = np.asarray(soc, dtype=float)
    else:
        raise ValueError("domain_report needs states or soc")
    n = int(z.size)
    ocv = model.ocv
    below = z < -SOC_OVERSHOOT
    above = z > 1.0 + SOC_OVERSHOOT
    tz = None if temp is None else np.broadcast_to(np.asarray(temp, dtype=float), z.shape)
    exc = ocv.excursion(z, tz)
    held = exc > EXCURSION_FLAG
    outside = below | above | held
    counts = {"soc_below_0": _count(below), "soc_above_1": _count(above), "ocv_extrapolated": _count(exc > 1e-12),
              "ocv_held": _count(held)}
    if clamped is not None:
        clamped = np.broadcast_to(np.asarray(clamped, dtype=bool), z.shape)
        counts["soc_clamped"] = _count(clamped)
        if current is not None and time_s is not None:
            pinned = pinned_beyond_band(clamped, z, current, time_s, model.capacity_ah)
            counts["soc_pinned"] = _count(pinned)
            outside = outside | pinned
    if voltage is not None:
        v = np.asarray(voltage, dtype=float)
        lo, hi = VOLTAGE_LOW * float(ocv.voltage[0]), VOLTAGE_HIGH * float(ocv.voltage[-1])
        bad_v = ~((v >= lo) & (v <= hi))  # NaN counts as implausible
        counts["voltage_implausible"] = _count(bad_v)
        outside = outside | np.broadcast_to(bad_v, outside.shape)
    if guards is None and states is not None and current is not None:
        guards = evaluate_guards(model, states, current, temp, time_s)
    guard_counts = dict(sorted(guards.counts.items())) if guards is not None else {}
    n_out = _count(outside)
    return {
        "samples": n,
        **counts,
        "soc_min": float(np.min(z)) if n else None,
        "soc_max": float(np.max(z)) if n else None,
        "guards": guard_counts,
        "outside": n_out,
        "outside_fraction": n_out / n if n else 0.0,
    }


def pinned_beyond_band(clamped, z, current, time_s, capacity_ah: float, band: float = EXCURSION_FLAG):
    """(…, T) bool: samples of a run of clamped samples at 0 (at 1) after which the record has discharged (charged)
    more than ``band`` of the capacity, counted from the run's first sample with the zero-order hold."""
    clamped = np.asarray(clamped, dtype=bool)
    T = clamped.shape[-1]
    i = np.broadcast_to(np.asarray(current, dtype=float), clamped.shape)
    dq = np.zeros(clamped.shape)
    dq[..., 1:] = i[..., :-1] * np.diff(np.asarray(time_s, dtype=float)) / (3600.0 * capacity_ah)  # into sample k
    out = np.zeros(clamped.shape, dtype=bool)
    for pinned, sign in ((clamped & (z <= SOC_TOLERANCE), 1.0), (clamped & (z >= 1.0 - SOC_TOLERANCE), -1.0)):
        if not pinned.any():
            continue
        c = np.cumsum(np.where(pinned, sign * dq, 0.0), axis=-1)
        # the charge since the run began: c minus its value at the run's first sample
        first = np.where(pinned & ~np.concatenate([np.zeros(pinned.shape[:-1] + (1,), bool), pinned[..., :-1]], -1),
                         np.arange(T), 0)
        start = np.maximum.accumulate(first, axis=-1)
        out |= pinned & (c - np.take_along_axis(c, start, axis=-1) > band)
    return out


def evaluate_guards(model, states, current, temp=None, time_s=None) -> GuardLog:
    """The guards of ``model`` along ``states (…, T, n)``: one ``output`` call on every sample and, with ``time_s``,
    one ``step`` call on every step (the same calls a simulation makes, on the whole path at once)."""
    log = GuardLog()
    states = np.asarray(states, dtype=float)
    i = np.broadcast_to(np.asarray(current, dtype=float), states.shape[:-1])
    tc = None if temp is None else np.broadcast_to(np.asarray(temp, dtype=float), states.shape[:-1])
    with np.errstate(all="ignore"):
        model.output(states, i, tc, guards=log)
        if time_s is not None and states.shape[-2] > 1:
            dt = np.diff(np.asarray(time_s, dtype=float))
            model.step(states[..., :-1, :], i[..., :-1], dt, None if tc is None else tc[..., :-1], guards=log)
    log.samples = int(np.prod(states.shape[:-1], dtype=int))
    return log


#: samples per block of runs in :func:`estimate_domain`: the report's masks and temporaries of one block stay in the
#: processor's cache (on a whole batch of 10⁴ runs they were 32 MB arrays, and the report cost a third of a compiled
#: filter's time)
DOMAIN_BLOCK = 1 << 16


def estimate_domain(model, estimate, profile) -> dict:
    """:func:`domain_report` of an :class:`~socbench.estimators.estimate.Estimate` on its profile: the posterior
    states when the estimator stored them (``store_states``; guards evaluated along them), else the SOC path; the
    clamp flags; the predicted voltage. Evaluated on blocks of runs (:data:`DOMAIN_BLOCK`) and merged: the same
    report as one call on the whole batch."""
    R, T = estimate.soc.shape
    cur = np.broadcast_to(profile.current_a, (R, T))
    temp = None if profile.temperature_c is None else np.broadcast_to(profile.temperature_c, (R, T))
    rows = max(1, DOMAIN_BLOCK // max(T, 1))
    reports = []
    for a in range(0, max(R, 1), rows):
        b = slice(a, a + rows)
        path = {"states": estimate.x[b]} if estimate.x is not None else {"soc": estimate.soc[b]}
        reports.append(domain_report(model, **path, current=cur[b], temp=None if temp is None else temp[b],
                                     time_s=profile.time_s, voltage=estimate.v_pred[b], clamped=estimate.clamped[b]))
    if len(reports) == 1:
        return reports[0]
    merged = merge(reports)
    return {k: merged[k] for k in reports[0]}  # the keys in the order of one report


def guard_fractions(report: dict) -> dict:
    """The report as ``{counter or guard: share of samples}``, only what acted (the ``guard_fractions`` JSON key)."""
    n = max(int(report.get("samples", 0)), 1)
    out = {k: report[k] / n for k in COUNTERS if report.get(k)}
    out.update({k: v / n for k, v in report.get("guards", {}).items() if v})
    return dict(sorted(out.items()))


def merge(reports: list[dict]) -> dict:
    """One report from reports on disjoint parts of a trajectory (segments, runs)."""
    reports = [r for r in reports if r]
    if not reports:
        return {}
    out = {"samples": sum(r["samples"] for r in reports)}
    for k in COUNTERS + ("outside",):
        if any(k in r for r in reports):
            out[k] = sum(r.get(k, 0) for r in reports)
    mins = [r["soc_min"] for r in reports if r.get("soc_min") is not None]
    maxs = [r["soc_max"] for r in reports if r.get("soc_max") is not None]
    out["soc_min"] = min(mins) if mins else None
    out["soc_max"] = max(maxs) if maxs else None
    guards: dict = {}
    for r in reports:
        for g, c in r.get("guards", {}).items():
            guards[g] = guards.get(g, 0) + c
    out["guards"] = dict(sorted(guards.items()))
    out["outside_fraction"] = out["outside"] / out["samples"] if out["samples"] else 0.0
    return out


def outside_message(report: dict, what: str, share: float = WARN_FRACTION) -> str | None:
    """One line saying how much of ``what`` lies outside the domain, or None when it is below ``share`` and no
    voltage is implausible."""
    n = report.get("samples", 0)
    if not n:
        return None
    frac = report.get("outside_fraction", 0.0)
    n_volt = report.get("voltage_implausible", 0)
    if frac < share and not n_volt:
        return None

    def pct(k):
        return 100.0 * report.get(k, 0) / n

    parts = []
    if report.get("soc_below_0") or report.get("soc_above_1"):
        parts.append(f"SOC below 0 on {pct('soc_below_0'):.1f} % and above 1 on {pct('soc_above_1'):.1f} % of "
                     f"samples (min {report['soc_min']:.2f}, max {report['soc_max']:.2f})")
    if report.get("ocv_held"):
        parts.append(f"OCV held beyond its {EXCURSION_FLAG:g} extrapolation band on {pct('ocv_held'):.1f} %")
    if report.get("soc_pinned"):
        parts.append(f"estimate held at 0 or 1 by the clamp while {EXCURSION_FLAG:g} of the capacity or more went "
                     f"beyond, on {pct('soc_pinned'):.1f} %")
    if n_volt:
        parts.append(f"model voltage implausible on {n_volt} samples")
    busy = [f"{g} {100.0 * c / n:.1f} %" for g, c in report.get("guards", {}).items() if c >= share * n]
    if busy:
        parts.append("guards acting: " + ", ".join(busy))
    return (f"{what}: {100.0 * frac:.1f} % of samples outside the model's domain ({'; '.join(parts)}); "
            "results there are not meaningful")


def warn_outside(report: dict, what: str, share: float = WARN_FRACTION) -> str | None:
    """Issue :func:`outside_message` as a :class:`SocbenchWarning` (the CLI prints it as one line); returns it."""
    msg = outside_message(report, what, share)
    if msg:
        warnings.warn(msg, SocbenchWarning, stacklevel=2)
    return msg
