"""Temperature-dependent parameter sets: tables over SOC × temperature and OCV curves per temperature.

The interpolation in temperature must be exact at the measured temperatures, stay between its two neighbouring
nodes, hold the end nodes outside the measured range, and carry the exact z-derivative (the filters' Jacobians). Every
registered model must run on such a set through the same lookups (one mechanism): Jacobians against finite differences,
the zero-order hold, and the whole-record open loop against the step loop with a varying temperature.
"""

from __future__ import annotations

import numpy as np
import pytest

from socbench.models import Constant, Lookup, Polynomial, make_model, model_names, paper_params
from socbench.models.params import (
    TemperatureTable,
    params_from_dict,
    params_to_dict,
    soc_function,
    temperature_weights,
)
from socbench.ocv import OCVCurve, TemperatureOCV, ocv_from_dict

from .model_points import random_points
from .test_models_generic import _rk4, assert_open_loop_matches_step_loop, test_jacobians_match_finite_differences

TEMPS = (-20.0, 0.0, 25.0)


def _scaled(f, c: float):
    """``c·f`` in the same form as ``f`` (a node of a table that differs from ``f`` by a known factor)."""
    if isinstance(f, Constant):
        return Constant(c * float(f.value))
    if isinstance(f, Polynomial):
        return Polynomial(tuple(c * x for x in f.coeffs))
    if isinstance(f, Lookup):
        return Lookup(tuple(f.soc), tuple(c * np.asarray(f.value)))
    raise TypeError(type(f))


def _table(f, factors=(2.5, 1.6, 1.0)):
    positive = f.range_on_unit()[0] > 0
    return TemperatureTable(TEMPS, tuple(_scaled(f, c) for c in factors), "log" if positive else "linear")


def _temperature_ocv(curve: OCVCurve) -> TemperatureOCV:
    # colder: the same curve a little lower (an entropic shift of a few mV per cell), still monotone
    shifts = (-0.04, -0.015, 0.0)
    return TemperatureOCV(TEMPS, [OCVCurve(curve.soc, curve.voltage + s) for s in shifts])


def temperature_params(name: str):
    """Model ``name``'s reference set with every parameter a three-temperature table and a temperature OCV."""
    p = paper_params(name)
    return p.replace(values={k: _table(v) for k, v in p.values.items()}, ocv=_temperature_ocv(p.ocv))


# --------------------------------------------------------------------------------------------------- the tables
@pytest.mark.parametrize("scale", ["linear", "log"])
def test_table_is_exact_at_nodes_bounded_between_and_held_outside(scale):
    nodes = (Polynomial((0.002, -0.001, 0.004)), Lookup((0.0, 0.5, 1.0), (0.003, 0.0015, 0.002)), Constant(0.0012))
    tab = TemperatureTable(TEMPS, nodes, scale)
    z = np.linspace(-0.1, 1.1, 241)
    for t, f in zip(TEMPS, nodes):
        v, d = tab.value_and_deriv(z, np.full(z.shape, t))
        v0, d0 = f.value_and_deriv(z)
        np.testing.assert_allclose(v, v0, rtol=1e-14, atol=0)
        np.testing.assert_allclose(d, d0, rtol=1e-12, atol=1e-18)
    rng = np.random.default_rng(0)
    for lo, hi, f_lo, f_hi in zip(TEMPS[:-1], TEMPS[1:], nodes[:-1], nodes[1:]):
        t = rng.uniform(lo, hi, z.size)
        v = tab(z, t)
        a, b = f_lo(z), f_hi(z)
        assert np.all(v >= np.minimum(a, b) - 1e-15) and np.all(v <= np.maximum(a, b) + 1e-15)
    np.testing.assert_array_equal(tab(z, np.full(z.shape, -60.0)), nodes[0](z))
    np.testing.assert_array_equal(tab(z, np.full(z.shape, 80.0)), nodes[-1](z))
    np.testing.assert_array_equal(tab(z), nodes[-1](z))  # temp None: the reference 25 °C, a node here


@pytest.mark.parametrize("scale", ["linear", "log"])
def test_table_z_derivative_matches_finite_differences(scale):
    nodes = (Polynomial((0.01, -0.02, 0.015, 0.003)), Polynomial((0.004, 0.001, 0.002)), Constant(0.0025))
    tab = TemperatureTable(TEMPS, nodes, scale)
    rng = np.random.default_rng(5)
    z = rng.uniform(0.02, 0.98, 500)
    t = rng.uniform(-30.0, 40.0, 500)
    h = 1e-6
    fd = (tab(z + h, t) - tab(z - h, t)) / (2 * h)
    np.testing.assert_allclose(tab.value_and_deriv(z, t)[1], fd, rtol=1e-6, atol=1e-10)


def test_table_broadcasts_z_and_temperature_and_survives_json():
    tab = TemperatureTable((-10.0, 25.0), (Constant(0.004), Polynomial((0.001, 0.002))), "log")
    v = tab(np.linspace(0, 1, 5)[None, :], np.array([[-10.0], [7.5], [25.0]]))
    assert v.shape == (3, 5)
    back = soc_function(tab.to_dict())
    z, t = np.linspace(0, 1, 11), np.linspace(-20, 30, 11)
    np.testing.assert_array_equal(back(z, t), tab(z, t))
    assert back.temperatures == (-10.0, 25.0)


def test_table_rejects_bad_input():
    from socbench.errors import ConfigError

    with pytest.raises(ConfigError, match="increasing"):
        TemperatureTable((25.0, 0.0), (Constant(1.0), Constant(2.0)))
    with pytest.raises(ConfigError, match="one SOC function per temperature"):
        TemperatureTable((0.0, 25.0), (Constant(1.0),))
    with pytest.raises(ConfigError, match="positive"):
        TemperatureTable((0.0, 25.0), (Constant(1.0), Polynomial((1.0, -0.5))), "log")


def test_weights_interpolate_and_clamp():
    k, w = temperature_weights((0.0, 10.0, 40.0), np.array([-5.0, 0.0, 5.0, 10.0, 25.0, 40.0, 50.0]))
    np.testing.assert_array_equal(k, [0, 0, 0, 1, 1, 1, 1])
    np.testing.assert_allclose(w, [0.0, 0.0, 0.5, 0.0, 0.5, 1.0, 1.0])


# --------------------------------------------------------------------------------------------------- OCV(z, T)
def test_temperature_ocv_exact_at_nodes_monotone_and_invertible():
    base = paper_params("dp").ocv
    tocv = _temperature_ocv(base)
    z = np.linspace(0.0, 1.0, 401)
    for t, c in zip(TEMPS, tocv.curves):
        np.testing.assert_array_equal(tocv(z, t), c(z))
    for t in (-25.0, -7.0, 12.0, 30.0):
        v, dv = tocv.value_and_slope(z, t)
        assert np.all(np.diff(v) >= 0) and np.all(dv >= 0)
        assert np.all(v >= tocv.curves[0](z) - 1e-12) and np.all(v <= tocv.curves[-1](z) + 1e-12)
        zz = np.linspace(0.05, 0.95, 19)
        np.testing.assert_allclose(tocv.inverse(tocv(zz, t), temp=t), zz, atol=1e-9)
    h = 1e-6
    zr = np.random.default_rng(2).uniform(0.0, 1.0, 400)  # off the knots (C¹ there: a difference quotient is O(h))
    t = np.full(zr.size, -7.0)
    fd = (tocv(zr + h, t) - tocv(zr - h, t)) / (2 * h)
    np.testing.assert_allclose(tocv.slope(zr, t), fd, rtol=1e-5, atol=1e-8)
    back = ocv_from_dict(tocv.to_dict())
    np.testing.assert_array_equal(back(zr, t), tocv(zr, t))


def test_temperature_ocv_excursion_uses_the_curves_in_play():
    cold = OCVCurve([0.2, 0.6, 1.0], [3.3, 3.7, 4.1])
    warm = OCVCurve([0.0, 0.5, 1.0], [3.0, 3.6, 4.15])
    tocv = TemperatureOCV((-10.0, 25.0), [cold, warm])
    assert float(tocv.excursion(0.1, 25.0)) == 0.0
    assert float(tocv.excursion(0.1, -10.0)) == pytest.approx(0.1)
    assert float(tocv.excursion(0.1, 0.0)) == pytest.approx(0.1)  # both curves weigh in between


# --------------------------------------------------------------------------------------------------- every model
MODELS = model_names()


@pytest.mark.parametrize("name", MODELS)
def test_every_model_reads_temperature_tables(name, monkeypatch):
    """At a measured temperature the model equals the plain model built on that node; in between it differs."""
    plain = make_model(name, paper_params(name))
    warm = make_model(name, temperature_params(name))
    rng = np.random.default_rng(11)
    x, i, dt, _ = random_points(plain, 50, rng)
    t25 = np.full(i.shape, 25.0)
    np.testing.assert_allclose(warm.h(x, i, t25), plain.h(x, i, t25), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(warm.f(x, i, dt, t25), plain.f(x, i, dt, t25), rtol=1e-13, atol=1e-13)
    cold = np.full(i.shape, -20.0)
    assert np.max(np.abs(warm.h(x, i, cold) - plain.h(x, i, cold))) > 1e-3  # the -20 °C node is another cell


@pytest.mark.parametrize("name", MODELS)
def test_every_model_jacobians_with_temperature_tables(name, monkeypatch):
    import tests.test_models_generic as generic

    monkeypatch.setattr(generic, "_model", lambda n, **o: make_model(n, temperature_params(n)))
    test_jacobians_match_finite_differences(name)


@pytest.mark.parametrize("name", MODELS)
def test_every_model_zoh_with_temperature_tables(name):
    m = make_model(name, temperature_params(name))
    rng = np.random.default_rng(8)
    x, i, _, temp = random_points(m, 40, rng)
    dts = np.full(len(i), 1.0)
    exact = m.f(x, i, dts, temp)
    fine = _rk4(m, x, i, dts, temp, x[:, 0], 400)
    keep = [k for k, s in enumerate(m.state_names) if s not in m.discrete_states]
    np.testing.assert_allclose(exact[:, keep], fine[:, keep], rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", MODELS)
def test_every_model_open_loop_with_temperature_tables(name):
    assert_open_loop_matches_step_loop(make_model(name, temperature_params(name)))


def test_temperature_set_survives_its_json_file(tmp_path):
    from socbench.models import load_params, save_params

    p = temperature_params("dp")
    save_params(tmp_path / "p.json", "dp", p)
    name, back = load_params(tmp_path / "p.json")
    assert name == "dp" and back.temperatures == TEMPS
    m1, m2 = make_model("dp", p), make_model("dp", back)
    x = m1.x0(np.array([0.3, 0.6, 0.9]))
    for t in (-30.0, -12.0, 3.0, 25.0):
        np.testing.assert_array_equal(m1.h(x, 2.0, t), m2.h(x, 2.0, t))
    assert params_from_dict(params_to_dict("dp", p))[1].temperatures == TEMPS
    assert paper_params("dp").temperatures == ()


def test_data_outside_the_measured_temperatures_is_warned_about_once():
    import warnings

    from socbench.checks import check_temperature_range
    from socbench.errors import SocbenchWarning
    from socbench.profile import Profile

    p = temperature_params("thevenin")
    t = np.arange(200.0)
    temp = np.full(200, 10.0)
    temp[:20] = -30.0  # 10 % below the coldest table
    prof = Profile(t, np.ones(200), voltage_v=np.full(200, 22.0), temperature_c=temp)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        out = check_temperature_range(prof, p)
        assert check_temperature_range(prof, paper_params("thevenin")) == {}  # one temperature: nothing to say
        inside = check_temperature_range(prof.with_(temperature_c=np.full(200, 10.0)), p)
        none = check_temperature_range(prof.with_(temperature_c=None), p)
    msgs = [str(w.message) for w in rec if issubclass(w.category, SocbenchWarning)]
    assert len(msgs) == 2 and "10.0 % of the samples are below" in msgs[0] and "no temperature column" in msgs[1]
    assert out["below"] == pytest.approx(0.1) and out["above"] == 0.0
    assert inside == {"temperatures": list(TEMPS), "below": 0.0, "above": 0.0} and none["below"] is None
