"""A filter of the EKF family started where the OCV curve is held flat (a guess of 0 % on a curve whose lowest rest
point lies at 10–30 %: an HPPC that stopped above empty) gets no gain on the SOC and never leaves: its prior mean is
moved to the edge of the curve's extrapolation band when that lies within one prior SD
(socbench.estimators.base.out_of_held_ocv). Over random cells, drives and starts."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from socbench.estimators import make_estimator
from socbench.estimators.base import out_of_held_ocv
from socbench.models import make_model, paper_params
from socbench.models.params import Constant
from socbench.ocv import EXCURSION_FLAG, OCVCurve
from socbench.profile import Profile, ProfileMeta

LINEARISED = ("ekf", "hinf")  # the IEKF runs numpy here: 20 s for the same rule


def _cell(rng):
    """The paper's Thevenin pack, its parameters constant (a constant-mode fit: nothing but the OCV moves the voltage
    with the SOC) at their mid-SOC values ×0.5–2, with an OCV curve measured from ``z_lo`` ∈ [0.1, 0.3] up (an
    NMC-like shape scaled to the pack)."""
    params = paper_params("thevenin")
    z_lo = rng.uniform(0.1, 0.3)
    soc = np.linspace(z_lo, 1.0, 12)
    volt = 3.3 + 0.75 * soc + 0.12 * np.tanh((soc - 0.15) / 0.08)
    values = {k: Constant(float(f(0.5)) * rng.uniform(0.5, 2.0)) for k, f in params.values.items()}
    ocv = OCVCurve(soc, params.ocv.voltage[-1] / volt[-1] * volt)
    return make_model("thevenin", dataclasses.replace(params, ocv=ocv, values=values)), z_lo


def _drive(model, rng, z0: float, hours: float = 0.5):
    """A noisy drive of random 1 s load from ``z0``: ``(profile with voltage and reference, true SOC)``."""
    n = int(hours * 3600)
    t = np.arange(n, dtype=float)
    q = model.capacity_ah
    cur = q * np.clip(0.3 + 0.5 * np.sin(t / rng.uniform(60, 400)) + 0.2 * rng.standard_normal(n), -0.5, 1.5)
    sim = model.simulate(Profile(t, cur, meta=ProfileMeta(capacity_ah=q)), soc0=z0, segments=False)
    v = sim.voltage_v + rng.normal(0.0, 0.005 * model.params.ocv.voltage[-1] / 4.2, n)
    return Profile(t, cur, v, soc_ref=np.clip(sim.soc, 0, 1), meta=ProfileMeta(capacity_ah=q, name="drive")), sim.soc


def test_the_prior_mean_moves_to_the_band_edge_only_within_one_sd():
    rng = np.random.default_rng(7)
    for _ in range(50):
        model, z_lo = _cell(rng)
        z = rng.uniform(0.0, 1.0, 40)
        sd = rng.uniform(0.01, 0.5, 40)
        x0 = model.x0(z, (40,))
        moved, info = out_of_held_ocv(model, x0, sd, None)
        edge = z_lo - EXCURSION_FLAG
        held = z < edge
        want = np.where(held & (edge - z <= sd), edge, z)
        np.testing.assert_allclose(moved[:, 0], want, atol=1e-12)
        np.testing.assert_array_equal(moved[:, 1:], x0[:, 1:])  # only the SOC moves
        n = int(np.sum(held & (edge - z <= sd)))
        assert (info is None) == (n == 0) and (info is None or info["runs"] == n)


@pytest.mark.parametrize("name", LINEARISED)
def test_a_filter_started_on_the_held_ocv_finds_the_soc(name):
    """Ten random cells each: the truth starts at 50–90 %, the filter at 0 with SD 0.3. Moved to the band's edge the
    filter's final SOC error is below 2 % in every draw (measured: at most 0.9 %); with the rule off (the mean kept on
    the flat part) it stays near 0 (measured: 34–71 points off in all 20) — the failure the rule removes."""
    rng = np.random.default_rng(abs(hash(name)) % 2**31)
    errors, stuck = [], []
    for _ in range(10):
        model, _ = _cell(rng)
        prof, z_true = _drive(model, rng, rng.uniform(0.5, 0.9))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est = make_estimator(name, model, soc0_sd=0.3).run(prof, soc0=0.0, segments=False)
            assert est.info["soc0_moved_out_of_held_ocv"]["runs"] == 1
            errors.append(abs(float(est.soc[0, -1]) - z_true[-1]))
            off_class = type("RuleOff", (type(make_estimator(name, model)),), {"linearises_output": False})
            off = off_class(model, soc0_sd=0.3).run(prof, soc0=0.0, segments=False)
            stuck.append(abs(float(off.soc[0, -1]) - z_true[-1]))
    assert max(errors) < 0.02, errors
    assert sum(e > 0.1 for e in stuck) >= 9, stuck
