"""The OCV points of an HPPC's rests, corrected for what the cell had not yet relaxed when each rest ended.

An HPPC reads the OCV at the end of each rest. A rest shorter than a few of the cell's slowest time constants ends
before the voltage has settled: after a discharge step its last voltage lies below the OCV by what the slow branch
still holds (``R₂·I·e^{−t_rest/τ₂}``: with τ₂ ≈ 1000 s and a 15-minute rest, 40 % of that branch's drop). Every
model fitted on those points learns a curve that is too low along the discharge, and on any later record the miss
shows as a slow error that hysteresis, a drifting SOC or a current offset can take up.

The model fitted on the record knows its own over-potential at each rest's end. With ``x_k`` its state at the last
sample of rest ``k`` (open loop over the record, from the fit's start SOC, its record gaps and its current offset)::

    η_k = E(z_k, T_k) − h(x_k, 0, T_k)          E(z, T) = h([z, 0, …], 0, T), the model's equilibrium voltage
    Û_k = v_k + η_k                              the relaxed OCV point at the rest's SOC z_k

and the model is fitted again on the curve through the relaxed points (same settings). Fitting changes the branches,
so the correction is repeated :data:`ITERATIONS` times, each from the last refit. Nothing of a later record is used:
the points move by what the fitted model's own branches hold at the rest ends, read on the record they were fitted on.

The correction is not well posed on its own: on the record, a slow branch's size and the OCV's level trade against
each other, and repeated rounds can drift (on records whose rests had relaxed, a fitted branch slower than the truth's
holds a few mV at each rest's end, and each round moves the points further). So it is only tried where the first fit
holds at least :data:`MIN_SHIFT_V` per cell at some rest's end (below that a refit cannot matter, and the cost of two
fits is saved), and :func:`refit_on_relaxed_ocv` keeps the refit only when every branch's time constant is within the
record (a branch slower than the record trades against the OCV offset freely) and, given validation records, when
their mean open-loop RMSE falls by :data:`~socbench.identify.pseudo_ocv.REFIT_GAIN` (the refined curve, which must
fit its own record that much better first, is held only to predicting them no worse,
:data:`~socbench.identify.pseudo_ocv.VALIDATION_GAIN`). The diagnosis' base fit calls it when asked to
(:func:`socbench.diagnose.core.fit_base`, ``diagnose(…, relax_ocv=True)``; off by default, the reason is there);
``socbench fit`` has no validation record to judge it by and does not.
"""

from __future__ import annotations

import numpy as np

from ..estimators.base import equilibrium
from ..models.effects import n_cells
from ..models.registry import make_model
from ..ocv import OCVCurve, monotone_points
from ..profile import Profile
from .fit import FitResult, fit_model, setup_fit
from .hppc import analyze_hppc
from .pseudo_ocv import keep_refit

#: rounds of correction and refit
ITERATIONS = 2
#: the least over-potential per cell the first fit must hold at some rest's end for the correction to be tried [V]
MIN_SHIFT_V = 1e-3


def rest_overpotential(fit: FitResult, profile: Profile, soc0: float | None = None):
    """``(z, v, η)`` of each OCV rest point of ``profile``: its SOC and rest-end voltage as the HPPC analysis read
    them, and the over-potential ``η_k`` the fitted model still holds there (module docstring); None when the record
    has no HPPC rest points."""
    return overpotential_at_rest_ends(fit.name, fit.params, profile, soc0)


def overpotential_at_rest_ends(name: str, params, profile: Profile, soc0: float | None = None):
    """:func:`rest_overpotential` of model ``name`` with the parameter set ``params`` (any set on the record's SOC
    axis, not only a fit's)."""
    prob = setup_fit(name, profile, "constant", params.ocv, params.capacity_ah, soc0)
    a = analyze_hppc(profile, capacity_ah=params.capacity_ah, soc_start=soc0)
    at_rest_end = {(r.soc_end, r.v_end): r.stop - 1 for r in a.rests}
    idx = [at_rest_end.get((z, v)) for z, v in zip(a.ocv_soc, a.ocv_voltage)]
    if a.ocv_soc.size < 2 or any(k is None for k in idx):
        return None
    idx = np.asarray(idx)
    model = make_model(name, params)
    rec = prob.fit_profile(profile)
    states, _ = prob.open_loop(model, rec, float(np.clip(prob.soc0, 0.0, 1.0)))
    x = states[idx]
    temp = None if rec.temperature_c is None else rec.temperature_c[idx]
    eta = equilibrium(model, x[:, 0], temp)[0] - model.output(x, np.zeros(idx.size), temp)[0]
    return np.asarray(a.ocv_soc), np.asarray(a.ocv_voltage), np.asarray(eta)


def relaxed_ocv(fit: FitResult, profile: Profile, soc0: float | None = None):
    """``(curve, largest η)``: the curve through the rest points of ``profile`` moved by the over-potential ``fit``
    holds at each rest's end (monotone, continued to the record's top like the plain curve), and the largest ``|η_k|``
    [V]; None without rest points."""
    got = rest_overpotential(fit, profile, soc0)
    if got is None:
        return None
    z, v, eta = got
    zm, vm = monotone_points(z, v + eta)
    top = fit.params.ocv
    if top.soc[-1] > zm[-1] + 1e-9:  # the plain curve's extension to the record's top, moved with its last point
        zm = np.append(zm, top.soc[-1])
        vm = np.append(vm, vm[-1] + (float(top.value(top.soc[-1])) - float(top.value(zm[-2]))))
    curve = OCVCurve(zm, vm, f"HPPC rest points of {profile.meta.source or profile.name}, relaxed by the fitted model")
    return curve, float(np.max(np.abs(eta)))


def refit_on_relaxed_ocv(fit: FitResult, profile: Profile, validation=(), **fit_kwargs):
    """``(refit or None, report)``: ``fit`` (fitted on ``profile`` with the OCV of its rest points) fitted again on
    the relaxed points (:func:`relaxed_ocv`, :data:`ITERATIONS` rounds) with the same ``fit_kwargs``, when the first fit
    holds :data:`MIN_SHIFT_V` per cell at some rest's end. The refit is returned when every branch is within the
    record's duration and, with ``validation`` records, when their mean open-loop RMSE falls by
    :data:`~socbench.identify.pseudo_ocv.REFIT_GAIN` (:func:`~socbench.identify.pseudo_ocv.keep_refit`);
    else None. ``report``: what was measured and ``why_not`` (None: kept)."""
    refit, held = fit, []
    for _ in range(ITERATIONS):
        got = relaxed_ocv(refit, profile, soc0=fit_kwargs.get("soc0"))
        if got is None:
            return None, {"relaxed": False, "why_not": "no HPPC rest points"}
        curve, eta = got
        held.append(eta)
        if eta < MIN_SHIFT_V * n_cells(make_model(fit.name, fit.params)) and refit is fit:
            return None, {"relaxed": False, "held_v": held,
                          "why_not": f"the fit holds under {1000 * MIN_SHIFT_V:g} mV per cell at every rest's end"}
        refit = fit_model(fit.name, profile, ocv=curve, capacity_ah=fit.params.capacity_ah, **fit_kwargs)
    # its own record is no judge here: the points moved by what the branches hold, which the refit fits as well
    return keep_refit(fit, refit, profile, validation, {"relaxed": True, "held_v": held})
