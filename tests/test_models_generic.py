"""Generic checks run on every registered model (a new model is picked up by the registry line alone)."""

from __future__ import annotations

import numpy as np
import pytest

from socbench.loads import constant_current, hppc
from socbench.models import make_model, model_names, paper_pack, paper_params

from .model_points import random_points

MODELS = model_names()


def _model(name, **opts):
    return make_model(name, paper_params(name, **opts))


def _fd_state_jac(fun, x, steps):
    """Central finite differences of ``fun`` (batched over points) w.r.t. each state column: (n, out..., nx)."""
    cols = []
    for j in range(x.shape[-1]):
        dx = np.zeros_like(x)
        dx[:, j] = steps[:, j]
        diff = fun(x + dx) - fun(x - dx)
        hj = 2 * steps[:, j].reshape((-1,) + (1,) * (diff.ndim - 1))
        cols.append(diff / hj)
    return np.stack(cols, axis=-1)


def _steps(x):
    return 1e-6 * np.maximum(1.0, np.abs(x))


def _assert_rel(analytic, fd, what, roundoff):
    """|analytic − fd| ≤ 1e-5 · (|fd| + scale of the row) + the rounding error of the difference quotient itself.

    ``roundoff`` ≈ 8 ε |f| / (2 h): a 24 V output differenced over h = 1e-6 carries ~1e-9 of pure rounding.
    """
    scale = np.max(np.abs(fd), axis=-1, keepdims=True) if fd.ndim > 1 else np.abs(fd)
    tol = 1e-5 * (np.abs(fd) + scale) + roundoff
    bad = np.abs(analytic - fd) > tol
    assert not bad.any(), f"{what}: {bad.sum()} entries off, worst {np.max(np.abs(analytic - fd) - tol):.3g}"


@pytest.mark.parametrize("name", MODELS)
def test_jacobians_match_finite_differences(name):
    m = _model(name)
    rng = np.random.default_rng(1234)
    x, i, dt, temp = random_points(m, 200, rng)
    xn, F, B = m.step(x, i, dt, temp, jac=True)
    y, H, D = m.output(x, i, temp, jac=True)
    h = _steps(x)
    F_fd = _fd_state_jac(lambda xx: m.f(xx, i, dt, temp), x, h)
    H_fd = _fd_state_jac(lambda xx: m.h(xx, i, temp), x, h)
    di = 1e-6 * np.maximum(1.0, np.abs(i))
    B_fd = (m.f(x, i + di, dt, temp) - m.f(x, i - di, dt, temp)) / (2 * di[:, None])
    D_fd = (m.h(x, i + di, temp) - m.h(x, i - di, temp)) / (2 * di)
    discrete = [k for k, s in enumerate(m.state_names) if s in m.discrete_states]
    keep = [k for k in range(m.n_states) if k not in discrete]
    eps = np.finfo(float).eps
    ro_f = 8 * eps * np.abs(xn)[:, :, None] / (2 * h[:, None, :])
    ro_h = 8 * eps * np.abs(y)[:, None] / (2 * h)
    _assert_rel(F[:, keep][:, :, keep], F_fd[:, keep][:, :, keep], f"{name} F", ro_f[:, keep][:, :, keep])
    _assert_rel(B[:, keep], B_fd[:, keep], f"{name} B", 8 * eps * np.abs(xn[:, keep]) / (2 * di[:, None]))
    _assert_rel(H, H_fd, f"{name} H", ro_h)
    _assert_rel(D[:, None], D_fd[:, None], f"{name} D", (8 * eps * np.abs(y) / (2 * di))[:, None])


@pytest.mark.parametrize("name", MODELS)
def test_jacobians_match_finite_differences_outside_the_soc_range(name):
    """Where a filter's sigma points and particles go before the clamp: SOC within the OCV's linear extension
    (0.05 beyond the rest points) and far beyond it, where the curve is held (socbench.ocv). The analytic H must
    still be the derivative of h (finite differences taken away from the kinks at the rest points and band edges)."""
    m = _model(name)
    rng = np.random.default_rng(4321)
    x, i, dt, temp = random_points(m, 200, rng)
    lo, hi = m.ocv.soc[0], m.ocv.soc[-1]
    x[:, 0] = np.concatenate([rng.uniform(lo - 0.045, lo - 0.005, 50), rng.uniform(hi + 0.005, hi + 0.045, 50),
                              rng.uniform(lo - 3.0, lo - 0.06, 50), rng.uniform(hi + 0.06, hi + 3.0, 50)])
    y, H, D = m.output(x, i, temp, jac=True)
    assert np.all(np.isfinite(y)) and np.all(np.isfinite(H))
    h = _steps(x)
    H_fd = _fd_state_jac(lambda xx: m.h(xx, i, temp), x, h)
    _assert_rel(H, H_fd, f"{name} H outside [0, 1]", 8 * np.finfo(float).eps * np.abs(y)[:, None] / (2 * h))


def _rk4(m, x, i, dt, temp, z_params, n):
    h = dt / n
    for _ in range(n):
        k1 = m.dxdt(x, i, temp, z_params)
        k2 = m.dxdt(x + 0.5 * h[:, None] * k1, i, temp, z_params)
        k3 = m.dxdt(x + 0.5 * h[:, None] * k2, i, temp, z_params)
        k4 = m.dxdt(x + h[:, None] * k3, i, temp, z_params)
        x = x + h[:, None] / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


@pytest.mark.parametrize("name", MODELS)
@pytest.mark.parametrize("dt", [0.1, 1.0, 10.0])
def test_discrete_step_is_exact_zoh(name, dt):
    m = _model(name)
    rng = np.random.default_rng(7)
    x, i, _, temp = random_points(m, 40, rng)
    dts = np.full(len(i), dt)
    exact = m.f(x, i, dts, temp)
    fine = _rk4(m, x, i, dts, temp, x[:, 0], 400)
    keep = [k for k, s in enumerate(m.state_names) if s not in m.discrete_states]
    np.testing.assert_allclose(exact[:, keep], fine[:, keep], rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", MODELS)
def test_batch_of_10000_matches_state_by_state(name):
    m = _model(name)
    rng = np.random.default_rng(99)
    x, i, dt, temp = random_points(m, 10_000, rng)
    xn, F, B = m.step(x, i, dt, temp, jac=True)
    y, H, D = m.output(x, i, temp, jac=True)
    assert xn.shape == x.shape and F.shape == x.shape + (m.n_states,) and y.shape == (10_000,)
    for k in rng.choice(10_000, size=300, replace=False):
        xk, Fk, Bk = m.step(x[k], i[k], dt[k], temp[k], jac=True)
        yk, Hk, Dk = m.output(x[k], i[k], temp[k], jac=True)
        np.testing.assert_array_equal(xk, xn[k])
        np.testing.assert_array_equal(Fk, F[k])
        np.testing.assert_array_equal(Bk, B[k])
        np.testing.assert_array_equal(yk, y[k])
        np.testing.assert_array_equal(Hk, H[k])
        np.testing.assert_array_equal(Dk, D[k])


@pytest.mark.parametrize("name", MODELS)
@pytest.mark.parametrize("load", ["1c", "hppc"])
def test_simulates_full_profiles_without_nan(name, load):
    pack = paper_pack()
    q = pack["capacity_ah"]
    prof = constant_current(q, 1.0, soc_span=0.99) if load == "1c" else hppc(q, dt=2.0, rest_s=600.0)
    sim = _model(name).simulate(prof, soc0=1.0)
    assert np.all(np.isfinite(sim.voltage_v)) and np.all(np.isfinite(sim.states))
    dz = np.diff(sim.soc)
    discharging = prof.current_a[:-1] >= 0
    assert np.all(dz[discharging] <= 0), "SOC must not rise while discharging"
    assert np.all(dz[~discharging] > 0), "SOC must rise while charging"
    assert sim.soc[-1] == pytest.approx(1.0 - prof.amp_hours()[-1] / q, abs=1e-9)


def assert_open_loop_matches_step_loop(m, exact_soc: bool = True):
    """``m.open_loop`` against ``m.open_loop_stepwise`` on a record with varying dt, charge and discharge, rests, an
    SOC jump, a temperature column and two initial states (shared with the augmented-model tests)."""
    rng = np.random.default_rng(7)
    n = 1500
    q = m.capacity_ah
    t = np.concatenate([[0.0], np.cumsum(rng.choice([0.1, 1.0, 5.0], size=n - 1))])
    levels = rng.choice([0.0, 0.5, 2.0, -1.0], size=n // 25 + 1) * q
    i = np.repeat(levels, 25)[:n] + rng.normal(0.0, 0.01 * q, n)
    temp = 25.0 + np.cumsum(rng.normal(0.0, 0.05, n))
    jumps = np.zeros(n)
    jumps[n // 2] = -0.02
    x0 = m.x0(np.array([0.95, 0.7]))
    s_fast, y_fast = m.open_loop(x0, t, i, temp, jumps)
    s_loop, y_loop = m.open_loop_stepwise(x0, t, i, temp, jumps)
    assert y_fast.shape == (2, n) and s_fast.shape == (2, n, m.n_states)
    np.testing.assert_allclose(s_fast, s_loop, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(y_fast, y_loop, rtol=1e-12, atol=1e-12)
    if exact_soc:  # the SOC path is the loop's own additions: identical, not just close
        np.testing.assert_array_equal(s_fast[..., 0], s_loop[..., 0])


@pytest.mark.parametrize("name", MODELS)
def test_whole_record_open_loop_matches_the_step_loop(name):
    """``open_loop`` (a prefix scan for the models that have one) against one step/output call per sample."""
    assert_open_loop_matches_step_loop(_model(name))


def test_whole_record_open_loop_takes_a_parameter_batch():
    """A fit simulates P + 1 parameter variants in one call: each row must equal its own one-variant simulation
    (the one-variant whole-record path is checked against the step loop by the test above, model by model; the step
    loop here cost 40 s of the suite for the same guarantee)."""
    from dataclasses import replace

    from socbench.identify import setup_fit

    rec = hppc(paper_pack()["capacity_ah"], dt=1.0)
    rec = replace(rec, voltage_v=_model("dp").simulate(rec, soc0=1.0).voltage_v)
    fp = setup_fit("dp", rec, mode="paper")
    rng = np.random.default_rng(3)
    thetas = fp.theta0 + rng.normal(0.0, 0.05, (4, fp.theta0.size))
    batched = fp.build(thetas)
    y_all = batched.open_loop(batched.x0(0.9, (4,)), rec.time_s, rec.current_a)[1]
    for r in range(4):
        one = fp.build(thetas[r])
        y_one = one.open_loop(one.x0(0.9), rec.time_s, rec.current_a)[1]
        np.testing.assert_allclose(y_all[r], y_one, rtol=1e-12, atol=1e-12)
