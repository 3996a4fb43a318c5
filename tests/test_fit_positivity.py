"""Positive parameters fitted as SOC polynomials stay positive between their nodes (FitProblem.positivity).

The paper's 6th-degree polynomials are fitted through their values at 7 nodes, log-parametrised: positive at the
nodes, not between them. On the tests' generator (tests/hppc_records.py: random cells, layouts and instruments),
paper-mode fits before the positivity term had a resistance or capacitance below zero somewhere in [0, 1] in 20 of 24
fits (thevenin and dp, 12 draws; below −10 % of the parameter's median in 15).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import socbench.identify.fit as fit_module
from socbench.identify import fit_model
from socbench.identify.fit import setup_fit
from socbench.identify.lsq import simulate_voltage
from socbench.identify.specs import PolyForm
from socbench.models.registry import make_model

from . import hppc_records as H

Z = np.linspace(0.0, 1.0, 401)
DRAWS = 6


def _lowest_share(params) -> float:
    """The smallest value over [0, 1] of any parameter, as a share of that parameter's median magnitude."""
    out = np.inf
    for f in params.values.values():
        v = np.broadcast_to(f.value_and_deriv(Z)[0], Z.shape)
        out = min(out, float(np.min(v) / np.median(np.abs(v))))
    return out


def test_positivity_residual_is_zero_above_the_floor_and_grows_below_it():
    prob = setup_fit("thevenin", H.issue_record().profile, "paper")
    spec, form, sl = next(p for p in prob.positive_polynomials if p[0].name == "R1")
    assert isinstance(form, PolyForm)
    theta = prob.theta0.copy()
    theta[sl] = np.log(5e-3)  # a flat curve: nothing to hold
    assert not np.any(prob.positivity(theta))
    # node values spanning four decades: the curve between the nodes overshoots below zero
    theta[sl] = np.log([5e-3, 1e-6, 5e-3, 5e-3, 5e-3, 1e-6, 5e-2])
    curve = np.exp(theta[sl]) @ form.grid_matrix
    assert curve.min() < 0.0
    pen = prob.positivity(theta)[0]
    assert pen.max() > 0.0
    theta[sl] = np.log([5e-3, 1e-6, 5e-3, 5e-3, 5e-3, 1e-6, 5e-1])  # a bigger overshoot costs more
    assert prob.positivity(theta)[0].sum() > pen.sum()


@pytest.mark.slow
def test_paper_fits_stay_positive_and_predict_a_drive_no_worse(monkeypatch):
    lowest, drive_rmse = [], {"held": [], "free": []}
    for k in range(DRAWS):
        rng, cell, lay, ins = H.random_setup(90_000 + k)
        rec = H.hppc_record(cell, lay, ins, seed=k, with_soc_ref=lay.gaps)
        drive = H.drive_record(cell, dataclasses.replace(ins, dt=max(ins.dt, 1.0)), seed=k, duration_s=5400.0,
                               soc0=0.95).profile
        for name in ("thevenin", "dp"):
            for key in ("held", "free"):
                with monkeypatch.context() as mp:
                    if key == "free":  # no positivity term at all (nor its refit)
                        mp.setattr(fit_module.FitProblem, "positive_polynomials", property(lambda self: []))
                    res = fit_model(name, rec.profile, mode="paper", capacity_ah=cell.capacity_ah)
                if key == "held":
                    lowest.append(_lowest_share(res.params))
                model = make_model(name, res.params)
                y = simulate_voltage(model, drive.time_s, drive.current_a, drive.temperature_c, model.x0(0.95, (1,)))
                drive_rmse[key].append(float(np.sqrt(np.mean((y[0] - drive.voltage_v) ** 2))))
    # nothing below zero (the floor, 1 % of the median, is held softly: 0.9 % at the lowest on the Panasonic DP fit)
    assert min(lowest) > 0.0, lowest
    # what holding them costs out of the fit: a drive record of the same cell predicted about as well (25 draws of
    # this generator: mean 22.2 mV held against 22.4 mV free; lower in 23 fits of 50, higher in 13)
    assert np.mean(drive_rmse["held"]) <= 1.1 * np.mean(drive_rmse["free"]), drive_rmse


@pytest.mark.slow
def test_a_fit_whose_curve_the_soft_term_let_through_zero_is_refitted_positive(monkeypatch):
    """Where the finished fit still has a positive parameter at or below zero somewhere on [0, 1], it is refitted with
    the term ``POSITIVITY_REFIT_WEIGHT`` heavy and says so. Exercised by a term 1e4 times lighter than the default
    on random draws of the tests' generator (dp fits: with that term, 8 of 8 draws crossed zero and were refitted,
    all positive after; thevenin 1 of 8) — every fit comes out positive — and on the case that found it:
    improved_rc on the harsh scenario's noisy HPPC, whose R2 the default term left at −2.4e-5 Ω near SOC 0.013
    (the noise recipe's open loop then refused the model)."""
    from socbench.scenarios import load_scenario

    res = fit_model("improved_rc", load_scenario("harsh").characterisation(), mode="paper")
    assert any("R2 fell to zero or below" in w and "positive now" in w for w in res.warnings), res.warnings
    assert _lowest_share(res.params) > 0.0
    monkeypatch.setattr(fit_module, "POSITIVITY_WEIGHT", 1e-4)
    refitted = 0
    for k in (1, 2, 4):  # three of those eight draws (draws 0 and 3 take 10–20 s to fit)
        rng, cell, lay, ins = H.random_setup(91_000 + k)
        rec = H.hppc_record(cell, lay, ins, seed=k, with_soc_ref=lay.gaps)
        res = fit_model("dp", rec.profile, mode="paper", capacity_ah=cell.capacity_ah)
        refitted += any("refitted with a heavier positivity term" in w for w in res.warnings)
        assert _lowest_share(res.params) > 0.0, (k, res.warnings[-1:])
    assert refitted >= 2  # the light term did leave curves through zero: the refit ran
