"""The OCV of a one-branch slow test, freed of the over-potential the fitted model holds at the test's current.

A slow test's discharge branch is the voltage under load, ``v(z) = U(z) − η(z)``, not the OCV. The mean of a
discharge and a charge branch cancels ``η`` (the two currents are alike); a test with one branch, or a diagnosis
told to use the discharge branch alone (``slow_ocv="discharge"``), keeps it. At C/20 on a cell of 50 mΩ that is a few
millivolts; at C/5 — the capacity check of an ageing campaign, the only slow test many life-cycle records hold
(the CMU eVTOL cells' reference discharges) — it is tens, and a model that takes the branch as its OCV subtracts its
own ``R·I`` a second time: on every later record it reads low by the test's over-potential.

The model fitted on the dynamic record knows its over-potential. Simulated open loop on the test from rest at the
start of the branch (the branch's own SOC count, from 1 at its start), with ``x_k`` its state at sample ``k``::

    η_k = E(z_k, T_k) − h(x_k, I_k, T_k)        E(z, T) = h([z, 0, …], 0, T), the model's equilibrium voltage
    Û(z_k) = v_k + η_k                           the branch, unloaded

and the curve through ``Û`` (binned along the SOC like the branch, monotone) replaces the branch; the model is
fitted again on it with the same settings. Nothing of an evaluation record enters the curve: the over-potential is
the fitted model's, read on the test it was fitted beside. :func:`refit_on_unloaded_branch` keeps the refit where its
branches stay within the record (:func:`~socbench.identify.pseudo_ocv.keep_refit`) and it fits the dynamic record no
worse: judged on the fit records alone. The evaluation records are not asked. They hold what the diagnosis is to
find, and an OCV left too low by the test's over-potential predicts an aged cell's capacity check better than the
unloaded one (the aged voltage falls earlier): asked (the first draft of this rule: the refit kept where they were
predicted no worse), they kept the bias in 34 of 36 of the CMU eVTOL cells' checks (``benchmarks/evtol_fade.py``),
spending part of the fade on the base.
"""

from __future__ import annotations

import numpy as np

from ..estimators.base import equilibrium
from ..models.registry import make_model
from ..ocv import OCVCurve, monotone_points
from ..profile import Profile
from .fit import FitResult, fit_model
from .hppc import _binned, _slow_branches
from .pseudo_ocv import keep_refit

#: SOC bins of the unloaded curve (those of :func:`~socbench.identify.hppc.ocv_from_slow_test`)
N_POINTS = 101


def unloaded_branch(fit: FitResult, test: Profile, i_min: float | None = None):
    """``(curve, median η)``: the discharge branch of the slow test ``test`` moved up by the over-potential the model
    of ``fit`` holds along it (module docstring), and the median of that over-potential [V]. ``i_min``: the current
    below which a sample is not on the branch (as the branch was read)."""
    (z, v, t), _, _ = _slow_branches(test, fit.params.capacity_ah, i_min)
    a = int(np.searchsorted(test.time_s, t[0]))
    rec = test.slice(a)
    model = make_model(fit.name, fit.params)
    states, y = model.open_loop(model.x0(1.0), rec.time_s, rec.current_a, rec.temperature_c)
    n = z.size
    temp = None if rec.temperature_c is None else rec.temperature_c[:n]
    eta = equilibrium(model, states[:n, 0], temp)[0] - y[:n]
    zb, ub = _binned(z, v + eta, n_bins=N_POINTS)
    zm, um = monotone_points(zb, ub)
    src = test.meta.source or test.name
    return OCVCurve(zm, um, f"discharge branch of {src}, freed of the fitted model's over-potential"), \
        float(np.median(eta))


def refit_on_unloaded_branch(fit: FitResult, profile: Profile, test: Profile, i_min: float | None = None,
                             **fit_kwargs):
    """``(refit or None, report)``: ``fit`` (fitted on the dynamic record ``profile`` with the slow test's discharge
    branch as its OCV) fitted again, with the same ``fit_kwargs``, on the branch freed of its over-potential
    (:func:`unloaded_branch`). Kept (module docstring) when every branch is within the record and ``profile`` is
    fitted no worse. ``report``: the median over-potential taken off, what was measured and ``why_not`` (None:
    kept)."""
    curve, eta = unloaded_branch(fit, test, i_min)
    refit = fit_model(fit.name, profile, ocv=curve, capacity_ah=fit.params.capacity_ah, **fit_kwargs)
    kept, report = keep_refit(fit, refit, profile, (), {"median_overpotential_v": eta})
    if kept is not None and refit.rmse_v > fit.rmse_v:
        kept = None
        report.update({"kept": False, "why_not": "fit record worse"})
    return kept, report
