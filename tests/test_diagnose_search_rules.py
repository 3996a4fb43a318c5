"""Rules of the effect search (socbench.diagnose.search), each on a randomised-benchmark case where it decides
the outcome (seed 7 of socbench.diagnose.randomized; the CI rates run its first 20 cases, these lie beyond them):

* the voltage noise is measured again on the residual of the model as it grows: a base model far off in the cold
  reads its own error at the drive cycle's current edges as noise (30× the sensor's), whose floor would stop the
  search; after the temperature step the estimate is back near the sensor's;
* a current offset the rests of the records measure is added as a measurement, even where another effect's error
  (the cold) hides what it does to the voltage, and the temperature is found beside it;
* an SOC drift named in one round is swapped for the drift the records hold once the later steps are in the model
  (a fade with grown resistances: a leak at its bound won the round alone; with the base refit beside it the fade
  explains more); by default that leak, at the limit of its physical range, is not scored at all, and the fade is
  named at once;
* a drift at the limit of its physical range is not scored (a synthetic leak of exactly 5 %/h: the rule's cost);
* an extra RC branch within ×TWIN_TAU of a branch of the base *as the base refit made it* is not named (a constant
  twin beside a looked-up branch buys that branch a new SOC shape: base-fit error, not a branch the structure lacks);
* nor is an extra branch named anywhere when two of the base's own branches lie within ×TWIN_TAU of each other, or
  one is slower than any branch (a ramp): one of them is spare, and the extra one is where it belongs, kept in the
  model as base-fit error: the rules on the paper's DP (its slow branch moved next to the fast one, or to a ramp),
  on a null case of the development seed 47 whose lookup fit put both DP branches at one time constant, and on the
  same case with its HPPC file's gaps (its step discharges unlogged: the DP fit leaves its slow branch at
  τ ≈ 10¹¹ s);
* where neither an effect nor the base refit cuts the error alone in the first round, the effect fitted jointly with
  the refit can (a hidden branch on the development seed 31, part of which the HPPC fit gave to the base's own
  parameters: alone it finds the base holding that part, the refit alone cannot make a branch the structure lacks);
* a state whose rate rests at the slow end of its range (a hysteresis at Plett's γ floor) is not scored: a null case
  of the development seed 31;
* the search run again without the first effect it named is kept where it ends 10 % lower (a hysteresis that won the
  first round from a slow branch beside a charge-transfer term, on the development seed 31);
* an effect the fit test measures is named where it predicts the evaluation records 10 % better, though the base
  already lies within the search's noise floor there (a hysteresis a slow OCV test shows, on the development seed 31);
* an effect the fit test found is dropped at the end only where the records do no worse without it, not within the
  search's 10 % (a hysteresis the base refit nearly takes up, on the development seed 777).
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from socbench.diagnose import diagnose
from socbench.diagnose.randomized import draw_case


@functools.cache
def _fade_case():
    """Case 18 of seed 7 (a fade with grown resistances) and its diagnosis with the defaults: two tests read it."""
    case = draw_case(18, 7, gaps=False)
    return case, diagnose(case.base, case.fit, case.evals, soc=False)


def test_noise_remeasured_and_measured_offset_taken_in_the_cold():
    case = draw_case(23, 7, gaps=False)
    assert set(case.effects) == {"current_bias", "temperature"}
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    true_binned = case.draws["v_sd"] / np.sqrt(max(1.0, 1.0 / case.draws["eval_dt_s"]))
    first, final = d.fit["voltage_noise_sd_binned"], d.fit["voltage_noise_sd_binned_final"]
    assert first > 10 * true_binned  # the base model's error read as noise
    assert final < 3 * true_binned, (final, true_binned)
    assert d.effects_added[0] == "current_bias" and "temperature" in d.effects_added, d.effects_added
    assert d.after["rmse_v"] <= 0.1 * d.before["rmse_v"]


@pytest.mark.slow
def test_soc_drift_swapped_beside_the_later_steps(monkeypatch):
    """The leak that wins the first round alone rests on its bound (5 %/h): by default it is not scored
    (``DRIFT_AT_BOUND``) and the fade is named with no swap; without that rule the fade takes the leak's place when
    the round's drifts are fitted beside the base refit (``DRIFT_BESIDE_REFIT``), and without that either, the swap
    at the end puts it there."""
    import socbench.diagnose.search as search

    case, d = _fade_case()
    assert case.effects == ("capacity",)
    assert d.effects_added == ["capacity"], [(s.effect, s.evidence) for s in d.steps]
    assert not any("swapped" in s.evidence or "in place of" in s.evidence for s in d.steps)
    monkeypatch.setattr(search, "DRIFT_AT_BOUND", False)
    for beside, how in ((True, "in place of self_discharge"), (False, "swapped")):
        monkeypatch.setattr(search, "DRIFT_BESIDE_REFIT", beside)
        d = diagnose(case.base, case.fit, case.evals, soc=False)
        assert d.effects_added == ["capacity"], [(s.effect, s.evidence) for s in d.steps]
        assert any(how in s.evidence for s in d.steps), [s.evidence for s in d.steps]
        assert d.after["rmse_v"] <= 0.3 * d.before["rmse_v"]


def test_the_drift_swap_keeps_to_the_candidates_asked_for():
    """The swap of an SOC drift (``Search._swap_drift``) chooses among the drifts the search was asked to try only.
    Case 143 of seed 2026 (a leak and a branch hidden in a Thevenin cell, a mission day with partial recharges):
    offered the branch and the leak alone (``--effects extra_rc,self_discharge``), the search named the leak and
    then swapped in the charge efficiency, an effect nobody asked for (found at stop 60; the oracle runs of
    benchmarks/undeclared_effects.py offer one candidate and met the same swap)."""
    case = draw_case(143, 2026, gaps=False)
    assert set(case.effects) == {"extra_rc", "self_discharge"}
    asked = ["extra_rc", "self_discharge"]
    d = diagnose(case.base, case.fit, case.evals, soc=False, candidates=asked)
    assert set(d.effects_added) <= set(asked), [(s.effect, s.evidence) for s in d.steps]
    assert "self_discharge" in d.effects_added


def test_an_effect_the_final_model_does_not_need_is_dropped_at_the_end():
    """The backward half of stepwise selection (``Search._prune``): a named effect whose removal, everything else
    refitted jointly, costs less than the forward step's gain is dropped; the effect the records hold stays. The
    spurious step is real: the best-scoring of the effects left out, fitted beside the final model."""
    from socbench.diagnose.search import effective_samples

    _, d = _fade_case()
    s, final = d.search, d.steps[-1]
    assert d.effects_added == ["capacity"]
    names = [n for n, _ in final.layout]
    empty = {g: {} for g in s.groups}
    n_eff = effective_samples(final.held_residual)
    extras = [s._try(e, names, final.fit.thetas, empty, None, final.rmse_after, n_eff)
              for e in ("coulombic_efficiency", "self_discharge", "hysteresis", "extra_rc")
              if e not in names and s.applicable(e) is None]
    extra = min((c for c in extras if c.fit is not None), key=lambda c: c.rmse_after)
    # it explains less than an added effect must (else the forward search would have taken it)
    assert extra.rmse_after > (1.0 - s.min_gain) * final.rmse_after
    pruned = s._prune(list(d.steps) + [extra], final.held_residual)
    assert [st.effect for st in pruned if st.effect != "base_refit"] == ["capacity"], [st.effect for st in pruned]
    assert "dropped at the end" in pruned[-1].evidence and extra.effect in pruned[-1].evidence
    assert pruned[-1].rmse_after <= final.rmse_after / (1.0 - s.min_gain)
    # the fade itself is needed: pruning the search's own answer leaves it as it is
    assert [st.effect for st in s._prune(list(d.steps), final.held_residual)] == [st.effect for st in d.steps]


def test_an_extra_branch_that_twins_a_refitted_branch_is_not_named():
    """A null case on a DP base (no hidden effect): the base refit wins the first round; fitted beside it, the extra
    RC branch lands within ×TWIN_TAU of one of the base's branches as the refit rescaled it (``τ_j·s_Rj·s_Cj``). It
    is scored out and says why (before, the rule was not applied once the refit was in the model)."""
    from socbench.diagnose.search import BASE_REFIT, TWIN_TAU
    from socbench.identify.fit import branch_time_constants

    case = draw_case(30, 7, gaps=False)
    assert case.effects == () and case.base == "dp"
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    assert d.steps and d.steps[0].effect == BASE_REFIT and "extra_rc" not in d.effects_added
    base_taus = branch_time_constants(d.base_model.params, d.base_model.required_params())
    twins = 0
    for c in [c for r in d.rounds[1:] for c in r["candidates"] if c.effect == "extra_rc" and c.fit is not None]:
        layout = [n for name, ps in c.layout for n in ((name, p) for p in ps)]
        row = dict(zip(layout, c.fit.row(None)))
        tau = 10.0 ** c.params["log10_tau"]
        refitted = {b: t * np.exp(row[(BASE_REFIT, f"log_R{b[1]}")] + row[(BASE_REFIT, f"log_C{b[1]}")])
                    for b, t in base_taus.items()}
        near_refitted = min(abs(np.log(tau / t)) for t in refitted.values()) <= np.log(TWIN_TAU)
        if near_refitted:
            assert c.score == -np.inf and "as refitted" in c.evidence, c.evidence
            twins += 1
    assert twins >= 1  # the case holds one


def _search_on(model):
    """A Search on ``model`` over a short constant-current record (the rules below read only the base's branches)."""
    from socbench.diagnose.data import make_folds
    from socbench.diagnose.search import Search
    from socbench.profile import Profile

    t = np.arange(0.0, 600.0, 1.0)
    i = np.full(t.size, 0.5 * model.capacity_ah)
    v = np.full(t.size, 3.7)
    return Search(model, make_folds([Profile(t, i, v, None, np.linspace(0.9, 0.8, t.size))]), 25.0)


def test_two_base_branches_at_one_time_constant_leave_one_to_spare():
    """``Search.spare_branch``: two RC branches of the base within ×TWIN_TAU of each other (the paper's DP: 748 and
    1403 s) are one branch and a spare; the base refit's scales move them (``τ_j·s_Rj·s_Cj``), apart or together."""
    from socbench.diagnose.search import TWIN_TAU
    from socbench.identify.fit import branch_time_constants
    from socbench.models import make_model, paper_params

    dp = make_model("dp", paper_params("dp"))
    taus = branch_time_constants(dp.params, dp.required_params())
    (b1, t1), (b2, t2) = sorted(taus.items(), key=lambda kv: kv[1])
    assert t2 / t1 < TWIN_TAU  # the premise: the paper's two branches lie within the window
    s = _search_on(dp)
    spare = s.spare_branch()
    assert spare is not None and {spare[0][0], spare[1][0]} == {b1, b2}
    # a refit that moves the slower branch ×(2·TWIN_TAU) away leaves none to spare
    apart = {f"log_C{b2[1]}": float(np.log(2.0 * TWIN_TAU))}
    assert s.spare_branch(apart) is None
    moved = s.refitted_taus(apart)
    assert np.isclose(moved[b2], t2 * 2.0 * TWIN_TAU) and np.isclose(moved[b1], t1)
    # and one that brings a branch far from the other next to it makes one again
    far = {f"log_R{b2[1]}": float(np.log(2.0)), f"log_C{b2[1]}": float(np.log(3.0))}  # ×6, still under 10⁴ s
    assert s.spare_branch(far) is None
    assert s.spare_branch({**far, f"log_C{b1[1]}": float(np.log(6.0 * t2 / t1))}) is not None


def test_a_base_branch_slower_than_any_branch_is_spare():
    """``Search.spare_branch``: a base branch whose time constant (as the base refit made it) lies beyond the slowest
    an extra branch may have (the upper end of its ``log10_tau`` range) is spare on its own; brought back within
    that range by the refit's scales, and clear of the other branch, it is not."""
    from socbench.identify.fit import branch_time_constants
    from socbench.models import make_model, paper_params

    dp = make_model("dp", paper_params("dp"))
    (b1, t1), (b2, t2) = sorted(branch_time_constants(dp.params, dp.required_params()).items(),
                                key=lambda kv: kv[1])
    fast = {f"log_C{b1[1]}": float(np.log(20.0 / t1))}  # the fast branch at 20 s: no pair within ×TWIN_TAU
    s = _search_on(dp)
    slowest = 10.0 ** s.bounds["extra_rc"]["log10_tau"][1]
    assert s.spare_branch(fast) is None  # 20 s and the paper's slow branch: nothing to spare
    ramp = {**fast, f"log_R{b2[1]}": float(np.log(4.0)), f"log_C{b2[1]}": float(np.log(4.0))}  # ×16 the slow branch
    dead = s.refitted_taus(ramp)[b2]
    assert dead > slowest and t2 < slowest  # the premise
    assert s.spare_branch(ramp) == ((b2, dead), None)
    # the same branch scaled back under the range's end is a branch again
    back = {**fast, f"log_C{b2[1]}": float(np.log(0.5 * slowest / t2))}
    assert s.spare_branch(back) is None


def test_an_extra_branch_beside_a_base_branch_left_as_a_ramp_is_kept_unnamed():
    """The null case of the test below with its HPPC file's Panasonic-style gaps (as the benchmark draws it): a DP fit
    on it leaves the slow branch as a ramp (τ ≈ 10¹¹ s as refitted), and the extra branch the search finds there is
    the DP's own slow branch put back. It stays in the model (base-fit error, like the base refit: the held-out error
    falls with it) and is not named; its evidence says why."""
    case = draw_case(111, 47)
    assert case.effects == () and case.base == "dp" and case.draws["hppc"]["gaps"]
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    assert d.effects_added == [], d.effects_added
    kept = [s for s in d.steps if s.effect == "extra_rc"]
    assert len(kept) == 1 and not kept[0].named and "a ramp" in kept[0].evidence and "is spare" in kept[0].evidence
    assert "extra_rc" in [e.name for e in d.final_model.effects]
    assert [s["kind"] for s in d.to_dict()["steps"] if s["effect"] == "extra_rc"] == ["base"]
    # the branch put back cuts what the base refit left by more than the search's gain, on held-out data
    refit = next(s for s in d.steps if s.effect == "base_refit")
    assert d.after["rmse_v"] <= 0.9 * refit.rmse_after < 0.9 * d.before["rmse_v"]


def test_an_extra_branch_where_the_base_has_one_to_spare_is_kept_unnamed():
    """A null case on a DP base (seed 47, a development seed of the randomised benchmark, case 111) whose lookup fit
    put both branches near each other (65 and 93 s) while the truth's lie at 58 and 438 s: the extra RC branch the
    search finds is the DP's own slow branch, misplaced. It stays in the model as base-fit error (the held-out error
    falls with it), is not named, and says why. (Case 51 of the same seed showed it until the slow OCV test's count
    was corrected (stop 39): its base fit is now sound.)"""
    case = draw_case(111, 47, gaps=False)
    assert case.effects == () and case.base == "dp"
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    assert d.effects_added == [], d.effects_added
    kept = [s for s in d.steps if s.effect == "extra_rc"]
    assert len(kept) == 1 and not kept[0].named and "within ×" in kept[0].evidence
    assert "is spare" in kept[0].evidence and "not named" in kept[0].evidence
    refit = next(s for s in d.steps if s.effect == "base_refit")
    assert d.after["rmse_v"] <= 0.9 * refit.rmse_after < 0.9 * d.before["rmse_v"]


def test_an_effect_hidden_by_the_base_misfit_is_found_jointly_with_the_refit():
    """Case 116 of the development seed 31: a Thevenin cell (τ1 ≈ 17 s) with a hidden RC branch (τ ≈ 185 s), a
    mission day. The HPPC fit gave part of the hidden branch to the base's own R0 and branch, so in the first round
    the branch alone and the base refit alone each cut the held-out error by less than the 10 % asked (the rule that
    follows is what decides); fitted jointly, the branch is named and the error falls by more than half. The HPPC
    shows the branch too (the diagnosis' default finds it there first, :mod:`socbench.identify.fit_test_effect`): the
    rule is tested with that step off."""
    from socbench.diagnose.search import BASE_REFIT

    case = draw_case(116, 31, gaps=False)
    assert case.effects == ("extra_rc",) and case.base == "thevenin"
    d = diagnose(case.base, case.fit, case.evals, soc=False, fit_test=False)
    first = {c.effect: c for c in d.rounds[0]["candidates"]}
    before = d.before["rmse_v"]
    for name in ("extra_rc", BASE_REFIT):
        assert first[name].rmse_after > 0.9 * before, (name, first[name].rmse_after, before)
    assert d.effects_added == ["extra_rc"], [(s.effect, s.evidence) for s in d.steps]
    joint = d.steps[0]
    assert [n for n, _ in joint.layout] == [BASE_REFIT, "extra_rc"]
    assert "fitted jointly with the base refit, where neither" in joint.evidence
    assert d.after["rmse_v"] < 0.5 * before


def test_a_drift_at_the_limit_of_its_physical_range_is_not_scored(monkeypatch):
    """A leak of 5 %/h, the top of the search's range (a soft short far beyond any cell in use): fitted, the leak
    rests on that bound, and a drift at the limit of its range stands in for something else on the records where it
    wins that way (a fade whose fold fit ran away, seed 2026 of the benchmark): it is not scored. Without the rule
    (``DRIFT_AT_BOUND = False``) the same fit is scored and named. The rule's cost, measured here: a truth at the
    bound itself is not named as such."""
    import socbench.diagnose.search as search
    from socbench.diagnose.synthetic import hidden_case

    fit, ev = hidden_case("self_discharge", "thevenin", "rests", "large", v_sd=1e-3, seed=7)
    d = diagnose("thevenin", [fit], [ev], soc=False, max_steps=1)
    leak = next(c for c in d.rounds[0]["candidates"] if c.effect == "self_discharge")
    assert not np.isfinite(leak.score) and "limit of its physical range" in leak.evidence, leak.evidence
    assert "self_discharge" not in d.effects_added
    monkeypatch.setattr(search, "DRIFT_AT_BOUND", False)
    off = diagnose("thevenin", [fit], [ev], soc=False, max_steps=1)
    leak_off = next(c for c in off.rounds[0]["candidates"] if c.effect == "self_discharge")
    assert np.isfinite(leak_off.score) and leak_off.params["rate"] == pytest.approx(leak.params["rate"])
    assert off.effects_added == ["self_discharge"], off.effects_added


@pytest.mark.slow
def test_a_state_at_the_slow_end_of_its_rate_is_not_scored(monkeypatch):
    """A null case of the development seed 31 (case 0: a DP cell, no effect hidden) whose base, once refitted on the
    evaluation records, still leaves a slow error along the SOC: a hysteresis fitted there rests on Plett's γ floor
    (γ = 1: its state settles over a whole capacity of charge moved, never within a record: a slow offset) and cut the
    held-out error by 10 % anyway. The search does not score a state at the slow end of its rate's range
    (``search.SLOW_END``, the rule the fit test's refit is held to), and nothing is named. Without the rule
    (``SLOW_END_RULE = False``) that hysteresis is named, its γ at the floor."""
    import socbench.diagnose.search as search

    case = draw_case(0, 31, gaps=False)
    assert case.hidden == {}
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    assert d.effects_added == [], d.effects_added
    slow = [c for r in d.rounds for c in r["candidates"] if c.effect == "hysteresis" and "lower end" in c.evidence]
    assert slow and all(not np.isfinite(c.score) for c in slow)
    assert all(c.params["gamma"] <= 1.5 for c in slow)
    monkeypatch.setattr(search, "SLOW_END_RULE", False)
    off = diagnose(case.base, case.fit, case.evals, soc=False)
    assert off.effects_added == ["hysteresis"], off.effects_added
    step = next(s for s in off.steps if s.effect == "hysteresis")
    assert step.params["gamma"] <= 1.5, step.params


def test_the_search_without_its_first_effect_is_kept_where_it_ends_lower(monkeypatch):
    """Case 42 of the development seed 31: a branch (τ ≈ 1100 s, slower than the HPPC's 8-minute rests, whose rest
    points then read part of it as OCV) and a charge-transfer term hidden together. The greedy search names a
    hysteresis first, and the branch then adds too little to be named. Run again without the hysteresis
    (``core.search_without_first``), the search names both hidden effects and ends more than 10 % lower, so that run
    is kept, and the report says so. With the recheck off, the greedy answer stands."""
    import socbench.diagnose.core as core

    case = draw_case(42, 31, gaps=False)
    assert set(case.effects) == {"butler_volmer", "extra_rc"}
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    rc = d.fit["recheck"]
    assert rc["without"] == "hysteresis" and rc["kept"], rc
    assert set(d.effects_added) == {"butler_volmer", "extra_rc"}, d.effects_added
    assert d.after["rmse_v"] == rc["rmse_v"] <= 0.9 * rc["rmse_v_with_it"]
    assert "the search without hysteresis, which it had named first" in d.steps[0].evidence
    monkeypatch.setattr(core, "RECHECK_FIRST", False)
    greedy = diagnose(case.base, case.fit, case.evals, soc=False)
    assert "recheck" not in greedy.fit
    assert greedy.effects_added[0] == "hysteresis" and "extra_rc" not in greedy.effects_added, greedy.effects_added
    assert greedy.after["rmse_v"] == pytest.approx(rc["rmse_v_with_it"], rel=1e-9)


def _candidate(effect, score, before, after):
    from socbench.diagnose.search import Candidate

    return Candidate(effect, score, before, after, {}, 0.0, "")


@pytest.mark.parametrize("draw", range(40))
def test_an_effect_is_preferred_to_a_winning_refit_only_where_it_would_be_added(draw):
    """PARSIMONY: an effect whose held-out RMSE lies within 10 % of a winning base refit's is chosen in its place, but
    only where it would be added itself (score above zero, the search's gain). An effect that falls short of that
    gain, chosen, ended the search: the refit, which passed, was never adopted, and the effect was never fitted again
    beside it (case 12 of seed 2026: an efficiency at 9 % beside a refit at 16 %; with the refit adopted, the
    efficiency then cut the error by half). Random rounds: which one is chosen follows the rule in each."""
    from types import SimpleNamespace

    from socbench.diagnose.search import BASE_REFIT, PARSIMONY, Search

    rng = np.random.default_rng(draw)
    search = SimpleNamespace(bias_measured=False, temperature_measured=False, min_gain=0.10)
    before = float(rng.uniform(1e-3, 5e-2))
    refit_after = before * float(rng.uniform(0.5, 0.88))  # the refit wins and passes the gain
    effect_after = refit_after * float(rng.uniform(1.0, 1.0 + PARSIMONY))  # within PARSIMONY of it
    refit = _candidate(BASE_REFIT, 1.0, before, refit_after)
    effect = _candidate("coulombic_efficiency", 0.5, before, effect_after)
    chosen = Search._choose(search, [refit, effect])
    passes = effect_after <= (1.0 - search.min_gain) * before
    assert chosen is (effect if passes else refit), (before, refit_after, effect_after)


def test_an_effect_the_fit_test_measures_is_named_within_the_noise_floor(monkeypatch):
    """Case 5 of the development seed 31: an LFP cell with a hysteresis (half-gap M = 10.6 mV) beside a C/20 slow OCV
    test, and a mission day whose voltage noise (5 mV) leaves the base model within 2.5 × the noise of its averaged
    records (the search's floor). The fit test measures the hysteresis (its slow test's branches; M within 15 % of
    the truth) and it predicts the day 10 % better held-out, no parameter of it fitted there but its state's start.
    It is named first: the floor guards against base-fit error that effects fitted on the evaluation records take
    up, and this one has none fitted there. Held to the floor (``FIT_TEST_FLOORED = True``, as before stop 62)
    nothing is named."""
    import socbench.diagnose.search as search

    case = draw_case(5, 31, gaps=False)
    assert set(case.hidden) == {"hysteresis"} and case.draws["slow_ocv_test"]
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    assert d.effects_added[:1] == ["hysteresis"], d.effects_added
    step = d.steps[0]
    assert step.fit_test and step.rmse_after <= 0.9 * step.rmse_before
    assert step.rmse_before <= search.NOISE_FLOOR * d.fit["voltage_noise_sd_binned"]  # the floor would stop it
    m_true = case.draws["hysteresis"]["M"]
    assert abs(step.params["M"] / m_true - 1.0) <= 0.15, (step.params, m_true)
    monkeypatch.setattr(search, "FIT_TEST_FLOORED", True)
    held = diagnose(case.base, case.fit, case.evals, soc=False)
    assert "hysteresis" not in held.effects_added, held.effects_added


def test_a_deferred_hysteresis_is_tried_beside_the_search_within_its_noise_floor():
    """Case 73 of the development seed 31: a current-sensor offset and an LFP hysteresis beside a C/20 slow OCV test.
    The fit test measures the hysteresis, but alone it does not predict the evaluation records 10 % better: the offset
    dominates their error. The search names the offset, which takes the records within its noise floor (where a
    deferred refit was not tried before stop 63); the hysteresis refit, whose only parameter fitted on the evaluation
    records is its state's start, is still tried beside it (``DEFERRED_UNFLOORED``) and both are named, the held-out
    RMSE 10 % below the offset's alone."""
    import socbench.diagnose.search as search

    case = draw_case(73, 31, gaps=False)
    assert set(case.effects) == {"current_bias", "hysteresis"} and case.draws["slow_ocv_test"]
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    assert set(d.effects_added) == {"current_bias", "hysteresis"}, d.effects_added
    assert d.fit["fit_test_effect"]["deferred"] == "hysteresis" and d.fit["fit_test_effect"]["added"]
    without = d.fit["fit_test_effect"]["without_it"]  # the search without the refit: the offset alone
    assert without["effects"] == ["current_bias"] and d.after["rmse_v"] <= 0.9 * without["rmse_v"]
    # … which ended within its noise floor (that of a search without the base refit: on this case it added the
    # offset alone, docs/undeclared_effects_seed31.json)
    assert without["rmse_v"] <= search.noise_floor(d.fit["voltage_noise_sd_binned_final"], False)


def test_the_drift_a_cold_record_holds_is_chosen_beside_the_base_refit():
    """Case 43 of the development seed 47: a leak (0.19 %/h) on a cell used at −3 °C (hidden temperature effect),
    over a 7-hour mission day. After the temperature, a fade wins the round alone (the leak alone fits worse than
    nothing: the base's resistances, off at the cold, are what the refit fixes) and passes the nested test against
    the base refit. Fitted jointly with the refit, the leak explains the day 10 % better than the fade does, alone or
    beside the refit, and it is the one named (``DRIFT_BESIDE_REFIT``; without the rule the fade is named, 10.4
    against 8.7 mV held-out, EKF SOC 1.69 against 0.67 %), with its rate within a factor of two of the truth's."""
    case = draw_case(43, 47, gaps=False)
    assert set(case.effects) == {"self_discharge", "temperature"}
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    assert d.effects_added == ["temperature", "self_discharge"], d.effects_added
    step = next(s for s in d.steps if s.effect == "self_discharge")
    assert "in place of capacity" in step.evidence, step.evidence
    assert 0.5 <= step.params["rate"] / case.draws["self_discharge"]["rate"] <= 2.0, step.params


def test_an_effect_the_fit_test_found_goes_only_where_the_records_do_no_worse_without_it():
    """Case 189 of the development seed 777: an NMC cell with a hysteresis (M = 4.1 mV), UAV flights with partial
    recharges. The fit test finds it (M within 25 % of the truth) and it predicts the flights 10 % better with nothing
    of it fitted on them; the base refit then takes most of what is left. Refitted without the hysteresis (the prune's
    own trial), the model is worse, but by less than the search's 10 %: the bar of an effect the search fitted on the
    records would drop it (as before stop 64); an effect the fit test found goes only where the records do no worse
    without it (``FIT_TEST_KEPT``), so it is named."""
    from socbench.diagnose.search import BASE_REFIT, effective_samples

    case = draw_case(189, 777, gaps=False)
    assert set(case.hidden) == {"hysteresis"}
    d = diagnose(case.base, case.fit, case.evals, soc=False)
    assert d.effects_added == ["hysteresis"] and d.steps[0].fit_test, d.effects_added
    m_true = case.draws["hysteresis"]["M"]
    assert abs(d.steps[0].params["M"] / m_true - 1.0) <= 0.25, (d.steps[0].params, m_true)
    s, final = d.search, d.steps[-1]
    rest, rows = s._without(final, "hysteresis")
    assert rest == [BASE_REFIT]
    without = s._try(rest[-1], rest[:-1], None, {g: {} for g in s.groups}, None, final.rmse_after,
                     effective_samples(final.held_residual), start=rows)
    assert final.rmse_after < without.rmse_after  # the records do worse without it …
    assert final.rmse_after >= (1.0 - s.min_gain) * without.rmse_after  # … by less than the search's gain
