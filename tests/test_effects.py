"""Augmented models (socbench.models.effects): the generic model checks, and each effect against an independent form."""

from __future__ import annotations

import numpy as np
import pytest

from socbench.errors import ConfigError
from socbench.loads import constant_current
from socbench.models import Constant, make_model, paper_params
from socbench.models.effects import (
    FARADAY,
    R_GAS,
    AugmentedModel,
    ButlerVolmer,
    Capacity,
    CoulombicEfficiency,
    CurrentBias,
    ExtraRC,
    Hysteresis,
    SelfDischarge,
    Temperature,
    augment,
    effect_names,
)
from socbench.profile import Profile

from . import test_models_generic as generic

#: every effect with non-default parameters (so every term is active)
EFFECTS = {
    "temperature": lambda: Temperature(Ea=35e3, dUdT=2e-3, t_ref=20.0),
    "hysteresis": lambda: Hysteresis(M=0.06, M0=-0.02, gamma=80.0, h0=0.3),
    "capacity": lambda: Capacity(cap0=1.2, r_growth=0.3),
    "current_bias": lambda: CurrentBias(b0=0.05),
    "extra_rc": lambda: ExtraRC(R=4e-3, log10_tau=2.7),
    "butler_volmer": lambda: ButlerVolmer(I0=6.0, dR=5e-4, Ea=40e3, t_ref=15.0),
    "coulombic_efficiency": lambda: CoulombicEfficiency(eta_c=0.95),
    "self_discharge": lambda: SelfDischarge(rate=0.02),
}

#: (case id, base model, effects): each effect alone on Thevenin, and stacks on other bases
CASES = {f"thevenin+{name}": ("thevenin", [name]) for name in EFFECTS}
CASES["dp+all"] = ("dp", list(EFFECTS))
CASES["rint+bias+capacity+ce+hysteresis"] = ("rint", ["current_bias", "capacity", "coulombic_efficiency", "hysteresis"])
CASES["pngv+temperature+extra_rc+butler_volmer+self_discharge"] = (
    "pngv", ["temperature", "extra_rc", "butler_volmer", "self_discharge"])


def _augmented(case):
    base, names = CASES[case]
    return augment(make_model(base, paper_params(base)), [EFFECTS[n]() for n in names])


def test_every_effect_is_covered():
    assert set(EFFECTS) == set(effect_names())


# ----------------------------------------------------------------------------------------------- generic checks
# The generic tests of test_models_generic.py, run unchanged on the augmented models (their model factory swapped).
@pytest.mark.parametrize("case", list(CASES))
def test_jacobians_match_finite_differences(case, monkeypatch):
    monkeypatch.setattr(generic, "_model", lambda name, **opts: _augmented(name))
    generic.test_jacobians_match_finite_differences(case)


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("dt", [0.1, 1.0, 10.0])
def test_discrete_step_is_exact_zoh(case, dt, monkeypatch):
    monkeypatch.setattr(generic, "_model", lambda name, **opts: _augmented(name))
    generic.test_discrete_step_is_exact_zoh(case, dt)


@pytest.mark.parametrize("case", ["dp+all", "rint+bias+capacity+ce+hysteresis"])
def test_batch_of_10000_matches_state_by_state(case, monkeypatch):
    monkeypatch.setattr(generic, "_model", lambda name, **opts: _augmented(name))
    generic.test_batch_of_10000_matches_state_by_state(case)


@pytest.mark.parametrize("case", list(CASES))
def test_whole_record_open_loop_matches_the_step_loop(case):
    """The augmented model's whole-record ``open_loop`` (effect states by prefix scans, the SOC path by a running
    sum or, with a leak, an SOC-only loop) against one step/output call per sample, on the record of the generic test
    (varying dt, charge and discharge, rests, an SOC jump, a temperature column, two initial states)."""
    m = _augmented(case)
    assert m.whole_record  # every effect and base model here has the whole-record path: the test compares two paths
    generic.assert_open_loop_matches_step_loop(m, exact_soc=False)


def test_whole_record_open_loop_takes_effect_parameter_batches():
    """The diagnosis fits simulate several effect-parameter variants in one call: each row must equal its own
    one-variant step loop."""
    base = make_model("dp", paper_params("dp"))
    gamma, tau, cap = np.array([3.0, 60.0, 400.0]), np.array([1.0, 2.5, 3.8]), np.array([0.8, 1.0, 1.3])
    growth = np.array([0.0, 0.4, 0.1])

    def make(g, lt, c, rg):
        return [Hysteresis(M=0.05, M0=0.01, gamma=g, h0=-0.5, h_ref=-1.0), ExtraRC(R=3e-3, log10_tau=lt),
                Capacity(cap0=c, r_growth=rg), SelfDischarge(rate=0.03), CurrentBias(b0=0.1)]

    batched = augment(base, make(gamma, tau, cap, growth))
    prof = _profile(_pulses(22.0), dt=2.0, temp=10.0)
    y_all = batched.simulate(prof, x0=batched.x0(0.8, (3,))).voltage_v
    assert y_all.shape == (3, prof.n)
    for r in range(3):
        one = augment(base, make(gamma[r], tau[r], cap[r], growth[r]))
        y_one = one.open_loop_stepwise(one.x0(0.8), prof.time_s, prof.current_a, prof.temperature_c)[1]
        np.testing.assert_allclose(y_all[r], y_one, rtol=1e-12, atol=1e-12)
    assert np.ptp(y_all[:, -1]) > 0.01  # the variants differ: the rows are not one simulation repeated


# ----------------------------------------------------------------------------------------------- each effect
def _profile(current, dt=1.0, temp=None):
    current = np.asarray(current, dtype=float)
    t = np.arange(current.size) * dt
    return Profile(t, current, temperature_c=None if temp is None else np.broadcast_to(temp, current.shape))


def _pulses(q, n=1200):
    """A discharge/charge pulse train with rests (A)."""
    k = np.arange(n)
    return np.where(k % 300 < 60, q, np.where(k % 300 < 120, 0.0, np.where(k % 300 < 160, -0.6 * q, 0.0)))


def _thevenin_scaled(k):
    """The paper Thevenin cell built directly with every R × k and every C / k (time constants unchanged), as
    201-point lookups of the paper's functions."""
    base_params = paper_params("thevenin")
    z = np.linspace(0, 1, 201)
    return make_model("thevenin", base_params.with_values(
        R0={"lookup": {"soc": z.tolist(), "value": (k * base_params["R0"](z)).tolist()}},
        R1={"lookup": {"soc": z.tolist(), "value": (k * base_params["R1"](z)).tolist()}},
        C1={"lookup": {"soc": z.tolist(), "value": (base_params["C1"](z) / k).tolist()}},
    ))


def test_temperature_equals_base_with_scaled_resistances_at_constant_temperature():
    base = make_model("thevenin", paper_params("thevenin"))
    eff = Temperature(Ea=40e3, dUdT=1.5e-3, t_ref=25.0)
    temp_c = -5.0
    k = np.exp(40e3 / 8.314462618 * (1 / (temp_c + 273.15) - 1 / 298.15))
    # the same cell built directly: every R × k, every C / k (τ unchanged), the OCV shifted by the entropic term
    direct = _thevenin_scaled(k)
    prof = _profile(_pulses(22.0), temp=temp_c)
    y_aug = augment(base, [eff]).simulate(prof, soc0=0.8).voltage_v
    y_dir = direct.simulate(prof, soc0=0.8).voltage_v + 1.5e-3 * (temp_c - 25.0)
    # lookup tables vs polynomials differ by the linear interpolation of R(z), C(z) only
    np.testing.assert_allclose(y_aug, y_dir, atol=2e-4)
    assert k > 5  # a real scaling, not a no-op
    # at the reference temperature (and without a temperature column) nothing changes
    at_ref = augment(base, [eff]).simulate(_profile(_pulses(22.0), temp=25.0), soc0=0.8).voltage_v
    np.testing.assert_allclose(at_ref, base.simulate(prof, soc0=0.8).voltage_v, atol=1e-12)


def test_capacity_resistance_growth_equals_the_aged_cell_and_composes_with_temperature():
    """An aged cell (every R × (1 + g), every C / (1 + g)) is the base model with the capacity effect's
    ``r_growth = g``; in the cold too, whichever order the two effects are listed in (the factors multiply: the
    entropic term is not scaled by the growth)."""
    base = make_model("thevenin", paper_params("thevenin"))
    g, temp_c = 0.35, 0.0
    prof = _profile(_pulses(22.0), temp=temp_c)
    y_aged = augment(base, [Capacity(r_growth=g)]).simulate(prof, soc0=0.8).voltage_v
    np.testing.assert_allclose(y_aged, _thevenin_scaled(1.0 + g).simulate(prof, soc0=0.8).voltage_v, atol=2e-4)
    assert np.max(np.abs(y_aged - base.simulate(prof, soc0=0.8).voltage_v)) > 0.02  # the growth shows
    temp = Temperature(Ea=30e3, dUdT=-1e-3, t_ref=25.0)
    k = np.exp(30e3 / R_GAS * (1 / (temp_c + 273.15) - 1 / 298.15))
    y_dir = _thevenin_scaled(k * (1.0 + g)).simulate(prof, soc0=0.8).voltage_v - 1e-3 * (temp_c - 25.0)
    for effects in ([temp, Capacity(r_growth=g)], [Capacity(r_growth=g), temp]):
        np.testing.assert_allclose(augment(base, effects).simulate(prof, soc0=0.8).voltage_v, y_dir, atol=2e-4)


def test_hysteresis_saturates_and_separates_rests_by_2M():
    base = make_model("rint", paper_params("rint"))
    M, q = 0.05, 22.0
    m = augment(base, [Hysteresis(M=M, M0=0.0, gamma=200.0, h0=0.0)])
    # 0.2 Q discharge then rest, vs 0.2 Q charge then rest ending at the same SOC
    dis = np.r_[np.full(720, q), np.zeros(600)]
    chg = np.r_[np.full(720, -q), np.zeros(600)]
    sd = m.simulate(_profile(dis), soc0=0.6)
    sc = m.simulate(_profile(chg), soc0=0.2)
    h = sd.states[..., m.state_names.index("h")]
    assert h[-1] == pytest.approx(-1.0, abs=1e-5) and h.min() >= -1.0
    hc = sc.states[..., m.state_names.index("h")]
    assert hc[-1] == pytest.approx(1.0, abs=1e-5)
    assert sd.soc[-1] == pytest.approx(sc.soc[-1], abs=1e-9)
    assert sc.voltage_v[-1] - sd.voltage_v[-1] == pytest.approx(2 * M, abs=1e-6)
    # relative to an OCV curve measured on the discharge branch (h_ref = −1): nothing to add after a discharge
    on_dis = augment(base, [Hysteresis(M=M, M0=0.01, gamma=200.0, h0=0.0, h_ref=-1.0)])
    y = on_dis.simulate(_profile(dis), soc0=0.6).voltage_v
    assert y[-1] == pytest.approx(base.simulate(_profile(dis), soc0=0.6).voltage_v[-1], abs=1e-6)


def test_capacity_and_coulombic_efficiency_scale_the_soc_change():
    base = make_model("thevenin", paper_params("thevenin"))
    q = base.capacity_ah
    prof = constant_current(q, 1.0, soc_span=0.3)
    for cap in (0.8, 1.25):
        sim = augment(base, [Capacity(cap0=cap)]).simulate(prof, soc0=0.9)
        assert 0.9 - sim.soc[-1] == pytest.approx(cap * prof.amp_hours()[-1] / q, rel=1e-9)
    ce = augment(base, [CoulombicEfficiency(eta_c=0.93)])
    chg = prof.with_(current_a=-prof.current_a)
    assert ce.simulate(chg, soc0=0.2).soc[-1] - 0.2 == pytest.approx(-0.93 * chg.amp_hours()[-1] / q, rel=1e-9)
    assert ce.simulate(prof, soc0=0.9).soc[-1] == pytest.approx(base.simulate(prof, soc0=0.9).soc[-1], abs=1e-12)


def test_current_bias_recovers_the_true_current():
    base = make_model("dp", paper_params("dp"))
    b = 0.4
    i_true = _pulses(22.0)
    truth = base.simulate(_profile(i_true), soc0=0.7)
    est = augment(base, [CurrentBias(b0=b)]).simulate(_profile(i_true + b), soc0=0.7)
    np.testing.assert_allclose(est.voltage_v, truth.voltage_v, atol=1e-12)
    np.testing.assert_allclose(est.soc, truth.soc, atol=1e-12)
    # without the bias state the model drifts: the SOC error grows with elapsed time (rests included)
    naive = base.simulate(_profile(i_true + b), soc0=0.7)
    err = truth.soc - naive.soc
    assert err[-1] == pytest.approx(b * (i_true.size - 1) / 3600 / 22.0, rel=1e-9)


def test_extra_rc_equals_a_second_branch():
    th = paper_params("thevenin")
    R2, tau = 3e-3, 400.0
    dp = make_model("dp", th.with_values(R2=Constant(R2), C2=Constant(tau / R2)))
    aug = augment(make_model("thevenin", th), [ExtraRC(R=R2, log10_tau=np.log10(tau))])
    prof = _profile(_pulses(22.0), dt=2.0)
    np.testing.assert_allclose(aug.simulate(prof, soc0=0.8).voltage_v, dp.simulate(prof, soc0=0.8).voltage_v,
                               atol=1e-12)


def test_butler_volmer_is_odd_and_its_slope_at_zero_is_the_linear_charge_transfer_resistance():
    base = make_model("rint", paper_params("rint"))
    i0, t = 5.0, 10.0
    m = augment(base, [ButlerVolmer(I0=i0, dR=0.0)])
    x = m.x0(0.5)
    n_s = 6  # the paper pack is 6S
    r_ct = n_s * R_GAS * (t + 273.15) / (FARADAY * i0)  # small-signal limit of N_s (2RT/F) asinh(I/2I0)
    assert m.D(x, 0.0, t) - base.D(x, 0.0) == pytest.approx(-r_ct, rel=1e-12)
    for cur in (3.0, 30.0, 80.0):
        extra_p = m.h(x, cur, t) - base.h(x, cur)
        extra_n = m.h(x, -cur, t) - base.h(x, -cur)
        assert extra_p == pytest.approx(-extra_n, rel=1e-12)
        assert -extra_p < r_ct * cur  # sub-linear: the apparent resistance falls with |I|
    assert -(m.h(x, 80.0, t) - base.h(x, 80.0)) / 80.0 < 0.5 * r_ct


def test_self_discharge_sags_during_rest():
    base = make_model("thevenin", paper_params("thevenin"))
    m = augment(base, [SelfDischarge(rate=0.01)])
    sim = m.simulate(_profile(np.zeros(3601)), soc0=1.0)
    # 1 %/h at full charge, the rate falling with the OCV: a little under 1 % in an hour
    assert 0.0098 < 1.0 - sim.soc[-1] < 0.01
    assert np.all(np.diff(sim.voltage_v) < 0)


def test_x0_carries_the_initial_states_and_augment_flattens():
    base = make_model("thevenin", paper_params("thevenin"))
    m = augment(augment(base, [Hysteresis(h0=0.7)]), [Capacity(cap0=1.1), CurrentBias(b0=0.2)])
    assert isinstance(m, AugmentedModel) and m.base is base
    assert m.state_names == ("z", "U1", "h", "s", "cap", "b")
    x = m.x0(0.5, (3,))
    np.testing.assert_array_equal(x[0], [0.5, 0.0, 0.7, 0.0, 1.1, 0.2])
    assert x.shape == (3, 6)
    with pytest.raises(ConfigError):
        augment(m, [Hysteresis()])
    with pytest.raises(ConfigError):
        Hysteresis(R=1.0)


def test_bounds_contain_defaults():
    base = make_model("thevenin", paper_params("thevenin"))
    for make in EFFECTS.values():
        e = make()
        for p, (lo, hi) in e.bounds(base).items():
            assert lo < hi and lo <= type(e).defaults[p] <= hi, (e.name, p)
