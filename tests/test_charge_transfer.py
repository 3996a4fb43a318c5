"""The charge-transfer term over temperature: ButlerVolmer's Arrhenius exchange current, the set that carries it in
PARAMS.json, and the temperature-aware fit that identifies it (socbench.identify.temperature, ``charge_transfer``).

The compiled kernel against numpy is checked with every other effect in tests/test_kernels.py (the ButlerVolmer case
of tests/test_effects.py has a non-zero activation energy and a reference temperature other than 25 °C).
"""

from __future__ import annotations

import numpy as np
import pytest

from socbench.errors import ConfigError
from socbench.identify.fit import fit_model
from socbench.identify.temperature import I0_LABEL, arrhenius_law, fit_temperatures
from socbench.models import Constant, ModelParams, load_params, make_model, paper_params, save_params
from socbench.models.effects import FARADAY, KELVIN, R_GAS, AugmentedModel, ButlerVolmer, augment
from socbench.models.params import params_to_dict

from .hppc_records import Cell, Instrument, Layout, hppc_record


def test_exchange_current_is_the_reference_value_at_t_ref_and_rises_with_temperature():
    bv = ButlerVolmer(I0=3.0, Ea=50e3, t_ref=10.0)
    assert bv.exchange_current(np.float64(10.0 + KELVIN)) == pytest.approx(3.0, rel=1e-15)
    temps = np.linspace(-40.0, 60.0, 101)
    i0 = bv.exchange_current(temps + KELVIN)
    assert np.all(np.diff(i0) > 0)
    # Arrhenius: ln I0 is linear in 1/T with slope −Ea/R
    slope = np.polyfit(1.0 / (temps + KELVIN), np.log(i0), 1)[0]
    assert slope == pytest.approx(-50e3 / R_GAS, rel=1e-9)
    # no activation energy: one I0 at every temperature
    np.testing.assert_array_equal(ButlerVolmer(I0=3.0, t_ref=10.0).exchange_current(temps + KELVIN), 3.0)


def test_default_reproduces_the_temperature_free_term_exactly():
    base = make_model("rint", paper_params("rint"))
    bv = ButlerVolmer(I0=5.0, dR=2e-3)
    m = augment(base, [bv])
    cur = np.linspace(-80.0, 80.0, 41)
    x = m.x0(0.6, (cur.size,))
    for t in (-20.0, 10.0, 45.0):
        g = 6 * 2.0 * R_GAS * (t + KELVIN) / FARADAY  # the paper pack is 6S
        want = -g * np.arcsinh(cur / (2.0 * 5.0)) + 2e-3 * cur  # the term before I0 depended on temperature
        got = m.h(x, cur, t) - base.h(x, cur)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_the_law_enters_only_through_the_exchange_current():
    """At any temperature the Arrhenius term equals a temperature-free term with I0 = I0(T)."""
    base = make_model("thevenin", paper_params("thevenin"))
    bv = ButlerVolmer(I0=4.0, dR=1e-3, Ea=60e3, t_ref=25.0)
    m = augment(base, [bv])
    cur = np.linspace(-60.0, 60.0, 13)
    x = m.x0(0.5, (cur.size,))
    for t in (-25.0, 0.0, 25.0, 40.0):
        fixed = augment(base, [ButlerVolmer(I0=float(bv.exchange_current(t + KELVIN)), dR=1e-3)])
        np.testing.assert_allclose(m.h(x, cur, t), fixed.h(x, cur, t), rtol=1e-13)
        np.testing.assert_allclose(m.D(x, cur, t), fixed.D(x, cur, t), rtol=1e-13)
    # the cold exchange current is smaller: the term's apparent resistance at a small current is larger
    assert np.all(m.D(x, 1.0, -20.0) < m.D(x, 1.0, 25.0))


def test_a_set_with_effects_round_trips_through_params_json(tmp_path):
    p = paper_params("dp").replace(effects=({"name": "butler_volmer",
                                             "values": {"I0": 7.5, "dR": -1e-3, "Ea": 42e3, "t_ref": 20.0}},))
    path = tmp_path / "p.json"
    save_params(path, "dp", p)
    name, q = load_params(path)
    assert name == "dp" and [dict(e["values"]) for e in q.effects] == [{"I0": 7.5, "dR": -1e-3, "Ea": 42e3,
                                                                         "t_ref": 20.0}]
    m = make_model(name, q)
    assert isinstance(m, AugmentedModel) and m.effect("butler_volmer")["Ea"] == 42e3
    x = m.x0(0.7)
    assert m.h(x, 30.0, -5.0) == make_model("dp", p).h(x, 30.0, -5.0)
    assert m.h(x, 30.0, -5.0) != make_model("dp", paper_params("dp")).h(x, 30.0, -5.0)
    # a set without effects is written as before
    assert "effects" not in params_to_dict("dp", paper_params("dp"))
    assert not isinstance(make_model("dp", paper_params("dp")), AugmentedModel)


@pytest.mark.parametrize("bad, message", [
    ({"name": "no_such_effect", "values": {}}, "unknown effect"),
    ({"name": "butler_volmer", "values": {"I1": 1.0}}, "no parameter 'I1'"),
    ({"name": "butler_volmer", "values": {"I0": float("nan")}}, "finite number"),
    ({"name": "butler_volmer"}, "must be"),
])
def test_a_bad_effect_in_a_set_is_refused(bad, message):
    with pytest.raises(ConfigError, match=message):
        paper_params("dp").replace(effects=(bad,))


def test_arrhenius_law_through_exact_points_and_its_refusals():
    temps = np.array([-20.0, 0.0, 25.0])
    i0 = ButlerVolmer(I0=2.0, Ea=35e3).exchange_current(temps + KELVIN)
    law = arrhenius_law(temps, i0, np.full(3, 0.01))
    assert law.i0_ref == pytest.approx(2.0, rel=1e-10) and law.ea == pytest.approx(35e3, rel=1e-10)
    # a point at a bound of the fit is left out, whatever its value
    law = arrhenius_law(temps, np.r_[i0[:2], 100.0], np.full(3, 0.01), usable=[True, True, False])
    assert law.ea == pytest.approx(35e3, rel=1e-10) and law.used == (True, True, False)
    # an exchange current that grows in the cold is no Arrhenius process: Ea = 0, the weighted geometric mean
    law = arrhenius_law(temps, i0[::-1], np.full(3, 0.01))
    assert law.ea == 0.0 and law.i0_ref == pytest.approx(np.exp(np.mean(np.log(i0))), rel=1e-12)


# ------------------------------------------------------------------------------------------------ recovery
def _cold_hppc(temp_c: float, truth_params: ModelParams, bv: ButlerVolmer, cell: Cell, seed: int):
    """An HPPC-like record (pulses of 0.5–4C at every 10 % of SOC, 1 h rests) of the dp + Butler–Volmer truth at a
    constant cell temperature, 1 mV voltage noise."""
    lay = Layout(pulses_c=(0.5, -0.5, 1.0, 2.0, 4.0), pulse_s=10.0, inner_rest_s=60.0, rest_s=3600.0, step=0.1)
    rec = hppc_record(cell, lay, Instrument(dt=1.0), seed=seed, name=f"synthetic-{temp_c:g}C")
    prof = rec.profile.with_(temperature_c=np.full(rec.profile.n, temp_c))
    truth = augment(make_model("dp", truth_params), [bv])
    v = truth.simulate(prof, soc0=1.0).voltage_v
    noise = np.random.default_rng(seed + 100).normal(0.0, 1e-3, v.size)
    return prof.with_(voltage_v=v + noise)


def _random_bv_cell(rng):
    """``(cell, dp parameters, Butler–Volmer term)`` of a random 2–3.5 Ah dp truth whose exchange current follows an
    Arrhenius law: I0 at 25 °C 0.5–1.5 × the 1C current, Ea 30–60 kJ/mol (nearly linear warm, strong cold)."""
    q = float(rng.uniform(2.0, 3.5))
    r0, r1, r2 = (float(rng.uniform(a, b)) / q for a, b in ((0.03, 0.06), (0.01, 0.03), (0.01, 0.03)))
    tau1, tau2 = float(rng.uniform(8.0, 30.0)), float(rng.uniform(200.0, 600.0))
    cell = Cell(q, "nmc", r0, ((r1, tau1), (r2, tau2)))
    params = ModelParams(capacity_ah=q, ocv=cell.ocv, values={
        "R0": Constant(r0), "R1": Constant(r1), "R2": Constant(r2), "C1": Constant(tau1 / r1),
        "C2": Constant(tau2 / r2)})
    bv = ButlerVolmer(I0=float(rng.uniform(0.5, 1.5)) * q, Ea=float(rng.uniform(30e3, 60e3)))
    return cell, params, bv


@pytest.mark.parametrize("draw", range(3))
def test_the_fit_recovers_a_planted_exchange_current_law(draw):
    cell, truth_params, planted = _random_bv_cell(np.random.default_rng(2026 + draw))
    temps = (-20.0, 0.0, 25.0)
    records = [_cold_hppc(t, truth_params, planted, cell, 10 * draw + k) for k, t in enumerate(temps)]
    res = fit_temperatures("dp", records, mode="constant", charge_transfer=True)
    ct = res.extra["charge_transfer"]
    want = planted.exchange_current(np.array(temps) + KELVIN)
    # every temperature's own exchange current (pass a) within 10 % or two of its standard errors (the warm one,
    # where the term is nearly linear and trades with R0, is the least determined), the law within 15 % everywhere
    miss = np.abs(np.log(np.asarray(ct["i0_fitted_a"]) / want))
    assert np.all(miss <= np.maximum(0.1, 2.0 * np.asarray(ct["i0_rel_se"]))), (ct, want)
    assert all(ct["used"])
    np.testing.assert_allclose(ct["i0_law_a"], want, rtol=0.15)
    assert ct["ea_j_per_mol"] == pytest.approx(planted["Ea"], rel=0.1)
    # the set carries the law, and it round-trips into the model make_model builds
    (eff,) = res.params.effects
    assert eff["name"] == "butler_volmer" and eff["values"]["Ea"] == ct["ea_j_per_mol"]
    assert isinstance(make_model("dp", res.params), AugmentedModel)
    # the term is what the linear model lacks: without it the cold fit is far worse
    plain = fit_temperatures("dp", records[:1], mode="constant")
    assert res.fits[0].rmse_v < 0.5 * plain.rmse_v
    assert I0_LABEL not in res.fits[0].values  # the second pass holds the law's I0


# ------------------------------------------------------------------------------------------------ pass (c)'s start
def _lookup_fit_pair(seed: int):
    """``(record, ButlerVolmer at the fitted I0, pass-(a)-like fit)``: a lookup-mode dp fitted with its exchange current
    on one cold synthetic HPPC of a random truth."""
    rng = np.random.default_rng(seed)
    cell, truth_params, planted = _random_bv_cell(rng)
    rec = _cold_hppc(float(rng.uniform(-20.0, 10.0)), truth_params, planted, cell, seed)
    first = fit_model("dp", rec, mode="lookup", effects=(ButlerVolmer(I0=cell.capacity_ah),))
    return rec, ButlerVolmer(I0=first.values[I0_LABEL]), first


@pytest.mark.parametrize("seed", (7, 8))
def test_a_refit_from_start_fit_starts_where_that_fit_ended(seed):
    """``fit_model(..., start_fit=f)`` starts from ``f``'s base θ, every SOC node as it ended (pass (c) of
    ``fit_temperatures`` with the charge-transfer term: only I0 moved since pass (a)). With the exchange current held
    where the first fit put it and a single evaluation, the refit is that fit; from the record's own guesses it is
    not."""
    rec, held, first = _lookup_fit_pair(seed)
    nb = sum(1 for name in first.corr_names if name != I0_LABEL)
    again = fit_model("dp", rec, mode="lookup", effects=(held,), fit_effects=False, start_fit=first, max_nfev=1)
    np.testing.assert_allclose(again.lsq.theta, first.lsq.theta[:nb], rtol=0, atol=1e-9)
    assert again.rmse_v == pytest.approx(first.rmse_v, rel=1e-6)
    cold = fit_model("dp", rec, mode="lookup", effects=(held,), fit_effects=False, warm_start=False, max_nfev=1)
    assert cold.rmse_v > 2.0 * first.rmse_v


def test_a_start_fit_of_another_layout_is_refused():
    rec, held, first = _lookup_fit_pair(9)
    with pytest.raises(ValueError, match="other base parameters"):
        fit_model("dp", rec, mode="constant", effects=(held,), fit_effects=False, start_fit=first)


def test_the_law_refit_starts_at_each_temperature_from_its_own_first_pass(monkeypatch):
    """Pass (c) refits every temperature from where pass (a) ended there, not from the record's guesses: from those,
    liu on the five Panasonic HPPCs (`socbench fit --data $HPPCS --model liu --mode auto --validation $CYCLES`, the
    per-temperature setting with the term) predicted its 25 °C Cycle_1 run at 171 mV; from pass (a), at 25 mV, as
    without the term."""
    import socbench.identify.temperature as temperature

    cell, truth_params, planted = _random_bv_cell(np.random.default_rng(11))
    records = [_cold_hppc(t, truth_params, planted, cell, 40 + k) for k, t in enumerate((-10.0, 25.0))]
    calls = []

    def spy(name, profile, **kw):
        out = fit_model(name, profile, **kw)
        calls.append((profile.name, kw.get("fit_effects", True), kw.get("start_fit"), out))
        return out

    monkeypatch.setattr(temperature, "fit_model", spy)
    fit_temperatures("dp", records, mode="constant", charge_transfer=True)
    first = {name: out for name, fitted, _, out in calls if fitted}
    second = [(name, start) for name, fitted, start, _ in calls if not fitted]
    assert len(first) == 2 and len(second) == 2
    assert all(start is first[name] for name, start in second)
