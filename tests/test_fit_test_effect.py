"""The cell's properties found on the fit test itself (socbench.identify.fit_test_effect), before the effect search.

A generator of this file's own draws cells over ranges (a Thevenin structure; R0 10–60 mΩ·Ah/Q; a first branch of
5–40 s; with a second branch the fitted structure lacks, 150–1500 s and 0.3–1 × R0; or a hysteresis of 10–30 mV; or
neither), records an HPPC on it (1C pulses of 10–30 s, rests of 20–60 min, 10 % steps, sampled every 1–4 s, 1 mV
noise; beside it, for the hysteresis, a C/20 discharge and charge) and one evaluation record (mixed discharge pulses,
charges and rests). The rules are asserted as rates over the draws: the branch and the hysteresis are found where
they are, nothing where neither is. With a capacity fade of 10–20 % between the HPPC and the evaluation record, the
fade dominates that record's error and the branch is tried again beside it (``core.search_beside``).

An HPPC alone in the discharge direction shows little hysteresis: its rest points, the OCV the base is fitted on, lie
on the discharge branch already, and its brief charge pulses barely move the state (2 of these 6 draws without the
slow test). Beside a slow test whose mean branch is the OCV, the rests lie half a gap below it: that is the fit test
that shows it.
"""

from __future__ import annotations

import numpy as np
import pytest

from socbench import loads
from socbench.diagnose import core, diagnose
from socbench.diagnose.core import _coarse, effect_on_fit_test_record, fit_base
from socbench.diagnose.synthetic import eval_current
from socbench.identify import fit_model, fit_test_effect
from socbench.identify.fit_test_effect import _at_bound
from socbench.models import Constant, ModelParams, make_model, paper_ocv
from socbench.models.effects import augment, make_effect
from socbench.ocv import OCVCurve
from socbench.profile import Profile, ProfileMeta

DRAWS = 6


def _measure(model, prof, soc0, rng, name, q, v_sd=1e-3):
    sim = model.simulate(prof, soc0=soc0)
    v = sim.voltage_v + rng.normal(0.0, v_sd, prof.n)
    meta = ProfileMeta(name=name, source=name, capacity_ah=q, n_series=1)
    return Profile(prof.time_s, prof.current_a, voltage_v=v, temperature_c=np.full(prof.n, 25.0),
                   soc_ref=np.clip(sim.soc, 0.0, 1.0), meta=meta)


def draw(kind: str, seed: int, fade: float = 0.0):
    """``(truth effect values or None, fit records, evaluation records)`` of one drawn cell (module docstring);
    ``fade``: the cell has lost this share of its capacity between the fit test and the evaluation record."""
    rng = np.random.default_rng([seed, {"extra_rc": 1, "hysteresis": 2, None: 3}[kind]])
    q = float(np.exp(rng.uniform(np.log(2.0), np.log(20.0))))
    r0 = rng.uniform(0.01, 0.06) / q
    pack = paper_ocv()
    params = ModelParams(q, OCVCurve(pack.soc, pack.voltage / 6.0, "paper pack OCV / 6"),
                         {"R0": Constant(r0), "R1": Constant(rng.uniform(0.3, 1.0) * r0),
                          "C1": Constant(rng.uniform(5.0, 40.0) / r0)})
    truth = make_model("thevenin", params)
    values = None
    if kind == "extra_rc":
        values = {"R": rng.uniform(0.3, 1.0) * r0, "log10_tau": np.log10(rng.uniform(150.0, 1500.0))}
    elif kind == "hysteresis":
        values = {"M": rng.uniform(0.01, 0.03), "M0": 0.0, "gamma": rng.uniform(30.0, 150.0), "h0": 1.0,
                  "h_ref": -1.0}
    effects = [] if values is None else [make_effect(kind, **values)]
    aged = augment(truth, effects + [make_effect("capacity", cap0=1.0 / (1.0 - fade))]) if fade else None
    truth = augment(truth, effects) if effects else truth
    hp = loads.hppc(q, dt=float(rng.uniform(1.0, 4.0)), rest_s=float(rng.uniform(1200.0, 3600.0)),
                    pulse_s=float(rng.choice([10.0, 18.0, 30.0])))
    fit = [_measure(truth, hp, 1.0, rng, "fit", q)]
    if kind == "hysteresis":  # a C/20 discharge and charge beside the HPPC: the OCV is the mean of both branches
        dt = 20.0
        segs = [(0.0, 3600.0), (q / 20.0, 0.97 * 72000.0), (0.0, 3600.0), (-q / 20.0, 0.97 * 72000.0), (0.0, 3600.0)]
        cur = np.concatenate([np.full(int(d / dt), a) for a, d in segs])
        fit.append(_measure(truth, Profile(np.arange(cur.size) * dt, cur), 1.0, rng, "slow", q))
    t, i = eval_current("pulses", q, seed)
    return values, fit, [_measure(aged or truth, Profile(t, i), 0.95, rng, "eval", q)]


def found(kind: str, seed: int):
    values, fit, evals = draw(kind, seed)
    evals = [_coarse(p, 1.0, 4000) for p in evals]
    base, info = fit_base("thevenin", fit, "auto", validation=evals)
    refit, _ = effect_on_fit_test_record("thevenin", base, fit, evals, info)
    return values, refit, info


@pytest.mark.parametrize("kind", ["extra_rc", "hysteresis"])
def test_a_property_the_fit_test_shows_is_found_there(kind):
    hits, close = 0, 0
    for seed in range(DRAWS):
        values, refit, info = found(kind, seed)
        if refit is not None and refit.params.effects[0]["name"] == kind:
            hits += 1
            got = refit.params.effects[0]["values"]
            if kind == "extra_rc":  # the branch's time constant within ×2 of the truth's
                close += abs(got["log10_tau"] - values["log10_tau"]) <= np.log10(2.0)
            else:  # the half-gap within 30 % of the truth's
                close += abs(got["M"] - values["M"]) <= 0.3 * values["M"]
    assert hits >= DRAWS - 1, (kind, hits)
    assert close >= hits - 1, (kind, close, hits)


def test_nothing_is_found_on_the_fit_test_of_a_cell_without_either():
    kept = [(seed, info["fit_test_effect"]["kept"]) for seed in range(DRAWS)
            for _, refit, info in [found(None, seed)] if refit is not None]
    assert not kept, kept


def test_a_fit_test_effect_is_a_step_scored_on_data_it_was_not_fitted_on():
    """The diagnosis names the branch the HPPC shows as its first step, found on the fit test; the step's error after
    is that of the base and branch fitted on the fit test alone, and the base before is the one fitted without it.
    With ``fit_test=False`` the step is not there."""
    values, fit, evals = draw("extra_rc", 0)
    d = diagnose("thevenin", fit, evals, soc=False)
    first = d.steps[0]
    assert first.effect == "extra_rc" and first.fit_test, d.effects_added
    assert d.to_dict()["steps"][0]["found_on"] == "fit test"
    assert first.rmse_before == pytest.approx(d.before["rmse_v"])
    assert first.rmse_after <= 0.9 * first.rmse_before
    rows = first.fit.thetas
    assert np.allclose(rows, rows[0])  # one parameter row for every fold: nothing fitted on the evaluation data
    off = diagnose("thevenin", fit, evals, soc=False, fit_test=False)
    assert not any(s.fit_test for s in off.steps)
    assert off.before["rmse_v"] == pytest.approx(d.before["rmse_v"])


def test_an_effect_parameter_at_its_bound_is_not_identified():
    _, fit, _ = draw(None, 0)
    res = fit_model("thevenin", fit[0], mode="constant", effects=[make_effect("hysteresis", gamma=1.0)])
    vals = dict(res.params.effects[0]["values"])
    assert "gamma" in (_at_bound("hysteresis", {**vals, "gamma": 1.0, "M": 0.01, "M0": 0.0}, res) or "")
    assert "M =" in (_at_bound("hysteresis", {**vals, "gamma": 50.0, "M": 0.0, "M0": 0.0}, res) or "")
    assert _at_bound("hysteresis", {**vals, "gamma": 50.0, "M": 0.01, "M0": 0.0}, res) is None
    # the initial state may rest on its physical limit
    assert _at_bound("hysteresis", {**vals, "gamma": 50.0, "M": 0.01, "M0": 0.0, "h0": -1.0}, res) is None



def _fade(seed: int) -> float:
    """The capacity lost between the fit test and use in draw ``seed``: 10–20 %."""
    return float(np.random.default_rng([seed, 4]).uniform(0.1, 0.2))


@pytest.mark.slow
def test_a_branch_a_fade_hides_on_the_evaluation_record_is_tried_beside_it(monkeypatch):
    """The cell has lost 10–20 % of its capacity since its HPPC: the evaluation record's error is the fade's, and the
    branch the HPPC shows (fitted there) predicts it no better alone. Deferred (the default), the refit is tried again
    beside what the search adds: the branch is named beside the fade in at least half the draws and in more than
    without the deferral, and where the deferred refit is kept, the held-out RMSE ends 10 % below the diagnosis
    without it. "Without it" is what the diagnosis reports of its search before the deferral
    (``fit_test_effect.without_it``); on the first draw where the deferral is kept, a diagnosis with the deferral off
    gives exactly that.

    The deferral is measured with the rests' evidence off (``REST_GAIN`` above 1): where the HPPC's rests show the
    branch it is a first step held only to "not worse" on the evaluation record, and named beside the fade without
    any deferral (5 of these 6 draws, with and without it)."""
    monkeypatch.setattr(fit_test_effect, "REST_GAIN", 2.0)
    named = {True: 0, False: 0}
    checked = False
    for seed in range(DRAWS):
        _, fit, evals = draw("extra_rc", seed, fade=_fade(seed))
        on = diagnose("thevenin", fit, evals, soc=False)
        without = on.fit.get("fit_test_effect", {}).get("without_it")  # the search as it ended before the deferral
        off = without["effects"] if without is not None else on.effects_added
        named[True] += set(on.effects_added) == {"extra_rc", "capacity"}
        named[False] += set(off) == {"extra_rc", "capacity"}
        if any(s.fit_test and "beside the later steps" in s.evidence for s in on.steps):
            assert on.fit["fit_test_effect"]["deferred"] == "extra_rc"
            assert on.after["rmse_v"] <= 0.9 * without["rmse_v"], (seed, on.after, without)
            if not checked:  # once: what the diagnosis reports as "without it" is the diagnosis without the deferral
                monkeypatch.setattr(core, "DEFER_FIT_TEST", False)
                plain = diagnose("thevenin", fit, evals, soc=False)
                monkeypatch.setattr(core, "DEFER_FIT_TEST", True)
                assert not any("beside the later steps" in s.evidence for s in plain.steps)
                assert plain.effects_added == without["effects"], (plain.effects_added, without)
                assert plain.after["rmse_v"] == pytest.approx(without["rmse_v"], rel=1e-12)
                checked = True
    assert checked
    assert named[True] >= DRAWS // 2 and named[True] > named[False], named


@pytest.mark.slow
def test_a_fade_alone_has_no_branch_named_beside_it():
    for seed in range(DRAWS):
        _, fit, evals = draw(None, seed, fade=_fade(seed))
        d = diagnose("thevenin", fit, evals, soc=False)
        assert "extra_rc" not in d.effects_added, (seed, d.effects_added)


def test_the_fit_test_gain_is_judged_in_the_base_form_where_constant_mode_hides_it(monkeypatch):
    """Case 69 of the development seed 4242: a flat LFP cell with a 17 mV hysteresis (γ ≈ 130), fitted by a Thevenin
    whose chosen form is SOC-lookup. In constant mode the hysteresis refit fits the HPPC 6 % better (13.93 → 13.04 mV,
    short of the 10 % asked); in the base's own form 12 % better (open loop, 5.74 → 5.07 mV), and it predicts the
    evaluation records 19 % better. With the gain judged in the base's form where constant mode falls short, it is the
    first step; judged in constant mode only, the search names nothing."""
    from socbench.diagnose.randomized import draw_case

    case = draw_case(69, 4242, gaps=False)
    assert case.effects == ("hysteresis",)
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    report = next(r for r in d.fit["fit_test_effect"]["reports"] if r["effect"] == "hysteresis")
    constant_before, constant_after = report["fit_rmse_v"]
    form_before, form_after = report["fit_rmse_v_in_form"]
    assert constant_after > (1.0 - fit_test_effect.FIT_GAIN) * constant_before  # constant mode falls short
    assert form_after <= (1.0 - fit_test_effect.FIT_GAIN) * form_before
    assert d.effects_added[:1] == ["hysteresis"] and d.steps[0].fit_test, d.effects_added
    assert d.after["rmse_v"] < 0.9 * d.before["rmse_v"]
    monkeypatch.setattr(fit_test_effect, "IN_FORM_GAIN", False)
    plain = diagnose(case.base, case.fit, case.evals, soc=False)
    assert "hysteresis" not in plain.effects_added, plain.effects_added
