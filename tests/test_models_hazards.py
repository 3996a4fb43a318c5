"""The numerical hazards of ECM_SPEC §5/§7 are handled the way the spec says, checked on numbers computed here.

Table 3 coefficients are typed in again below (from ECM_SPEC §5, not read from the package's JSON files) and
evaluated with numpy, so a transcription error in ``socbench/data/paper/*.json`` fails these tests.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import quad

from socbench.errors import ModelError
from socbench.loads import constant_current
from socbench.models import GuardLog, Polynomial, make_model, model_class, model_names, paper_ocv, paper_params

from .model_points import random_points
from .test_models_generic import _assert_rel, _fd_state_jac, _steps

Q = 22.0
EPS = 1e-3  # ECM_SPEC §4 B6

# Table 3 (ECM_SPEC §5), highest degree first
RINT_R0 = [0.4196, -1.1809, 1.2548, -0.6560, 0.1840, -0.0248, 0.0026]
PNGV_C0 = [969.2571, 887.6013, 1178.589, 884.2022, 1021.6423, 982.9249, 949.3935]
GNL_C0 = [995.5311, 989.7628, 978.2611, 954.1399, 900.7134, 776.5904, 440.0053]
IRC_R1 = [-0.0677, 0.2359, -0.342, 0.2609, -0.0908, 0.0164, 0.0012]
IRC_R2 = [-0.0215, 0.0754, -0.1052, 0.0786, -0.0241, 0.0037, 0.0005]
IRC_C1 = [336133.6554, -173161.7203, 56453.1902, 664439.2213, -187981.7236, 34324.8044, -976.6841]
IRC_C2 = [-66039255.7773, 199336970.6359, -233768933.8113, 134938550.9402, -42125510.64, 6083989.9682, 93971.9972]


def _model(name, mode=None, **options):
    return make_model(name, paper_params(name, **options), mode)


def _roots_in_unit(coeffs, level=0.0):
    c = np.array(coeffs, dtype=float)
    c[-1] -= level
    r = np.roots(c)
    r = r[np.abs(r.imag) < 1e-9].real
    return np.sort(r[(r >= 0) & (r <= 1)])


def _irc_lambda(z):
    c1, c2 = np.polyval(IRC_C1, z), np.polyval(IRC_C2, z)
    return -(1 / c1 + 1 / c2) / (np.polyval(IRC_R1, z) + np.polyval(IRC_R2, z))


# ----------------------------------------------------------------------------------------------------- (1) Rint
def test_rint_r0_negative_near_full_is_kept_in_strict_and_floored_in_robust():
    roots = _roots_in_unit(RINT_R0)
    assert roots.size == 1 and roots[0] == pytest.approx(0.90335, abs=1e-5)
    z = np.array([0.5, 0.95, 0.98, 1.0])
    r0 = np.polyval(RINT_R0, z)
    assert r0[0] > 0 and np.all(r0[1:] < 0)
    assert r0[2] == pytest.approx(-0.000766, abs=2e-6) and r0[3] == pytest.approx(-0.0007, abs=1e-12)
    x = z[:, None]
    _, _, d_strict = _model("rint", "strict").output(x, 22.0, jac=True)
    log = GuardLog()
    _, _, d_robust = _model("rint", "robust").output(x, 22.0, jac=True, guards=log)
    np.testing.assert_allclose(d_strict, -r0, rtol=1e-12)
    np.testing.assert_allclose(d_robust, [-r0[0], 0.0, 0.0, 0.0], rtol=1e-12)
    assert log.counts == {"R0_floor": 3}


# ------------------------------------------------------------------------------------------- (3), (5) C0 drift
@pytest.mark.parametrize("name, c0, printed_drift", [("pngv", PNGV_C0, 43.2), ("gnl", GNL_C0, 73.5)])
def test_c0_as_printed_drifts_tens_of_volts_and_disabled_stays_zero(name, c0, printed_drift):
    full = 3600.0 * Q * quad(lambda z: 1.0 / np.polyval(c0, z), 0.0, 1.0)[0]
    assert full == pytest.approx(printed_drift, abs=0.05)  # ECM_SPEC §5.3/§7.2
    prof = constant_current(Q, 1.0, dt=2.0, soc_span=1.0)
    sim = _model(name, c0="as_printed").simulate(prof, soc0=1.0)
    z_end = sim.soc[-1]
    expected = 3600.0 * Q * quad(lambda z: 1.0 / np.polyval(c0, z), z_end, 1.0)[0]
    u0 = sim.states[-1, 1]
    assert u0 == pytest.approx(expected, rel=2e-3)
    assert u0 > 0.99 * printed_drift
    # the drift lands on the terminal voltage: it ends tens of volts below the 22 V pack's OCV
    assert sim.voltage_v[-1] < paper_ocv()(z_end) - 0.99 * printed_drift
    off = _model(name).simulate(prof, soc0=1.0)
    assert np.all(off.states[..., 1] == 0.0)
    assert abs(off.voltage_v[-1] - paper_ocv()(z_end)) < 1.0


# -------------------------------------------------------------------------------------------- (6) Improved RC
def test_irc_table3_sign_windows():
    assert _roots_in_unit(IRC_C1) == pytest.approx([0.03403], abs=1e-5)
    assert _roots_in_unit(IRC_C2) == pytest.approx([0.53083], abs=1e-5)
    assert _roots_in_unit(np.add(IRC_C1, IRC_C2)) == pytest.approx([0.57295], abs=1e-5)
    assert _irc_lambda(0.02) > 0 and _irc_lambda(0.55) > 0
    assert _irc_lambda(0.3) < 0 and _irc_lambda(0.8) < 0  # 0.8: stable λ, but C2 < 0


@pytest.mark.parametrize("z", [0.02, 0.55, 0.8])
def test_irc_strict_mode_raises_where_c_negative_or_lambda_positive(z):
    assert np.polyval(IRC_C1, z) < 0 or np.polyval(IRC_C2, z) < 0
    m = _model("improved_rc", "strict")
    with pytest.raises(ModelError):
        m.step(m.x0(z), 22.0, 1.0)
    with pytest.raises(ModelError):
        m.dxdt(m.x0(z), 22.0)


def test_irc_strict_mode_raises_on_flight_start_and_robust_mode_stays_finite():
    prof = constant_current(Q, 1.0, dt=10.0, soc_span=0.99)
    with pytest.raises(ModelError):
        _model("improved_rc", "strict").simulate(prof, soc0=1.0)
    sim = _model("improved_rc", "robust").simulate(prof, soc0=1.0)
    assert np.all(np.isfinite(sim.voltage_v)) and np.all(np.isfinite(sim.states))
    # the floors act where Table 3 gives C < 1e3 F: C2 for z > 0.5303, C1 for z < 0.0854 (roots computed here)
    (z2,) = _roots_in_unit(IRC_C2, 1e3)
    (z1,) = _roots_in_unit(IRC_C1, 1e3)
    z = sim.soc[:-1]  # the state before each of the T − 1 steps; fractions are per sample (T)
    n = sim.soc.size
    span = 1.0 - sim.soc[-1]
    assert sim.guard_fractions["C2_floor"] == pytest.approx((1.0 - z2) / span * (n - 1) / n, abs=2 / n)
    assert sim.guard_fractions["C1_floor"] == pytest.approx(max(z1 - z.min(), 0.0) / span * (n - 1) / n, abs=2 / n)
    # with the floors the network is stable: the deviation voltages stay within a volt on a 1 C discharge
    assert np.max(np.abs(sim.states[:, 1:])) < 1.0


# --------------------------------------------------------------------------------------- (9), (14) at z = 1
def test_nernst_and_plett_are_finite_at_full_charge_with_the_eps_guard():
    zs_hi = 1.0 - EPS
    k0 = -0.0004  # Nernst: −K0 ln z_s + K1 ln(1 − z_s)
    nernst = -k0 * np.log(zs_hi) + 0.0013 * np.log(1.0 - zs_hi)
    plett = 0.0022 - (-0.0009) / zs_hi - 0.0064 * 1.0 + 0.0051 * np.log(zs_hi) + (-0.0002) * np.log(1.0 - zs_hi)
    assert nernst == pytest.approx(-0.00898, abs=1e-5) and plett == pytest.approx(-0.00192, abs=1e-5)
    u1 = float(paper_ocv()(1.0))
    for name, term, r0 in (("nernst", nernst, 0.0016), ("plett", plett, 0.0016)):
        m = _model(name)
        log = GuardLog()
        y, H, D = m.output(np.array([1.0]), 22.0, jac=True, guards=log)
        assert y == pytest.approx(u1 + term - r0 * 22.0, abs=1e-12)
        assert np.all(np.isfinite(H)) and D == pytest.approx(-r0)
        assert log.counts == {"singular_eps": 1}
        # inside the guard band the term is the unclipped formula
        y_in = m.output(np.array([0.9]), 0.0)[0]
        if name == "nernst":
            t_in = 0.0004 * np.log(0.9) + 0.0013 * np.log(0.1)
        else:
            t_in = 0.0022 + 0.0009 / 0.9 - 0.0064 * 0.9 + 0.0051 * np.log(0.9) - 0.0002 * np.log(0.1)
        assert y_in == pytest.approx(float(paper_ocv()(0.9)) + t_in, abs=1e-12)


# ------------------------------------------------------------------------------------------- (13) Tremblay2
def test_tremblay2_voltage_rises_toward_empty():
    m = _model("tremblay2")
    z = np.array([0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 0.9])
    x = np.stack([z, np.zeros_like(z)], axis=-1)
    term = m.output(x, 0.0)[0] - paper_ocv()(z)
    np.testing.assert_allclose(term, 0.0018 * Q * (1 - z) / z, rtol=1e-10)  # −K Q (1 − z)/z with K = −0.0018
    assert term[2] == pytest.approx(0.752, abs=5e-4)  # ECM_SPEC §3.4 table, z = 0.05
    assert term[0] == pytest.approx(3.92, abs=5e-3)
    assert np.all(np.diff(term) < 0)  # the model voltage rises as the pack empties: unphysical K < 0, flagged
    # −K I*/z: +36 mV per ampere of I* at z = 0.05 (discharge branch)
    per_amp = m.output(np.array([0.05, 1.0]), 0.0)[0] - m.output(np.array([0.05, 0.0]), 0.0)[0]
    assert per_amp == pytest.approx(0.036, abs=1e-9)


def test_tremblay_charge_branch_uses_the_1_over_1p1_minus_z_form():
    m = _model("tremblay2")
    z, istar = 0.4, -5.0
    y_c = m.output(np.array([z, istar]), 0.0)[0] - m.output(np.array([z, 0.0]), 0.0)[0]
    k = -0.0018
    assert y_c == pytest.approx(-k * istar / (1.1 - z), rel=1e-10)


# ------------------------------------------------------------------------------------------------ (11) Liu
def test_liu_with_k_zero_is_ocv_plus_exponential_zone():
    m = _model("liu")
    rng = np.random.default_rng(3)
    z = rng.uniform(0.0, 1.0, 500)
    istar = rng.uniform(-40.0, 60.0, 500)
    i = rng.uniform(-30.0, 60.0, 500)
    y = m.output(np.stack([z, istar], axis=-1), i)[0]
    expected = paper_ocv()(z) + (-0.0017) * np.exp(0.072 * Q * (1 - z)) - 0.0016 * i
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-12)
    # ECM_SPEC §3.4: −8.2 mV at z = 0.01 … −1.7 mV near z = 1
    corr = m.output(np.array([[0.01, 0.0], [0.999, 0.0]]), 0.0)[0] - paper_ocv()(np.array([0.01, 0.999]))
    np.testing.assert_allclose(corr, [-0.0082, -0.0017], atol=6e-5)


# -------------------------------------------------------------------------------- §0 item 16: duplicates
def test_tremblay1_with_a_zero_is_shepherd():
    t1 = _model("tremblay1")
    assert t1.params["A"](0.5) == 0.0
    k, r0 = float(t1.params["K"](0.5)), float(t1.params["R0"](0.5))
    sh = make_model("shepherd", paper_params("shepherd").with_values(K=k, R0=r0))
    z = np.r_[0.0, 5e-4, np.linspace(0.01, 0.99, 50), 1.0, 1.02][:, None]
    i = np.linspace(-30, 60, z.shape[0])
    for a, b in zip(t1.output(z, i, jac=True), sh.output(z, i, jac=True)):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(t1.step(z, i, 1.0, jac=True), sh.step(z, i, 1.0, jac=True)):
        np.testing.assert_array_equal(a, b)


def test_liu_and_tremblay2_are_one_structure():
    liu, t2 = model_class("liu"), model_class("tremblay2")
    assert liu.__mro__[1] is t2.__mro__[1] and liu.param_names == t2.param_names
    m = make_model("liu", paper_params("tremblay2"))
    x = np.array([[0.3, 12.0], [0.7, -8.0]])
    np.testing.assert_array_equal(m.output(x, 5.0)[0], _model("tremblay2").output(x, 5.0)[0])


# ----------------------------------------------------------------------------------------- strict vs robust
@pytest.mark.parametrize("name", model_names())
def test_strict_and_robust_agree_where_no_guard_acts(name):
    strict, robust = _model(name, "strict"), _model(name, "robust")
    x, i, dt, temp = random_points(robust, 120, np.random.default_rng(11))
    compared = 0
    for k in range(len(i)):
        log = GuardLog()
        r_step = robust.step(x[k], i[k], dt[k], temp[k], jac=True, guards=log)
        r_out = robust.output(x[k], i[k], temp[k], jac=True, guards=log)
        if log.counts:
            continue
        compared += 1
        for a, b in zip(
            r_step + r_out,
            strict.step(x[k], i[k], dt[k], temp[k], jac=True) + strict.output(x[k], i[k], temp[k], jac=True),
        ):
            np.testing.assert_array_equal(a, b)
    assert compared >= 40, f"only {compared} guard-free points"


# ------------------------------------------------------------------- SOC-dependent parameters (chain rule)
NEW_MODELS = ["shepherd", "unnewehr", "nernst", "fang", "liu", "tremblay1", "tremblay2", "plett", "esc"]


def _as_polynomials(params):
    """Every constant ``c`` becomes ``c (1 − 0.3 z + 0.2 z²)`` (zeros become 1e-3 + 2e-3 z)."""
    new = {}
    for k, f in params.values.items():
        c = float(f(0.5))
        new[k] = Polynomial((0.2 * c, -0.3 * c, c)) if c != 0 else Polynomial((2e-3, 1e-3))
    return params.replace(values=new)


@pytest.mark.parametrize("name", NEW_MODELS)
def test_jacobians_include_parameter_slopes(name):
    m = make_model(name, _as_polynomials(paper_params(name)))
    x, i, dt, temp = random_points(m, 100, np.random.default_rng(5))
    xn, F, _ = m.step(x, i, dt, temp, jac=True)
    y, H, _ = m.output(x, i, temp, jac=True)
    h = _steps(x)
    eps = np.finfo(float).eps
    keep = [k for k, s in enumerate(m.state_names) if s not in m.discrete_states]
    F_fd = _fd_state_jac(lambda xx: m.f(xx, i, dt, temp), x, h)
    H_fd = _fd_state_jac(lambda xx: m.h(xx, i, temp), x, h)
    ro_f = 8 * eps * np.abs(xn)[:, :, None] / (2 * h[:, None, :])
    _assert_rel(F[:, keep][:, :, keep], F_fd[:, keep][:, :, keep], f"{name} F", ro_f[:, keep][:, :, keep])
    _assert_rel(H, H_fd, f"{name} H", 8 * eps * np.abs(y)[:, None] / (2 * h))


# ---------------------------------------------------------------------------------------------------- ESC
def test_esc_hysteresis_and_sign_memory():
    m = _model("esc")
    n = m.n_states
    jh, js = n - 2, n - 1
    x = m.x0(0.8)
    for _ in range(30):  # 30 s of 1 C: h → −(1 − e^{−γ·22·30/(3600·22)})
        x = m.f(x, 22.0, 1.0)
    assert x[jh] == pytest.approx(-(1 - np.exp(-100.0 * 30 / 3600.0)), rel=1e-12)
    assert x[js] == 1.0
    x_small = m.f(x, -0.1, 1.0)  # |I| ≤ Q/100: the sign memory holds
    assert x_small[js] == 1.0
    x_chg = m.f(x, -5.0, 1.0)
    assert x_chg[js] == -1.0 and x_chg[jh] > x[jh]
    r = m.params
    rest = paper_ocv()(x[0]) + r["M"](0) * x[jh] - r["R1"](0) * x[1] - r["R2"](0) * x[2]
    assert m.h(x, 0.0) == pytest.approx(rest + r["M0"](0) * 1.0, abs=1e-12)  # held sign
    # a charge sample flips the instantaneous sign in its own output (simCell.m: s_k from I_k)
    assert m.h(x, -5.0) == pytest.approx(rest - r["M0"](0) + r["R0"](0) * 5.0, abs=1e-12)
    assert m.H(x, -5.0)[js] == 0.0 and m.H(x, -0.1)[js] == r["M0"](0)


# ------------------------------------------------------------------------------------------ docs/models.md
def test_models_doc_lists_every_registered_model_with_its_states():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "models.md").read_text()
    rows = {}
    for line in doc.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 6 and re.fullmatch(r"`[a-z0-9_]+`", cells[1]):
            rows[cells[1].strip("`")] = cells
    assert sorted(rows) == sorted(model_names())
    for name, cells in rows.items():
        m = _model(name)
        num = "" if m.paper_number is None else str(m.paper_number)
        assert cells[0] == num, name
        assert [s.strip(" `") for s in cells[2].split(",")] == list(m.state_names), name
        assert [p.strip(" `") for p in cells[4].split(",")] == list(m.required_params()), name
