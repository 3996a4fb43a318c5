"""The randomised benchmark's generator and scoring (socbench.diagnose.randomized), and the current-sensor evidence of
the effect search on field records shaped like its loads.

* the evaluation loads never run the cell past empty (a drive used to be cut only once below 25 %, so one more drive
  could take the cell to 0 % and its voltage to a fraction of a volt, a record no instrument delivers);
* a vehicle's stop (a small steady auxiliary current, below C/20, for a minute or two) is not a rest that measures
  the current sensor: the search reads no offset from such records, and reads the offset when there is one;
* the footprint of each hidden effect alone, and the rates by detectability;
* the footprint beyond the base: what a rescaled base cannot take (a nearly linear charge-transfer over-potential is
  taken, a capacity fade is not);
* a hidden extra RC branch is one the truth base lacks: its time constant lies outside the ×TWIN_TAU window of every
  branch of the truth's base structure (the window in which the search calls a branch a misfit of the base's own);
* a quarter of the fit tests are files with the Panasonic-style gaps, drawn from a stream of their own: the other
  cases are what they were, and the HPPC analysis counts a gapped file's charge from its reference.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from socbench.diagnose import search
from socbench.diagnose.randomized import (
    EFFECT_NAMES,
    EFFECT_RANGES,
    EXTRA_RC_TAU_MAX_S,
    FOOTPRINT_BINS,
    GAPPED_SHARE,
    by_footprint,
    case_kind,
    draw_case,
    eval_current,
    footprint,
    footprint_beyond_base,
    missing_time_constant,
    rates,
)
from socbench.diagnose.search import FIELD_REST_MIN_S, REST_OFFSET_C, TWIN_TAU, rest_current
from socbench.identify import analyze_hppc
from socbench.identify.fit import branch_time_constants
from socbench.models.effects import augment, make_effect
from socbench.profile import Profile


@pytest.mark.parametrize("kind", ["drive", "uav", "day"])
def test_evaluation_loads_keep_the_cell_above_empty(kind):
    lows = []
    for seed in range(12):
        rng = np.random.default_rng([99, seed])
        q = float(np.exp(rng.uniform(0.0, np.log(50.0))))
        dt = float(np.exp(rng.uniform(np.log(0.5), np.log(10.0))))
        _, i, _ = eval_current(rng, kind, q, dt)
        z = 0.98 - np.cumsum(i) * dt / (3600.0 * q)
        lows.append(float(z.min()))
    assert min(lows) >= 0.1 - 1e-9, lows  # the charge planned on the true capacity stops at 10 %


def _drive_record(seed: int, offset_c: float):
    """A drive record (stops with an auxiliary load, rests between drives) read by a sensor with ``offset_c``·C."""
    rng = np.random.default_rng([5, seed])
    q = float(rng.uniform(2.0, 30.0))
    dt = float(rng.uniform(0.5, 2.0))
    t, i, _ = eval_current(rng, "drive", q, dt)
    i_meas = i + offset_c * q + rng.normal(0.0, 0.003 * q, t.size)
    return Profile(t, i_meas, voltage_v=np.full(t.size, 3.7)), q


def test_field_rests_do_not_read_a_vehicles_stops_as_a_sensor_offset(monkeypatch):
    wrong, seen = 0, 0
    for seed in range(10):
        p, q = _drive_record(seed, 0.0)
        r = rest_current(p, q, min_s=FIELD_REST_MIN_S)
        if r is None:
            continue
        seen += 1
        mean, se, _ = r
        wrong += abs(mean) > max(4.0 * se, q * REST_OFFSET_C)  # the search's rule for "the rests read an offset"
    assert seen >= 8 and wrong == 0
    # while every quiet spell of 30 s or more (the stops included) does read one, in most records, by the pooled
    # level's error alone (the scatter of the spells' levels, search.REST_SPREAD, keeps the stops out here too)
    monkeypatch.setattr(search, "REST_SPREAD", False)
    short = [rest_current(*_drive_record(seed, 0.0)) for seed in range(10)]
    assert sum(abs(m) > max(4 * se, 5e-4 * q) for (m, se, _), (_, q) in
               zip(short, [_drive_record(s, 0.0) for s in range(10)])) >= 5


def test_field_rests_read_a_real_sensor_offset():
    for seed in range(6):
        p, q = _drive_record(seed, 0.01)
        mean, se, _ = rest_current(p, q, min_s=FIELD_REST_MIN_S)
        assert mean == pytest.approx(0.01 * q, abs=5 * se + 0.001 * q)


def test_each_hidden_effect_has_its_own_footprint():
    k = next(k for k in range(10) if case_kind(k)[0] == "pair")
    case = draw_case(k, 11)
    own = {n: footprint(case, only=n) for n in case.effects}
    both = footprint(case)
    assert all(v >= 0 for v in own.values()) and both > 0
    assert max(own.values()) > 0.2 * both  # one of the two carries a real share of what both add
    single = draw_case(next(k for k in range(10) if case_kind(k)[0] == "single"), 11)
    assert footprint(single, only=single.effects[0]) == pytest.approx(footprint(single), rel=1e-9)


def _with_hidden(case, name, **values):
    """``case`` with ``name`` at ``values`` as its one hidden effect (the records' currents are kept: the footprints
    simulate the truth on them)."""
    effect = make_effect(name, **values)
    return dataclasses.replace(case, effects=(name,), hidden={name: effect},
                               truth=augment(case.truth_without, [effect]), draws={**case.draws, name: values})


def test_the_footprint_beyond_the_base_is_what_a_rescaled_base_cannot_take():
    """A charge-transfer over-potential with I0 = 5 C is within 2 % of linear over a 3 C load: a rescaled R0 takes it,
    so little of its footprint is left beyond the base. A 20 % capacity fade drifts the SOC, which no scaling of
    resistances and capacitances reproduces: most of its footprint is left. Four drawn cells; the fit starts from
    the truth's own parameters, so it never ends above the plain footprint."""
    cases = [draw_case(k, 11) for k in range(10) if case_kind(k)[0] == "single"][:4]
    for case in cases:
        q = case.capacity_ah
        linear_bv = _with_hidden(case, "butler_volmer", I0=5.0 * q, dR=0.0)
        fade = _with_hidden(case, "capacity", cap0=1.0 / 0.8)
        fp_bv, fp_fade = footprint(linear_bv), footprint(fade)
        assert fp_bv > 0.5 and fp_fade > 0.5, (fp_bv, fp_fade)  # both show on the records
        beyond_bv, beyond_fade = footprint_beyond_base(linear_bv), footprint_beyond_base(fade)
        assert beyond_bv < 0.2 * fp_bv, (case.index, fp_bv, beyond_bv)
        assert beyond_fade > 0.6 * fp_fade, (case.index, fp_fade, beyond_fade)
        assert beyond_bv <= fp_bv * (1 + 1e-9) and beyond_fade <= fp_fade * (1 + 1e-9)


def test_rates_by_detectability_put_each_case_in_its_footprint_class():
    res = [{"kind": "single", "effects": ["hysteresis"], "added": [], "first": None, "footprint": 0.4,
            "footprints": {"hysteresis": 0.4}, "rmse_before": 1.0, "rmse_after": 1.0},
           {"kind": "single", "effects": ["capacity"], "added": ["capacity"], "first": "capacity", "footprint": 9.0,
            "footprints": {"capacity": 9.0}, "rmse_before": 1.0, "rmse_after": 0.2},
           {"kind": "pair", "effects": ["capacity", "coulombic_efficiency"], "added": ["capacity"],
            "first": "capacity", "footprint": 9.0, "footprints": {"capacity": 8.0, "coulombic_efficiency": 2.0},
            "rmse_before": 1.0, "rmse_after": 0.3}]
    bins = by_footprint(res)
    assert [b["footprint"] for b in bins] == [label for _, _, label in FOOTPRINT_BINS]
    low, mid, high = bins
    assert low["named_first_single"] == {"n": 1, "hits": 0, "rate": 0.0}
    assert high["named_first_single"] == {"n": 1, "hits": 1, "rate": 1.0} and high["cut_30_single"]["hits"] == 1
    assert mid["named_in_pair"] == {"n": 1, "hits": 0, "rate": 0.0}
    assert high["named_in_pair"] == {"n": 1, "hits": 1, "rate": 1.0}


def test_the_rates_count_the_effects_named_that_are_not_there():
    """Cases with a hidden effect where something not hidden is named too (beside or instead of what is): counted
    over single and two-effect cases, never over null cases (those have their own rate)."""
    def case(kind, effects, added):
        return {"kind": kind, "effects": effects, "added": added, "first": added[0] if added else None,
                "footprint": 1.0, "rmse_before": 1.0, "rmse_after": 1.0}

    res = [case("single", ["capacity"], ["capacity"]),
           case("single", ["capacity"], ["capacity", "hysteresis"]),  # a false second effect
           case("single", ["extra_rc"], ["coulombic_efficiency"]),  # a false first one
           case("pair", ["capacity", "hysteresis"], ["hysteresis"]),  # one missed, nothing false
           case("null", [], ["extra_rc"])]  # the null rate's business
    r = rates(res)
    assert r["false_effect_hidden"] == {"n": 4, "hits": 2, "rate": 0.5}
    assert r["nothing_added_null"]["hits"] == 0


def _outside_every_window(tau, branch_taus) -> bool:
    # the search's rule for a twin branch is |ln(τ/τ_j)| ≤ ln TWIN_TAU; the window's edge itself is measure zero
    return all(abs(np.log(tau / tj)) >= np.log(TWIN_TAU) * (1.0 - 1e-9) for tj in branch_taus)


def test_missing_time_constant_skips_the_base_branches_windows():
    rng = np.random.default_rng(3)
    lo, hi = EFFECT_RANGES["extra_rc"]["tau_s"]
    for _ in range(300):
        taus = (float(rng.uniform(5.0, 60.0)),) + ((float(rng.uniform(150.0, 1500.0)),) if rng.random() < 0.7 else ())
        tau = missing_time_constant(float(rng.random()), lo, hi, taus)
        assert lo <= tau <= EXTRA_RC_TAU_MAX_S and _outside_every_window(tau, taus), (tau, taus)
    # no window above lo: the plain log-uniform draw over [lo, hi], the same value for the same uniform number
    for u in (0.0, 0.3, 0.9):
        assert missing_time_constant(u, lo, hi, (20.0,)) == pytest.approx(lo * (hi / lo) ** u, rel=1e-12)
    # DP branches at 30 s and 1000 s: from lo to 1000/TWIN_TAU s, then from 1000·TWIN_TAU s on, and no further than
    # the cap (the log-length of [lo, hi] would reach beyond it), each part by its share of the log-length
    taus, gap = (30.0, 1000.0), (1000.0 / TWIN_TAU, 1000.0 * TWIN_TAU)
    share = np.log(gap[0] / lo) / (np.log(gap[0] / lo) + np.log(EXTRA_RC_TAU_MAX_S / gap[1]))
    assert missing_time_constant(share - 1e-9, lo, hi, taus) == pytest.approx(gap[0], rel=1e-6)
    assert missing_time_constant(share + 1e-9, lo, hi, taus) == pytest.approx(gap[1], rel=1e-6)
    assert missing_time_constant(1.0 - 1e-12, lo, hi, taus) == pytest.approx(EXTRA_RC_TAU_MAX_S, rel=1e-9)


def test_hidden_extra_rc_lies_outside_the_truth_branches_windows():
    extra = EFFECT_NAMES.index("extra_rc")
    bases = []
    for k in [k for k in range(120) if case_kind(k) == ("single", extra)]:
        case = draw_case(k, 13)
        taus = list(branch_time_constants(case.truth_without.params).values())
        tau = 10.0 ** case.draws["extra_rc"]["log10_tau"]
        assert _outside_every_window(tau, taus), (k, case.base, tau, taus)
        bases.append(case.base)
    assert "dp" in bases  # a DP base (τ2 150–1500 s) is the case the rule is for


def test_a_quarter_of_the_fit_tests_have_the_panasonic_gaps():
    """Over 40 cases (seed 61, unseen), about a quarter of the fit HPPCs leave out every step discharge but the last
    (one gap per step), with the reference SOC carrying their charge: the analysis counts the cell's capacity from it
    to 2 % (the truth's, faded or not: the fit test is the fresh cell) and reads an OCV point at every set."""
    gapped = 0
    for k in range(40):
        case = draw_case(k, 61)
        if not case.draws["hppc"]["gaps"]:
            continue
        gapped += 1
        hppc = next(p for p in case.fit if p.name == "fit-hppc")
        big_steps = np.flatnonzero(np.diff(hppc.time_s) > 60.0)
        a = analyze_hppc(hppc)
        assert big_steps.size >= 8 and a.ocv_soc.size >= big_steps.size, (k, big_steps.size, a.ocv_soc.size)
        assert abs(a.capacity_ah / case.capacity_ah - 1.0) <= 0.02, (k, a.capacity_ah, case.capacity_ah)
    assert abs(gapped / 40 - GAPPED_SHARE) <= 0.15, gapped
