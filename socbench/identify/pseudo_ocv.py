"""The OCV between an HPPC's rest points, read from its step segments through a fitted model.

An HPPC measures the OCV only at its rest points, 5–10 % of SOC apart; between them the monotone interpolant
(ECM_SPEC §3.3) guesses. Where the curve bends within a step — the top of charge, LFP's steps between plateaus — the
guess misses by tens of mV, and every model fitted on that curve carries the miss into each record it simulates.
The constant-current discharges between the rests pass through those SOCs. With the model fitted on the record, the
measured voltage plus the model's over-potential is the OCV there::

    Û(z_k) = v_k + (U(z_k) − y_k) = U(z_k) + e_k          e = v − y, the fit's open-loop residual

so the curve's correction at SOC ``z`` is the residual there: ``c(z)`` = the median of ``e`` over the discharge
samples in a bin of width ``bin_soc`` (discharge only: the rest points follow discharge steps, the same hysteresis
branch; the median ignores the edges of the pulses, where the dynamics err most). An HPPC run in the charge
direction (its levels reached by charge steps, :func:`step_direction`) reads the charge samples instead: its rest
points follow charge steps, and its discharges are only pulses (read from its discharge pulses, 10 draws of such
an HPPC with levels 12–20 % apart kept the refinement once, the curve 7–26 mV off between the points; from its charge
steps, 10 of 10, 0.3–2.7 mV: ``tests/test_pseudo_ocv.py``).

The over-potential carries the model's own error (a resistance off by δR moves ``Û`` by δR·I along a whole
discharge); the rest points carry none. So the correction is **anchored**: on each interval between two rest points
``z_a < z_b`` the straight line through its values at both ends is taken off::

    c̃(z) = c(z) − [c(z_a) + (c(z_b) − c(z_a))·(z − z_a)/(z_b − z_a)]

What every step shares is dynamics, not OCV: a branch the model lacks (or misfits) charges up along each step
discharge alike, and a hysteresis state swings alike after each set of charge pulses, while the OCV's bends differ
from step to step. So the median over the intervals of ``c̃`` at the same position ``u = (z − z_a)/(z_b − z_a)``
within them comes off too (with at least three intervals to take it from). The refined curve — the rest points,
and ``U(z_m) + c̃(z_m) − median shape(u_m)`` at the centres of the bins inside each interval (clipped to the
voltages of its two rest points and made monotone by isotonic regression, each run the regression pools one point
at its mean SOC, a bin clipped to a rest point's voltage left out) — passes through every rest point as
measured; only the shape between them comes from the load. PCHIP interpolates it like any OCV curve. Whether the
refinement helps is for validation to say: :func:`refit_on_refined_ocv` keeps the refit on it only when none of its
branches is slower than the record (such a branch only ramps with the charge moved, trading against the refined
curve's slope), when it fits its own record :data:`REFIT_GAIN` better and, given validation records, when it predicts
them no worse (:data:`VALIDATION_GAIN`). ``socbench fit
--refine-ocv`` and ``diagnose(…, refine_ocv=True)`` call it.
"""

from __future__ import annotations

import numpy as np

from ..errors import DataError
from ..models.registry import make_model
from ..ocv import OCVCurve, collapse_ties, monotone_points
from ..profile import Profile
from .fit import FitResult, branches_identified, fit_model, setup_fit
from .hppc import analyze_hppc
from .select import validation_rmse

#: SOC bin of the correction (0.5 %: ten points in a 5 % HPPC step)
BIN_SOC = 0.005
#: samples a bin needs for its median to count
MIN_BIN_SAMPLES = 3
#: a discharge sample: current above this share of the record's median discharge current
DISCHARGE_SHARE = 0.5
#: intervals needed before their common shape is taken for dynamics (a median of fewer says nothing)
MIN_INTERVALS = 3
#: points of the common shape over the position within an interval
COMMON_GRID = 21
#: the refit on the refined curve is kept when it fits its own record by this share better (a curve read from the record
#: takes part of that record's own error with it: better alone is not enough, see :func:`refit_on_refined_ocv`)
REFIT_GAIN = 0.10
#: with validation records, the refit is kept when their mean open-loop RMSE falls by this share: 0, no worse. No
#: parameter of the refined curve is fitted on them, so any fall is the curve's, not a fit of their noise; a share of
#: their RMSE (0.10 until stop 51) refused the curve where the validation records' noise dominates it (an LFP's flat
#: top read 33 mV high at 98 % SOC by the rest points' interpolant, 1 mV by the refined curve, refused for a fall of
#: 5.5 → 5.1 mV over a record with 3.4 mV of noise: case 0 of the randomised benchmark's seed 2026)
VALIDATION_GAIN = 0.0


def step_direction(profile: Profile, capacity_ah: float | None = None, soc0: float | None = None) -> str:
    """How the HPPC ``profile`` moves between its SOC levels, "discharge" or "charge"
    (:attr:`~socbench.identify.hppc.HPPCAnalysis.steps`); "discharge" for a record that is not an HPPC."""
    try:
        return analyze_hppc(profile, capacity_ah=capacity_ah, soc_start=soc0).steps
    except DataError:
        return "discharge"


def refine_ocv(fit: FitResult, profile: Profile, bin_soc: float = BIN_SOC,
               soc0: float | None = None) -> OCVCurve | None:
    """The OCV curve of ``fit`` refined between its points from the step segments of ``profile`` (discharge; charge
    for an HPPC in the charge direction) (the record it was fitted on, from ``soc0`` as the fit was (None: the HPPC
    analysis' start); see the module docstring), or None when the record holds no such segment between two of its
    points."""
    ocv = fit.params.ocv
    prob = setup_fit(fit.name, profile, "constant", ocv, fit.params.capacity_ah, soc0)
    prof = prob.fit_profile(profile)
    model = make_model(fit.name, fit.params)
    with np.errstate(all="ignore"):
        xs, y = prob.open_loop(model, prof)
    # the segments in the direction of the HPPC's steps: its rest points follow them (one hysteresis branch)
    direction = step_direction(profile, fit.params.capacity_ah, soc0)
    i = prof.current_a * (-1.0 if direction == "charge" else 1.0)
    z, e = xs[..., 0], prof.voltage_v - y
    moving = i[i > 0]
    if moving.size == 0:
        return None
    use = (i > DISCHARGE_SHARE * float(np.median(moving))) & np.isfinite(e) & (z > ocv.soc[0]) & (z < ocv.soc[-1])
    if np.count_nonzero(use) < MIN_BIN_SAMPLES:
        return None
    edges = np.arange(ocv.soc[0], ocv.soc[-1] + bin_soc, bin_soc)
    k = np.searchsorted(edges, z[use], side="right") - 1
    centres, corr = [], []
    for b in np.unique(k):
        sel = k == b
        if np.count_nonzero(sel) >= MIN_BIN_SAMPLES:
            centres.append(float(np.mean(z[use][sel])))
            corr.append(float(np.median(e[use][sel])))
    if len(centres) < 2:
        return None
    centres, corr = np.asarray(centres), np.asarray(corr)
    # anchor each interval between rest points: the line through the correction at its two ends comes off
    anchors, anchor_v = np.asarray(ocv.soc, dtype=float), np.asarray(ocv.voltage, dtype=float)
    at_anchor = np.interp(anchors, centres, corr)
    intervals = []  # (interval, bin centres inside it, their anchored correction)
    for a in range(anchors.size - 1):
        za, zb = anchors[a], anchors[a + 1]
        # the bins inside the interval, clear of its ends by half a bin (a rest point already stands there)
        inside = (centres > za + 0.5 * bin_soc) & (centres < zb - 0.5 * bin_soc)
        if np.any(inside):
            zc = centres[inside]
            line = at_anchor[a] + (at_anchor[a + 1] - at_anchor[a]) * (zc - za) / (zb - za)
            intervals.append((a, zc, corr[inside] - line))
    # what every step shares is dynamics, not OCV: the common shape over the position within the interval comes off
    common = _common_shape([((zc - anchors[a]) / (anchors[a + 1] - anchors[a]), c) for a, zc, c in intervals])
    points_z, points_v = [anchors], [anchor_v]
    for a, zc, c in intervals:
        u = (zc - anchors[a]) / (anchors[a + 1] - anchors[a])
        # monotone within the interval and between its two rest points, which stay as measured: a bin clipped to
        # a rest point's voltage leaves the curve to the rest point, and the runs the isotonic regression pools are
        # one point each (socbench.ocv.collapse_ties: no step of flat runs for a filter's Jacobian)
        zi, vi = monotone_points(zc, np.clip(ocv(zc) + c - common(u), anchor_v[a], anchor_v[a + 1]))
        inside = (vi > anchor_v[a]) & (vi < anchor_v[a + 1])
        zi, vi = collapse_ties(zi[inside], vi[inside])
        points_z.append(zi)
        points_v.append(vi)
    zs, vs = np.concatenate(points_z), np.concatenate(points_v)
    return OCVCurve(zs, vs, source=f"{ocv.source}; refined between its points from the {direction} segments of "
                                   f"{profile.meta.source or profile.name} (socbench.identify.pseudo_ocv)")


def _common_shape(shapes):
    """``u ↦`` the median over the intervals of their anchored corrections at the position ``u`` ∈ [0, 1] within the
    interval (0 with fewer than :data:`MIN_INTERVALS` intervals to take it from)."""
    grid = np.linspace(0.0, 1.0, COMMON_GRID)
    rows = [np.interp(grid, u, c, left=np.nan, right=np.nan) for u, c in shapes if u.size >= 2]
    if len(rows) < MIN_INTERVALS:
        return lambda u: np.zeros_like(u)
    rows = np.array(rows)
    seen = np.isfinite(rows).any(axis=0)  # grid points some interval reaches (nanmedian warns on the others)
    med = np.full(grid.size, np.nan)
    med[seen] = np.nanmedian(rows[:, seen], axis=0)
    ok = np.isfinite(med)
    if np.count_nonzero(ok) < 2:
        return lambda u: np.zeros_like(u)
    return lambda u: np.interp(u, grid[ok], med[ok])


def refit_on_refined_ocv(fit: FitResult, profile: Profile, validation=(), **fit_kwargs):
    """``(refit or None, report)``: ``fit`` (fitted on ``profile`` with the OCV of its rest points) fitted again, with
    the same ``fit_kwargs`` (mode, sample weighting…), on its curve refined by :func:`refine_ocv`. The refit is
    returned when every branch's time constant is within the record's duration, when its RMSE on ``profile`` itself
    falls by :data:`REFIT_GAIN` and, with ``validation`` records, when their mean open-loop RMSE is no higher
    (:data:`VALIDATION_GAIN`); else
    None. ``report``: what was measured, and ``why_not`` the first of those rules the refit failed (None: kept)."""
    refined = refine_ocv(fit, profile, soc0=fit_kwargs.get("soc0"))
    if refined is None:
        return None, {"refined": False}
    refit = fit_model(fit.name, profile, ocv=refined, capacity_ah=fit.params.capacity_ah, **fit_kwargs)
    report = {"refined": True, "ocv_points": [int(fit.params.ocv.soc.size), int(refined.soc.size)]}
    # a curve refined from the record that fits the record no better has added error: the refit must fit its own
    # record REFIT_GAIN better too. Better is not enough (the ORNL Leaf HPPC at 25 °C: 9.2 → 8.1 mV on itself, its
    # first 1C discharge 57.5 → 58.2 mV): validation records decide where there are any
    return keep_refit(fit, refit, profile, validation, report, own_record=True, gain=VALIDATION_GAIN)


def keep_refit(fit: FitResult, refit: FitResult, profile: Profile, validation, report: dict,
               own_record: bool = False, gain: float = REFIT_GAIN):
    """``(refit or None, report)``: the keep rule of a base refit on a corrected OCV curve (this module's,
    :mod:`socbench.identify.relaxed_ocv`'s and :func:`socbench.identify.fit_test_effect.relax_rest_points`'): every RC
    branch's time constant within the record's duration (a slower branch only ramps with the charge moved and trades
    against the curve freely); with ``own_record`` the refit fits ``profile`` :data:`REFIT_GAIN` better; with
    ``validation`` records their mean open-loop RMSE falls by ``gain`` (0: no worse). ``report`` gains what was
    measured, ``kept`` and ``why_not`` (the first rule failed; None: kept)."""
    identified = branches_identified(refit.params, profile.duration_s)
    report.update({"fit_rmse_v": [fit.rmse_v, refit.rmse_v], "branches_identified": identified})
    why = None if identified else "an RC branch slower than the record"
    if why is None and own_record and refit.rmse_v > (1.0 - REFIT_GAIN) * fit.rmse_v:
        why = f"fit not {100 * REFIT_GAIN:.0f} % better"
    if validation:
        before, after = (float(np.mean([validation_rmse(f, r) for r in validation])) for f in (fit, refit))
        report["validation_rmse_v"] = [before, after]
        if why is None and after > (1.0 - gain) * before:
            why = f"validation not {100 * gain:.0f} % better" if gain > 0 else "validation worse"
    report.update({"kept": why is None, "why_not": why})
    return (refit if why is None else None), report
