"""The noise recipe (socbench.estimators.model_error) and its coloured model-error states.

The calibration test plants a *known* model error in synthetic records: the filter's model is exactly the truth's
structure and parameters, and the measured voltage carries an additive Gauss–Markov error (random SD and correlation
time), a resistance the model has wrong (a random offset per draw) and white noise. The recipe measures that error on
separate validation draws at the true SOC; the filter then runs on fresh draws from a wrong initial SOC. Over many
randomised draws its ±3σ band must hold the truth 90–100 % of the time, and the sensor-only covariance must not (so
the test can fail).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from socbench.errors import ConfigError
from socbench.estimators import SensorNoise, make_estimator
from socbench.estimators import model_error as recipe
from socbench.estimators.scoring import score
from socbench.models import make_model, paper_params
from socbench.models.effects import ModelError, augment
from socbench.profile import Profile, ProfileMeta

T_STEPS = 2400
DT = 1.0


def _current(rng, R: int, capacity: float) -> np.ndarray:
    """Piecewise-constant discharge currents, levels 0…2 C held 5–60 s, some short charges (regeneration)."""
    out = np.empty((R, T_STEPS))
    for r in range(R):
        k = 0
        while k < T_STEPS:
            n = int(rng.integers(5, 60))
            level = rng.choice([0.0, rng.uniform(0.2, 2.0), -rng.uniform(0.1, 0.5)], p=[0.25, 0.65, 0.1])
            out[r, k:k + n] = level * capacity
            k += n
    return out


def _gauss_markov(rng, R: int, tau: float) -> np.ndarray:
    phi = np.exp(-DT / tau)
    g = np.empty((R, T_STEPS))
    g[:, 0] = rng.standard_normal(R)
    w = rng.standard_normal((R, T_STEPS)) * np.sqrt(1 - phi * phi)
    for k in range(1, T_STEPS):
        g[:, k] = phi * g[:, k - 1] + w[:, k]
    return g


def _draws(model, rng, R: int, err: dict, load: float = 1.0) -> Profile:
    """``R`` records of ``model`` from SOC 0.9 with the planted error ``err`` (slow σ, τ; resistance σ; white σ), the
    current × ``load`` and the slow and white errors × ``load^err["load_power"]`` (default 0: an error that ignores
    the load)."""
    t = np.arange(T_STEPS) * DT
    cur = load * _current(rng, R, model.capacity_ah)
    x0 = model.x0(np.full(R, 0.9), (R,))
    states, v = model.open_loop(x0, t, cur)
    dr = err["r_sd"] * rng.standard_normal((R, 1))  # one wrong resistance per record
    grow = load ** err.get("load_power", 0.0)
    v = v + grow * (err["slow_sd"] * _gauss_markov(rng, R, err["tau"]) + err["white_sd"] * rng.standard_normal(
        (R, T_STEPS))) - dr * cur
    return Profile(t, cur, v, None, np.clip(states[..., 0], 0, 1), ProfileMeta(name="draw", capacity_ah=22.0))


CONFIGS = [
    # slow SD [V], its correlation time [s], resistance SD [Ω], white SD [V] (the pack: 6 cells in series)
    {"slow_sd": 0.03, "tau": 300.0, "r_sd": 0.0, "white_sd": 0.005},
    {"slow_sd": 0.08, "tau": 900.0, "r_sd": 0.0005, "white_sd": 0.01},
    {"slow_sd": 0.015, "tau": 120.0, "r_sd": 0.001, "white_sd": 0.003},
    # an error more persistent than the record (τ > its 40 min): a filter must not average it as if it renewed
    {"slow_sd": 0.04, "tau": 6000.0, "r_sd": 0.0005, "white_sd": 0.005},
]


def calibration_case(rng, cfg: int, n_test: int, measured_on: str = ""):
    """``(model, err, stats, test, sensor, guess)``: configuration ``cfg`` randomised around its values (a family of
    cells and errors, not one hand-picked case), the recipe measured on 6 validation draws at the true SOC (said to be
    ``measured_on``), ``n_test`` fresh draws, the sensor, and a guess 5 points (SD) off the true initial SOC."""
    err = {k: v * rng.uniform(0.7, 1.4) for k, v in CONFIGS[cfg].items()}
    model = make_model("thevenin", paper_params("thevenin"))
    validation = _draws(model, rng, 6, err)
    stats = recipe.estimate(model, [validation.run(r) for r in range(validation.n_runs)], measured_on=measured_on)
    test = _draws(model, rng, n_test, err)
    sensor = SensorNoise(voltage_sd=err["white_sd"], current_sd=0.01)
    guess = np.clip(test.soc_ref[:, 0] + rng.normal(0.0, 0.05, test.n_runs), 0, 1)
    return model, err, stats, test, sensor, guess


@pytest.mark.parametrize("measured_on", ["", "validation"])
@pytest.mark.parametrize("cfg", range(len(CONFIGS)))
def test_recipe_band_holds_the_truth_with_a_known_model_error(cfg, measured_on):
    """The band holds the truth with the slow scale counted twice (records not said to be out of sample) and shared
    between the two slow states (validation records: draws of the same error as the test's, κ = √½)."""
    model, err, stats, test, sensor, guess = calibration_case(np.random.default_rng(100 + cfg), cfg, 40, measured_on)
    assert recipe.slow_share(stats, test) == (np.sqrt(0.5) if measured_on else 1.0)
    covered = {}
    for noise in ("model", "sensor"):
        m, n = recipe.apply(model, sensor, stats, test, noise=noise)
        est = make_estimator("ekf", m, n, soc0_sd=0.05).run(test, soc0=guess)
        s = score(est, test)
        assert s["failed_runs"] == 0
        covered[noise] = s["frac_within_3sigma"]
        per_draw = s["runs"]["frac_within_3sigma"]
        if noise == "model":
            assert 0.9 <= covered[noise] <= 1.0, (err, covered)
            assert np.mean(per_draw >= 0.8) >= 0.85  # not a few perfect draws hiding many bad ones
            assert 0.2 < s["nis_mean"] < 3.0
    assert covered["sensor"] < 0.9  # without the recipe the same filter is overconfident: the test can fail


def test_estimate_recovers_a_planted_gauss_markov_error():
    rng = np.random.default_rng(7)
    model = make_model("thevenin", paper_params("thevenin"))
    for slow, tau in ((0.02, 200.0), (0.05, 800.0)):
        err = {"slow_sd": slow, "tau": tau, "r_sd": 0.0, "white_sd": 0.004}
        prof = _draws(model, rng, 12, err)
        st = recipe.estimate(model, [prof.run(r) for r in range(prof.n_runs)])
        rms_slow = np.sqrt(np.mean(np.square(st.slow_sd)))
        assert rms_slow == pytest.approx(slow, rel=0.3)
        # the integral time of a Gauss–Markov process is its τ (finite records shorten it somewhat)
        assert 0.4 * tau < st.tau_slow_s < 1.6 * tau
        assert st.white_sd[0] == pytest.approx(0.004, rel=0.35)


def _sustained_draw(rng, model, n: int) -> tuple:
    """A flight-like record of ``model`` (a mean 1.5–3 C held with gusts of SD 0.2–0.5 C, τ 3–10 s) whose measured
    voltage carries a resistance error of one size in the gusts and another at the mean: ``e = −r_dyn (I − Ī) +
    r_dc Ī`` (``Ī`` the current low-passed at 30–120 s; a model fitted on 1 C pulses and flown at 3 C), plus white
    noise. Returns ``(profile, e)``."""
    t = np.arange(n) * DT
    cap = model.capacity_ah
    phi = np.exp(-DT / rng.uniform(3.0, 10.0))
    gust = np.zeros(n)
    for k in range(1, n):
        gust[k] = phi * gust[k - 1] + np.sqrt(1 - phi * phi) * rng.standard_normal()
    cur = cap * (rng.uniform(1.5, 3.0) + rng.uniform(0.2, 0.5) * gust)
    a = np.exp(-DT / rng.uniform(30.0, 120.0))
    lp = np.empty(n)
    lp[0] = cur[0]
    for k in range(1, n):
        lp[k] = a * lp[k - 1] + (1 - a) * cur[k]
    err = -rng.uniform(0.5, 2.0) * 1e-3 * (cur - lp) + rng.uniform(0.5, 2.0) * 1e-3 * lp
    x0 = model.x0(np.full(1, 0.95), (1,))
    states, v = model.open_loop(x0, t, cur[None])
    v = v[0] + err + rng.uniform(0.001, 0.004) * rng.standard_normal(n)
    prof = Profile(t, cur, v, None, np.clip(states[0, :, 0], 0, 1), ProfileMeta(name="sustained", capacity_ah=22.0))
    return prof, err


def test_resistive_split_never_makes_the_rest_larger_than_the_error():
    """On a sustained load the local resistance (seen in the gusts) applied to the whole current must not leave a
    "rest" larger than the error itself: the filter adds the two parts' variances as independent (module docstring,
    "Why c"). Over 12 random flight-like records, the slow scale stays within the error's RMS."""
    rng = np.random.default_rng(41)
    model = make_model("thevenin", paper_params("thevenin"))
    for _ in range(12):
        prof, err = _sustained_draw(rng, model, 1500)
        st = recipe.estimate(model, [prof])
        rms_slow = float(np.sqrt(np.mean(np.square(st.slow_sd))))
        assert rms_slow <= 1.1 * float(np.sqrt(np.mean(err * err))), (rms_slow, float(np.sqrt(np.mean(err * err))))


def test_stats_survive_json_and_reject_bad_shapes():
    st = recipe.ModelErrorStats((0.0, 25.0), (0.0, 0.5, 1.0), [[1, 2, 3], [4, 5, 6]], [[0, 0, 0]] * 2,
                                [[0.001] * 3] * 2, (0.01, 0.02), 300.0, 2.0, 500.0)
    back = recipe.ModelErrorStats.from_dict(st.to_dict())
    assert back == st
    with pytest.raises(ConfigError, match="temperatures × SOC"):
        recipe.ModelErrorStats((25.0,), (0.0, 1.0), [[1, 2, 3]], [[0, 0]], [[0, 0]], (0.01,), 300.0, 2.0, 500.0)
    with pytest.raises(ConfigError, match="correlation times"):
        recipe.ModelErrorStats((25.0,), (0.0, 1.0), [[1, 2]], [[0, 0]], [[0, 0]], (0.01,), 0.0, 2.0, 500.0)


def test_slow_share_counts_the_slow_variance_once_only_where_it_was_measured():
    """κ = √½ for validation records at the record's temperatures; the slow scale counted twice (κ = 1) in sample, when
    nothing is said, or at a temperature the records did not cover; the covered range survives JSON."""
    grid = dict(temps=(25.0,), soc=(0.0, 1.0), slow_sd=[[0.02, 0.04]], fast_sd=[[0.0, 0.0]],
                resistance_sd=[[0.0, 0.0]], white_sd=(0.002,), tau_slow_s=900.0, tau_fast_s=2.0, tau_r_s=600.0)
    val = recipe.ModelErrorStats(**grid, measured_on="validation", covered_c=(24.0, 36.0))
    t = np.arange(100.0)

    def rec(temp):
        return Profile(t, np.ones(100), np.full(100, 3.7), np.asarray(temp, dtype=float) + 0 * t, None,
                       ProfileMeta(name="r"))

    assert recipe.slow_share(val, rec(30.0)) == pytest.approx(np.sqrt(0.5))
    assert recipe.slow_share(val, rec(40.0)) == pytest.approx(np.sqrt(0.5))  # within the 5 K margin
    assert recipe.slow_share(val, rec(0.0)) == 1.0  # a temperature the records did not cover
    assert recipe.slow_share(val, rec(np.where(t < 80, 30.0, 0.0))) == 1.0  # a fifth of it outside: 1
    assert recipe.slow_share(val, rec(np.where(t < 95, 30.0, 0.0))) == pytest.approx(np.sqrt(0.5))
    assert recipe.slow_share(val, None) == pytest.approx(np.sqrt(0.5))  # no record: at 25 °C
    for said in ("identification", ""):
        assert recipe.slow_share(recipe.ModelErrorStats(**grid, measured_on=said, covered_c=(24.0, 36.0)),
                                 rec(30.0)) == 1.0
    # without a covered range (an older PARAMS.json) the temperature nodes stand for it
    assert recipe.slow_share(recipe.ModelErrorStats(**grid, measured_on="validation"), rec(45.0)) == 1.0
    assert recipe.ModelErrorStats.from_dict(val.to_dict()).covered_c == (24.0, 36.0)
    with pytest.raises(ConfigError, match="covered"):
        recipe.ModelErrorStats(**grid, covered_c=(30.0, 20.0))
    # the share scales both slow-scale states of the filter's model, and only them
    model = make_model("thevenin", paper_params("thevenin"))
    sensor = SensorNoise(voltage_sd=0.002, current_sd=0.01)
    run_in, _ = recipe.apply(model, sensor, val, rec(30.0))
    run_out, _ = recipe.apply(model, sensor, val, rec(0.0))
    s_in = run_in.effects[-1].scale(0.5, 30.0, ())[0]
    s_out = run_out.effects[-1].scale(0.5, 30.0, ())[0]
    assert s_in[0] == pytest.approx(np.sqrt(0.5) * 0.03) and s_out[0] == pytest.approx(0.03)
    assert s_in[1:] == pytest.approx(s_out[1:])


def test_apply_adds_four_states_inside_the_kernel_noise_form():
    model = make_model("dp", paper_params("dp"))
    st = recipe.ModelErrorStats((25.0,), (0.0, 1.0), [[0.02, 0.01]], [[0.003, 0.003]], [[1e-3, 2e-3]], (0.004,),
                                400.0, 2.0, 600.0)
    prof = Profile(np.arange(100) * 0.5, np.ones(100), np.full(100, 22.0))
    sensor = SensorNoise(voltage_sd=0.002, current_sd=0.05)
    m, n = recipe.apply(model, sensor, st, prof)
    assert m.n_states == model.n_states + 4
    assert m.state_names[-4:] == ("eps_slow", "eps_fast", "eps_r", "eps_mid")
    # white at 1 s resolution: a record sampled every 0.5 s gets twice the variance per sample
    assert n.voltage_sd == pytest.approx(0.004 * np.sqrt(2.0)) and n.current_sd == 0.05 and n.dt == 0.5
    walk = np.asarray(n.walk_sd) ** 2
    assert np.all(walk[: model.n_states] == 0)
    # the mid state: the geometric middle of the 10 s window and the slow part's 400 s, 63.2 s
    np.testing.assert_allclose(walk[-4:], 1 - np.exp(-2 * 0.5 / np.array([400.0, 2.0, 600.0, 63.2456])), rtol=1e-5)
    assert recipe.apply(model, sensor, st, prof, noise="sensor") == (model, sensor)
    with pytest.raises(ConfigError, match="unknown noise"):
        recipe.apply(model, sensor, st, prof, noise="wild")
    # a record that does not start at rest: the error states start at their stationary spread
    P = make_estimator("ekf", m, n).initial_cov(1, None)[0]
    np.testing.assert_allclose(np.diag(P)[-4:], 1.0)


def test_model_error_effect_jacobians_match_finite_differences():
    eff = ModelError(temps=(-10.0, 25.0), soc=(0.0, 0.5, 1.0), sd_slow=((0.03, 0.02, 0.05), (0.01, 0.008, 0.02)),
                     sd_fast=((0.004, 0.004, 0.006), (0.002, 0.002, 0.003)),
                     sd_r=((0.01, 0.004, 0.008), (0.002, 0.001, 0.002)), tau_slow=300.0, tau_fast=2.0, tau_r=500.0,
                     tau_mid=60.0)
    m = augment(make_model("thevenin", paper_params("thevenin")), [eff])
    rng = np.random.default_rng(3)
    x = m.x0(rng.uniform(0.05, 0.95, 30), (30,))
    x[:, 1] = rng.normal(0, 0.05, 30)
    x[:, -4:] = rng.normal(0, 1, (30, 4))
    i = rng.uniform(-20, 40, 30)
    temp = rng.uniform(-20, 35, 30)
    y, H, D = m.output(x, i, temp, jac=True)
    h = 1e-6
    for j in range(m.n_states):
        dx = np.zeros(m.n_states)
        dx[j] = h
        fd = (m.h(x + dx, i, temp) - m.h(x - dx, i, temp)) / (2 * h)
        np.testing.assert_allclose(H[:, j], fd, rtol=1e-5, atol=1e-7)
    fd = (m.h(x, i + h, temp) - m.h(x, i - h, temp)) / (2 * h)
    np.testing.assert_allclose(D, fd, rtol=1e-5, atol=1e-7)
    xn, F, B = m.step(x, i, 1.0, temp, jac=True)
    np.testing.assert_allclose(np.diagonal(F[:, -4:, -4:], 0, -2, -1),
                               np.exp(-1.0 / np.array([300.0, 2.0, 500.0, 60.0])) * np.ones((30, 4)))
    # open loop: without noise the error states only decay; the whole-record path equals the step loop
    t = np.arange(50.0)
    s1, v1 = m.open_loop(x[:2], t, np.full((2, 50), 10.0), np.full((2, 50), 5.0))
    s2, v2 = m.open_loop_stepwise(x[:2], t, np.full((2, 50), 10.0), np.full((2, 50), 5.0))
    np.testing.assert_allclose(v1, v2, rtol=1e-10, atol=1e-10)


def test_scheduling_drops_the_soc_slope_of_the_dynamics_in_ekf_and_ukf_alike():
    from socbench.estimators.base import scheduled_jacobian, scheduled_step

    model = make_model("dp", paper_params("dp"))
    rng = np.random.default_rng(2)
    x = model.x0(rng.uniform(0.1, 0.9, 4), (4,))
    x[:, 1:] = rng.normal(0, 0.02, (4, model.n_states - 1))
    _, F, _ = model.step(x, np.full(4, 20.0), 1.0, None, jac=True)
    assert np.all(scheduled_jacobian(model, F) == F)  # off by default: the full Jacobian
    sched = make_model("dp", paper_params("dp"))
    sched.schedule_soc = True
    Fs = scheduled_jacobian(sched, F)
    assert np.all(Fs[:, 1:, 0] == 0) and np.all(Fs[:, :, 1:] == F[:, :, 1:]) and np.all(Fs[:, 0, 0] == F[:, 0, 0])
    # sigma points: every point's RC states step with the mean's parameters; the SOC keeps its own deviation
    X = x[:, None, :] + rng.normal(0, 0.03, (4, 5, model.n_states))
    Xf, _, _ = scheduled_step(sched, X, x, np.full((4, 1), 20.0), 1.0, None, False)
    Xm = X.copy()
    Xm[..., 0] = x[:, None, 0]
    ref, _, _ = model.step(Xm, np.full((4, 1), 20.0), 1.0, None)
    np.testing.assert_allclose(Xf[..., 1:], ref[..., 1:], rtol=1e-12)
    plain, _, _ = model.step(X, np.full((4, 1), 20.0), 1.0, None)
    np.testing.assert_allclose(Xf[..., 0], plain[..., 0], rtol=1e-12, atol=1e-15)
    assert recipe.apply(model, SensorNoise(0.002, 0.02), recipe.ModelErrorStats(
        (25.0,), (0.0, 1.0), [[0.02, 0.01]], [[0.0, 0.0]], [[0.0, 0.0]], (0.004,), 400.0, 2.0, 600.0))[0].schedule_soc


def test_scheduling_reads_the_soc_off_the_equilibrium_curve_alone_in_ekf_and_ukf_alike():
    """The output counterpart: under scheduling the SOC column of H is the OCV slope (an RC model's equilibrium
    curve), not OCV' − R0'(z)·I; sigma points take the output at the mean SOC plus their own OCV difference, so their
    spread follows that same H."""
    from socbench.estimators.base import scheduled_output, scheduled_points_output

    rng = np.random.default_rng(3)
    model = make_model("dp", paper_params("dp"))  # R0, R1, C1… are SOC polynomials (R0'(z) ≠ 0)
    sched = make_model("dp", paper_params("dp"))
    sched.schedule_soc = True
    x = model.x0(rng.uniform(0.2, 0.8, 5), (5,))
    x[:, 1:] = rng.normal(0, 0.05, (5, model.n_states - 1))
    i = rng.uniform(20.0, 60.0, 5)
    y, H, D = model.output(x, i, None, jac=True)
    ys, Hs, Ds = scheduled_output(sched, x, i, None)
    np.testing.assert_array_equal(ys, y)
    np.testing.assert_array_equal(Ds, D)
    np.testing.assert_array_equal(Hs[:, 1:], H[:, 1:])
    z, dz = x[:, 0], 1e-6
    ocv_slope = (model.ocv.value(z + dz) - model.ocv.value(z - dz)) / (2 * dz)
    np.testing.assert_allclose(Hs[:, 0], ocv_slope, rtol=1e-5)
    assert np.max(np.abs(H[:, 0] - ocv_slope)) > 1e-3  # the full Jacobian has R0'(z)·I: a different column
    assert np.all(scheduled_output(model, x, i, None)[1] == H)  # off by default
    # sigma points around each mean (point 0 the mean): output differences follow the scheduled H to first order
    dX = rng.normal(0, 1e-5, (5, 6, model.n_states))
    dX[:, 0] = 0.0
    X = x[:, None, :] + dX
    Y, _, _ = scheduled_points_output(sched, X, i[:, None], None, False)
    np.testing.assert_allclose(Y[:, 0], y, rtol=1e-14)  # y + E(z̄) − E(z̄)
    np.testing.assert_allclose(Y - y[:, None], np.einsum("rsi,ri->rs", dX, Hs), rtol=1e-4, atol=1e-12)
    Yfull, _, _ = scheduled_points_output(model, X, i[:, None], None, False)
    np.testing.assert_allclose(Yfull - y[:, None], np.einsum("rsi,ri->rs", dX, H), rtol=1e-4, atol=1e-12)
    assert np.max(np.abs(Y - Yfull)) > 1e-3 * np.max(np.abs(Y - y[:, None]))  # the two forms differ


def test_correlation_time_beyond_the_record_and_robust_cell_scales():
    # a Gauss–Markov correlation measured to 1200 s gives its τ even when τ is longer than the lags (persistence)
    lags = np.arange(1201.0)
    for tau in (300.0, 5000.0, 12000.0):
        assert recipe._pooled_time([(np.exp(-lags / tau), 1.0, 0.0)], 1.0, 1200.0) == pytest.approx(tau, rel=0.02)
    assert recipe._pooled_time([(np.ones(1201), 1.0, 0.0)], 1.0, 1200.0) == recipe.MAX_LAG_S  # a bias: capped
    # an error that changes sign within the lags: the integral time, not the persistence formula
    osc = np.cos(lags / 200.0) * np.exp(-lags / 400.0)
    assert recipe._pooled_time([(osc, 1.0, 0.0)], 1.0, 1200.0) < 400.0
    # cells holding few independent looks move toward the row's median cell; well-observed cells keep their own
    num = np.array([1.0, 4.0, 9.0, 100.0]) * np.array([1e5, 1e5, 1e5, 10.0])
    den = np.array([1e5, 1e5, 1e5, 10.0])
    v = recipe._shrunk(num, den, (25.0,), (0.0, 0.3, 0.6, 1.0), 100.0)[0]
    np.testing.assert_allclose(v[:3], [1.0, 4.0, 9.0], rtol=0.01)
    assert v[3] == pytest.approx((0.1 * 100.0 + 6.5) / 1.1)  # the row median of 1, 4, 9, 100 is 6.5


@pytest.mark.parametrize("cfg", range(len(CONFIGS)))
def test_particle_filter_takes_the_recipe_as_an_inflated_white_r(cfg):
    """The bootstrap PF declares the inflated form: the model is not augmented, R holds every part of the error, and
    the weights count the coloured part once per correlation time (``SensorNoise.weight_extra_var``). On planted
    errors its band then holds the truth in 90–100 % of the samples, and in most draws (without the widened weights:
    8–16 % on these draws, so the test can fail), and its SOC stays within 2.5× the EKF's (with the coloured states
    its particles collapse: 15–31 % SOC RMSE on these draws)."""
    from socbench.estimators import estimator_class

    assert estimator_class("pf").model_error_form == "inflated"
    assert estimator_class("ekf").model_error_form == "states"
    model, err, stats, test, sensor, guess = calibration_case(np.random.default_rng(600 + cfg), cfg, 16)
    m, n = recipe.apply(model, sensor, stats, test, form="inflated")
    assert m is model
    parts = stats.summary()
    floor = parts["white"][0] ** 2 + parts["slow"][0] ** 2 + parts["fast"][0] ** 2
    assert n.voltage_sd ** 2 >= floor * (1 - 1e-12) and n.voltage_sd >= sensor.voltage_sd
    # the coloured part at least once per its correlation time: the slow part alone, twice (slow and mid states)
    assert n.weight_extra_var >= 2.0 * parts["slow"][0] ** 2 * 2.0 * stats.tau_mid_s

    def run(noise):
        return score(make_estimator("pf", m, noise, soc0_sd=0.05, n_particles=200).run(test, soc0=guess, seed=3), test)

    pf, white = run(n), run(replace(n, weight_extra_var=0.0))
    assert pf["failed_runs"] == 0 and np.isfinite(pf["nis_mean"])
    assert 0.9 <= pf["frac_within_3sigma"] <= 1.0, pf["frac_within_3sigma"]
    assert np.mean(pf["runs"]["frac_within_3sigma"] >= 0.8) >= 0.85
    assert white["frac_within_3sigma"] < 0.9
    ms, ns = recipe.apply(model, sensor, stats, test, form="states")
    ekf = score(make_estimator("ekf", ms, ns, soc0_sd=0.05).run(test, soc0=guess), test)
    assert pf["soc_rmse"] < max(2.5 * ekf["soc_rmse"], 0.01), (pf["soc_rmse"], ekf["soc_rmse"])
    with pytest.raises(ConfigError):
        recipe.apply(model, sensor, stats, test, form="bands")


def test_inflated_form_counts_the_white_part_at_the_measured_resolution():
    """A 10 Hz record gets the white part ten times per-sample variance (the same information per second as the
    states form); the coloured parts are per-sample variances and do not scale."""
    rng = np.random.default_rng(5)
    model = make_model("thevenin", paper_params("thevenin"))
    err = {"slow_sd": 0.03, "tau": 300.0, "r_sd": 0.0, "white_sd": 0.005}
    validation = _draws(model, rng, 4, err)
    stats = recipe.estimate(model, [validation.run(r) for r in range(validation.n_runs)])
    sensor = SensorNoise(voltage_sd=0.001, current_sd=0.01)
    slow = _draws(model, rng, 1, err)
    fast = Profile(slow.time_s / 10.0, slow.current_a, slow.voltage_v, None, slow.soc_ref, slow.meta)
    v1 = recipe.inflated_noise(sensor, stats, slow).voltage_sd ** 2
    v10 = recipe.inflated_noise(sensor, stats, fast).voltage_sd ** 2
    white = stats.white_var(None)
    assert v10 - v1 == pytest.approx(9.0 * white, rel=1e-9)


def test_cli_fit_measures_the_recipe_on_an_hppc_without_a_reference(tmp_path, capsys):
    """`socbench fit` on an HPPC record that carries no reference SOC still stores a measured model error (on the
    HPPC's own SOC axis, counted from full), so `socbench estimate` with those parameters runs the recipe instead of
    warning that there is none; a record that is neither (no reference, no HPPC) gets the note and no block."""
    import json

    from socbench.cli import main

    from . import hppc_records as H

    rec = H.issue_record(seed=5)
    assert rec.profile.soc_ref is None
    hppc = H.write_canonical(rec.profile, tmp_path / "hppc.csv")
    ins = H.Instrument(dt=1.0, v_noise=1e-3)
    drive = H.drive_record(H.ISSUE_CELL, ins, seed=6, duration_s=1800.0).profile
    drive_csv = H.write_canonical(drive, tmp_path / "drive.csv")
    params = tmp_path / "p.json"
    assert main(["fit", "--data", str(hppc), "--model", "thevenin", "--out", str(params)]) == 0
    assert "on its HPPC SOC axis" in capsys.readouterr().out
    block = json.loads(params.read_text()).get("model_error")
    assert block is not None and all(np.isfinite(np.asarray(block["slow_sd_v"], dtype=float)).ravel())
    assert main(["estimate", "--data", str(drive_csv), "--params", str(params), "--estimator", "ekf",
                 "--out", str(tmp_path / "E")]) == 0
    assert "no measured model error" not in capsys.readouterr().err
    # no reference and no HPPC structure: nothing to measure on
    bare = H.write_canonical(drive.with_(soc_ref=None), tmp_path / "bare.csv")
    ocv = tmp_path / "ocv.json"
    z, v = H.OCV_SHAPES["nmc"]
    ocv.write_text(json.dumps({"soc": z, "voltage": v}))
    assert main(["fit", "--data", str(bare), "--model", "thevenin", "--ocv", str(ocv), "--capacity", "3.3",
                 "--out", str(tmp_path / "q.json")]) == 0
    assert "no model_error block" in capsys.readouterr().out
    assert "model_error" not in json.loads((tmp_path / "q.json").read_text())


def _hppc_recipe_on_a_drive(seed: int, tmp_path) -> dict:
    """One draw of the test generator (tests/hppc_records: random cell, layout, instrument): thevenin fitted by
    `socbench fit` on the HPPC, so the recipe is measured on the identification record itself (in sample, as a user
    without validation records gets it); then the EKF from the true SOC on a 1-hour drive of the same cell, with the
    recipe as it is and with ``ε_mid`` held at 0. ``{variant: (SOC RMSE, share within 3σ)}``."""
    import contextlib
    import io
    import json

    from socbench.cli import main
    from socbench.models import load_params

    from . import hppc_records as H

    rec = H.random_hppc(seed)
    hppc = H.write_canonical(rec.profile, tmp_path / f"hppc{seed}.csv")
    params = tmp_path / f"p{seed}.json"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["fit", "--data", str(hppc), "--model", "thevenin", "--out", str(params)]) == 0
    name, p = load_params(params)
    stats = recipe.ModelErrorStats.from_dict(json.loads(params.read_text())["model_error"])
    ins = H.Instrument(dt=1.0, v_noise=rec.instrument.v_noise, i_noise_c=rec.instrument.i_noise_c)
    drive = H.drive_record(rec.cell, ins, seed=seed + 100, duration_s=3600.0).profile
    out = {}
    for variant in ("as is", "without mid"):
        model, noise = recipe.apply(make_model(name, p), SensorNoise(voltage_sd=0.01, current_sd=0.0), stats, drive)
        if variant == "without mid":
            model, noise = recipe.without_mid(model, noise)
        s = score(make_estimator("ekf", model, noise, soc0_sd=0.01).run(drive, soc0=float(drive.soc_ref[0])), drive)
        out[variant] = (s["soc_rmse"], s["frac_within_3sigma"])
    return out


@pytest.mark.slow
def test_mid_state_keeps_the_band_on_a_drive_the_hppc_recipe_did_not_see(tmp_path):
    """The recipe measured on an HPPC (in sample) meets a drive cycle whose error moves at periods of minutes, which
    one persistent slow state does not describe (module docstring). Over 24 random cells of the test generator the
    band holds the truth (≥ 0.9 of the samples) in at least three draws more with ``ε_mid`` than with it held at 0, and
    the median SOC error is not larger; where the HPPC file holds its step discharges, the band holds in at least 80 %
    of the draws. Measured (thevenin): 16 of 24 against 13, 15 of the 17 with steps; seeds 1000–1047: 36 of 48 against
    30, 34 of the 42 with steps.

    Where the file leaves the steps out (Panasonic-style gaps: only the pulses and part of each rest), the HPPC holds no
    sustained load at all, and the recipe measured on it cannot see the error a drive's sustained load brings (a slow
    branch a one-branch fit lacks: 15–46 mV open loop on these drives); the band held there in 1 of 7 draws (2 of 6 on
    seeds 1000–1047), and `socbench fit` says the recipe is too small for a drive. Until stop 69 it held in all 7:
    the recipe ran the HPPC open loop on the raw current, and the lab sensor's offset, integrated over the day-long
    test, was read as a slow model error that widened the band (tests/test_recipe_sensor_offset.py)."""
    runs = [(_hppc_recipe_on_a_drive(seed, tmp_path), _steps_left_out(seed)) for seed in range(24)]
    held = {v: sum(r[v][1] >= 0.9 for r, _ in runs) for v in ("as is", "without mid")}
    assert held["as is"] >= held["without mid"] + 3, held
    with_steps = [r for r, gaps in runs if not gaps]
    assert sum(r["as is"][1] >= 0.9 for r in with_steps) >= 0.8 * len(with_steps), held
    med = {v: np.median([r[v][0] for r, _ in runs]) for v in held}
    assert med["as is"] <= med["without mid"], med


def _steps_left_out(seed: int) -> bool:
    """Whether draw ``seed`` of the test generator leaves the HPPC's step discharges out of the file."""
    from . import hppc_records as H

    return bool(H.random_setup(seed)[2].gaps)
