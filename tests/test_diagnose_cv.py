"""Blocked cross-validation of the diagnosis: honest held-out scores, an effect that shows in part of the data only,
and the SOC estimate of the augmented model.

* honest: the parameters fold j fits never depend on the voltage of block j (corrupt it, they do not move, to
  rounding), while the all-data fit and the other folds do;
* split-proof: hysteresis that only shows after the first recharge, in the second half of a single record, is found
  (one first/second-half cut fits on a half where it leaves no trace);
* SOC: adding the found effect does not make the EKF's or the UKF's held-out SOC error worse by more than 0.2 points.
"""

from __future__ import annotations

import numpy as np
import pytest

from socbench import loads
from socbench.diagnose import diagnose, make_folds
from socbench.diagnose.core import _coarse, fit_base, soc_attribution
from socbench.diagnose.search import Search
from socbench.diagnose.synthetic import cell, hidden_case
from socbench.models import make_model
from socbench.models.effects import augment, make_effect
from socbench.profile import Profile, ProfileMeta


def test_fold_parameters_never_see_their_held_out_block():
    fit, ev = hidden_case("capacity", "thevenin", "pulses", "small", v_sd=1e-3, seed=3)
    base, info = fit_base("thevenin", [fit], "constant")
    rec = _coarse(ev, 1.0, 4000)
    folds = make_folds([rec], 4)
    search = Search(base, folds, info["t_ref_c"], base_refit=False)
    theta0 = np.array([1.05])
    clean = search.fit(["capacity"], theta0)[0]
    bad_v = rec.voltage_v + np.where(folds.blocks[0] == 2, 0.05 + 0.01 * np.sin(np.arange(rec.n)), 0.0)
    corrupt = make_folds([rec.with_(voltage_v=bad_v)], 4)
    dirty = Search(base, corrupt, info["t_ref_c"], base_refit=False).fit(["capacity"], theta0)[0]
    np.testing.assert_allclose(dirty.row(2), clean.row(2), rtol=1e-12, atol=1e-12)
    assert abs(dirty.row(None)[0] - clean.row(None)[0]) > 1e-4  # the all-data fit sees block 2
    assert max(abs(dirty.row(j)[0] - clean.row(j)[0]) for j in (0, 1, 3)) > 1e-4  # so do the other folds
    assert abs(clean.row(2)[0] - 1.15) < 0.05  # and the fit itself is right: the hidden capacity factor


def _late_hysteresis_record(seed: int):
    """A thevenin cell with hysteresis (M = 25 mV) starting on the discharge branch: the first half of the record
    discharges in pulses (h stays at −1, where the HPPC's rest points put the OCV), the second half recharges
    partially between pulses, so the hysteresis shows only there."""
    rng = np.random.default_rng(seed)
    name, params = cell("thevenin")
    q = params.capacity_ah
    truth = augment(make_model(name, params), [make_effect("hysteresis", M=0.025, M0=0.0, gamma=40.0, h0=-1.0)])
    segs = []
    for _ in range(16):  # first half: discharge pulses and rests
        segs += [(q * rng.uniform(0.3, 0.8), rng.uniform(60, 120)), (0.0, rng.uniform(120, 300))]
    for _ in range(5):  # second half: recharges and discharges
        segs += [(-q * rng.uniform(0.5, 1.0), rng.uniform(200, 400)), (0.0, rng.uniform(120, 300)),
                 (q * rng.uniform(0.5, 1.5), rng.uniform(150, 300)), (0.0, rng.uniform(120, 300))]
    i = np.concatenate([np.full(int(s / 2.0), a) for a, s in segs])
    t = np.arange(i.size) * 2.0
    prof = Profile(t, i, temperature_c=np.full(t.size, 25.0))
    sim = truth.simulate(prof, soc0=0.95)
    meta = ProfileMeta(name="late", source="late", capacity_ah=q)
    ev = Profile(t, i, voltage_v=sim.voltage_v + rng.normal(0, 1e-3, t.size), temperature_c=prof.temperature_c,
                 soc_ref=np.clip(sim.soc, 0, 1), meta=meta)
    hp = loads.hppc(q, dt=2.0, rest_s=1800.0)
    v_hp = truth.simulate(Profile(hp.time_s, hp.current_a), soc0=1.0).voltage_v + rng.normal(0, 1e-3, hp.n)
    fit = Profile(hp.time_s, hp.current_a, voltage_v=v_hp, temperature_c=np.full(hp.n, 25.0),
                  meta=ProfileMeta(name="hppc", source="hppc", capacity_ah=q))
    return fit, ev, truth


def test_an_effect_that_shows_only_in_the_second_half_of_the_record_is_found():
    fit, ev, _ = _late_hysteresis_record(21)
    d = diagnose("thevenin", [fit], [ev])
    e, blocks = d.held_out_residual["before"], d.split.blocks[0]
    first, second = np.sqrt(np.mean(e[blocks < 2] ** 2)), np.sqrt(np.mean(e[blocks >= 2] ** 2))
    assert second > 4 * first  # the base model's error lives in the second half
    assert d.effects_added[:1] == ["hysteresis"], [(c.effect, c.score) for c in d.rounds[0]["candidates"]]
    assert d.after["rmse_v"] <= 0.5 * d.before["rmse_v"]
    # and the filters' SOC is not made worse by the added states (0.2 points)
    for name in ("ekf", "ukf"):
        assert d.after["soc"][name]["soc_rmse"] <= d.before["soc"][name]["soc_rmse"] + 0.002


@pytest.mark.parametrize("effect,load,seed", [("capacity", "pulses", 31), ("current_bias", "rests", 32)])
def test_soc_of_the_augmented_model_is_not_worse(effect, load, seed):
    fit, ev = hidden_case(effect, "thevenin", load, "small", v_sd=1e-3, seed=seed)
    d = diagnose("thevenin", [fit], [ev])
    assert effect in d.effects_added
    for name in ("ekf", "ukf"):
        assert d.after["soc"][name]["soc_rmse"] <= d.before["soc"][name]["soc_rmse"] + 0.002, d.after["soc"]
    if effect == "capacity":
        att = soc_attribution(d, [ev])
        for key in ("before", "after"):  # its "own" runs are the diagnosis' own SOC numbers, recomputed
            for name in ("ekf", "ukf"):
                assert att[key]["own"][name] == pytest.approx(getattr(d, key)["soc"][name]["soc_rmse"], rel=1e-6)
        # with the voltage ignored the filters count the current: on the fitted capacity (after) far better than on
        # the base model's, 15 % off
        for name in ("ekf", "ukf"):
            assert att["after"]["voltage_ignored"][name] < 0.5 * att["before"]["voltage_ignored"][name], att


@pytest.mark.parametrize("effect,measured", [("temperature", True), (None, False), ("capacity", False)])
def test_a_measured_temperature_away_from_the_fit_is_evidence(effect, measured):
    # the synthetic temperature case warms from −5 to 20 °C against a 25 °C fit; the others stay at the fit's 25 °C
    fit, ev = hidden_case(effect, "thevenin", "pulses", "small", v_sd=1e-3, seed=5)
    base, info = fit_base("thevenin", [fit], "constant")
    search = Search(base, make_folds([_coarse(ev, 1.0, 4000)], 4), info["t_ref_c"], base_refit=False)
    assert search.temperature_measured is measured



def test_two_starts_each_fold_keeps_the_fit_of_its_own_training_samples():
    """A candidate fitted from two starts (the signature's guesses, the effect's defaults) keeps, group by group, the
    rows of the start that fits that group's training samples better: every group's training error is the lower of the
    two, and fold j's row never depends on the voltage of block j (corrupt it: the row does not move, to rounding)."""
    from socbench.diagnose.cv import cv_residual
    from socbench.diagnose.search import effective_samples
    from socbench.diagnose.signatures import signatures

    fit, ev = hidden_case("extra_rc", "thevenin", "pulses", "large", v_sd=1e-3, seed=0)
    base, info = fit_base("thevenin", [fit], "constant")
    rec = _coarse(ev, 1.0, 4000)

    def both_starts(record):
        search = Search(base, make_folds([record], 4), info["t_ref_c"], base_refit=False)
        trajs = search.trajectories(None, None)
        fold_sigs = {g: signatures(base, trajs[g], search.bounds, search.t_ref, search.rows[g])
                     for g in search.groups if g is not None}
        fold_sigs[None] = signatures(base, trajs[None], search.bounds, search.t_ref)
        r0, _, _ = cv_residual(base, search.folds, search.soc0s)
        rmse0, n_eff, sig = float(np.sqrt(np.mean(r0 ** 2))), effective_samples(r0), fold_sigs[None]["extra_rc"]
        a = search._try("extra_rc", [], None, fold_sigs, sig, rmse0, n_eff)
        b = search._try("extra_rc", [], None, {}, sig, rmse0, n_eff)
        return search, a, b, search._better(a, b, sig, n_eff)

    search, a, b, best = both_starts(rec)
    sa, sb, s_best = search._group_sse(a), search._group_sse(b), search._group_sse(best)
    assert np.any(sb < sa * (1 - 1e-6)) and np.any(sa < sb * (1 - 1e-6)), (sa, sb)  # each start wins a group
    np.testing.assert_allclose(s_best, np.minimum(sa, sb), rtol=1e-9)
    folds = make_folds([rec], 4)
    bad_v = rec.voltage_v + np.where(folds.blocks[0] == 1, 0.05 + 0.01 * np.sin(np.arange(rec.n)), 0.0)
    _, _, _, dirty = both_starts(rec.with_(voltage_v=bad_v))
    np.testing.assert_allclose(dirty.fit.row(1), best.fit.row(1), rtol=1e-10, atol=1e-12)
