"""Domain checks (socbench.domain) on every model and estimator, and the clamped OCV extrapolation (socbench.ocv)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator

from socbench.domain import SOC_OVERSHOOT, domain_report, guard_fractions, outside_message, warn_outside
from socbench.errors import SocbenchWarning
from socbench.estimators import estimator_names, make_estimator
from socbench.models import make_model, model_names, paper_params
from socbench.ocv import EXCURSION_FLAG, OCVCurve
from socbench.profile import Profile, ProfileMeta

MODELS = model_names()


def _through_empty(q: float, rng, overshoot: float, dt=None):
    """A discharge from SOC 1 to ``−overshoot`` (counted independently here), random rate, step and ripple."""
    dt = rng.choice([0.5, 1.0, 2.0, 10.0]) if dt is None else dt
    c_rate = rng.uniform(0.5, 3.0)
    n = int(np.ceil((1.0 + overshoot) * 3600.0 / (c_rate * dt))) + 1
    t = np.arange(n) * dt
    i = c_rate * q * (1.0 + 0.2 * rng.uniform(0.0, 1.0, n))  # discharge only: η = 1, the counter is exact
    z = 1.0 - np.concatenate([[0.0], np.cumsum(i[:-1] * dt)]) / (3600.0 * q)
    return Profile(t, i, meta=ProfileMeta(name="through-empty", capacity_ah=q)), z


@pytest.mark.parametrize("name", MODELS)
def test_every_model_counts_soc_below_zero_and_ocv_extrapolation(name):
    m = make_model(name, paper_params(name))
    rng = np.random.default_rng(abs(hash(name)) % 2**32)
    lo = m.ocv.soc[0]
    for _ in range(5):
        prof, z = _through_empty(m.capacity_ah, rng, overshoot=rng.uniform(0.1, 0.6))
        sim = m.simulate(prof, soc0=1.0)
        d = sim.domain
        np.testing.assert_allclose(sim.soc, z, rtol=0, atol=1e-9)
        assert d["samples"] == prof.n
        assert d["soc_below_0"] == np.count_nonzero(z < -SOC_OVERSHOOT)
        assert d["ocv_extrapolated"] == np.count_nonzero((z < lo - 1e-12) | (z > m.ocv.soc[-1] + 1e-12))
        assert d["ocv_held"] == np.count_nonzero(z < lo - EXCURSION_FLAG)
        assert d["outside"] >= d["soc_below_0"] and d["outside_fraction"] == pytest.approx(d["outside"] / prof.n)
        assert np.all(np.isfinite(sim.voltage_v))
        # the guard log of the simulation is in the report and in the shares
        assert guard_fractions(d)["soc_below_0"] == pytest.approx(d["soc_below_0"] / prof.n)
        for g, c in d["guards"].items():
            assert guard_fractions(d)[g] == pytest.approx(c / prof.n)
        assert outside_message(d, name) is not None  # ≥ 9 % of samples below empty: always worth a warning


def _cc_cv_charge(q: float, soc0: float, end: float, rng):
    """A CC-CV charge of a cell of ``q`` Ah from ``soc0`` whose count ends at ``end`` (random rate, step, taper): the CC
    phase to 90 % of the charge, then a current decaying exponentially to a twentieth of its start."""
    dt = rng.choice([0.5, 1.0, 2.0, 10.0])
    c_rate = rng.uniform(0.3, 1.5)
    n_cc = max(int(0.9 * (end - soc0) * 3600.0 / (c_rate * dt)), 2)
    tau = rng.uniform(300.0, 1200.0)
    taper = np.exp(-np.arange(0.0, 3.0 * tau, dt) / tau)
    shape = np.concatenate([np.ones(n_cc), taper, np.zeros(int(rng.integers(10, 100)))])
    i = -shape * (end - soc0) * 3600.0 * q / (np.sum(shape[:-1]) * dt)  # charge: negative; the last one never acts
    t = np.arange(shape.size) * dt
    z = soc0 - np.concatenate([[0.0], np.cumsum(i[:-1] * dt)]) / (3600.0 * q)
    return Profile(t, i, meta=ProfileMeta(name="cc-cv", capacity_ah=q)), z


@pytest.mark.parametrize("name", ["rint", "thevenin", "dp", "esc"])
def test_a_count_that_ends_a_charge_a_hair_above_full_is_not_outside_the_domain(name):
    """A CC-CV charge whose count ends up to 0.05 % above full (the model's capacity and the cycler's a few 1e-4 apart,
    as a fit gives) is inside the domain and raises no warning; one that ends 1–5 % above full is outside on every
    sample beyond ``1 + SOC_OVERSHOOT``, and warned about. 20 random charges each."""
    m = make_model(name, paper_params(name))
    rng = np.random.default_rng(sum(map(ord, name)))
    for _ in range(10):
        prof, z = _cc_cv_charge(m.capacity_ah, rng.uniform(0.1, 0.6), 1.0 + rng.uniform(1e-5, 5e-4), rng)
        d = m.simulate(prof, soc0=float(z[0])).domain
        assert d["soc_max"] > 1.0 and d["soc_above_1"] == 0 and d["outside"] == 0, d
        assert outside_message(d, name) is None
    for _ in range(10):
        prof, z = _cc_cv_charge(m.capacity_ah, rng.uniform(0.1, 0.6), 1.0 + rng.uniform(0.01, 0.05), rng)
        sim = m.simulate(prof, soc0=float(z[0]))
        np.testing.assert_allclose(sim.soc, z, rtol=0, atol=1e-9)
        assert sim.domain["soc_above_1"] == np.count_nonzero(z > 1.0 + SOC_OVERSHOOT) > 0
        assert outside_message(sim.domain, name) is not None


@pytest.mark.parametrize("name", MODELS)
def test_the_ocv_of_every_model_is_held_far_outside_its_rest_points(name):
    """Driven to SOC −50 the voltage no longer follows an unbounded line: the OCV part is the held end value."""
    m = make_model(name, paper_params(name))
    ocv = m.ocv
    z = np.array([-50.0, -5.0, ocv.soc[0] - 0.06, ocv.soc[-1] + 0.06, 5.0, 50.0])
    u, du = ocv.value_and_slope(z)
    low = ocv.voltage[0] - ocv._slope_lo * EXCURSION_FLAG
    high = ocv.voltage[-1] + ocv._slope_hi * EXCURSION_FLAG
    np.testing.assert_allclose(u, [low, low, low, high, high, high], rtol=1e-12)
    assert np.all(du == 0.0)


def test_ocv_clamp_value_and_derivative_on_random_curves():
    rng = np.random.default_rng(11)
    for _ in range(50):
        k = rng.integers(3, 15)
        z = np.sort(np.r_[rng.uniform(0.0, 0.1), rng.uniform(0.1, 0.9, k - 2), rng.uniform(0.9, 1.0)])
        v = 2.5 + np.cumsum(rng.uniform(0.01, 0.3, k))
        ocv = OCVCurve(z, v)
        lo, hi = ocv.soc[0], ocv.soc[-1]
        # the end slopes: the interpolant's end derivatives, never flatter than the end segments
        d, secant = PchipInterpolator(ocv.soc, ocv.voltage).derivative(), np.diff(ocv.voltage) / np.diff(ocv.soc)
        s_lo, s_hi = max(float(d(lo)), secant[0]), max(float(d(hi)), secant[-1])
        # inside the band: the linear extension with the end slopes; beyond: held at the band edge
        zin = np.r_[rng.uniform(lo - EXCURSION_FLAG, lo, 20), rng.uniform(hi, hi + EXCURSION_FLAG, 20)]
        want = np.where(zin < lo, ocv.voltage[0] + s_lo * (zin - lo), ocv.voltage[-1] + s_hi * (zin - hi))
        np.testing.assert_allclose(ocv(zin), want, rtol=1e-12, atol=1e-12)
        zout = np.r_[rng.uniform(lo - 10.0, lo - EXCURSION_FLAG, 20), rng.uniform(hi + EXCURSION_FLAG, hi + 10, 20)]
        want_out = np.where(zout < lo, ocv.voltage[0] - s_lo * EXCURSION_FLAG, ocv.voltage[-1] + s_hi * EXCURSION_FLAG)
        np.testing.assert_allclose(ocv(zout), want_out, rtol=1e-12)
        # continuous at the rest points and band edges; derivative = finite differences away from the kinks
        for edge in (lo, hi, lo - EXCURSION_FLAG, hi + EXCURSION_FLAG):
            assert abs(float(ocv(edge + 1e-9) - ocv(edge - 1e-9))) < 1e-6
        zz = np.linspace(lo - 0.3, hi + 0.3, 3001)
        kinks = np.r_[ocv.soc, lo - EXCURSION_FLAG, hi + EXCURSION_FLAG]
        off = np.min(np.abs(zz[:, None] - kinks[None, :]), axis=1) > 1e-5
        h = 1e-7
        fd = (ocv(zz + h) - ocv(zz - h)) / (2 * h)
        np.testing.assert_allclose(ocv.slope(zz)[off], fd[off], rtol=1e-5, atol=1e-6)
        # the inverse stops at the held ends
        assert ocv.inverse(ocv.voltage[0] - 10.0) == pytest.approx(lo - EXCURSION_FLAG, abs=1e-9)
        assert ocv.inverse(ocv.voltage[-1] + 10.0) == pytest.approx(hi + EXCURSION_FLAG, abs=1e-9)


@pytest.mark.parametrize("estimator", estimator_names())
def test_every_estimator_reports_its_domain_and_warns_when_driven_past_empty(estimator):
    """A record that goes 40 % past empty on the counted charge: every estimator's report counts it (the clamp holds
    the estimate at 0 where the counter would be below); the same record stopped at 20 % is clean."""
    m = make_model("thevenin", paper_params("thevenin"))
    q = m.capacity_ah
    rng = np.random.default_rng(5)
    prof_past, z = _through_empty(q, rng, overshoot=0.4, dt=10.0)
    v = m.simulate(prof_past.with_(), soc0=1.0).voltage_v
    prof_past = prof_past.with_(voltage_v=v + 0.005 * rng.standard_normal(v.size))
    keep = int(np.argmax(z < 0.2))
    prof_ok = prof_past.slice(0, keep)
    opts = {"n_particles": 100} if estimator in ("pf", "rbpf") else {}
    for prof, past in ((prof_past, True), (prof_ok, False)):
        est = make_estimator(estimator, m, **opts).run(prof, soc0=1.0, seed=1)
        d = est.domain
        assert d["samples"] == prof.n and d["segments"] == 1
        if estimator == "coulomb":  # open loop: clamped exactly where the count is below 0
            assert d["soc_clamped"] == np.count_nonzero(z[:prof.n] < 0.0)
        if past:
            assert d["outside_fraction"] > 0.05, d
            with pytest.warns(SocbenchWarning, match="outside the model's domain"):
                warn_outside(d, estimator)
        else:
            assert d["outside"] == 0, d
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                assert warn_outside(d, estimator) is None


def test_guards_are_evaluated_along_given_states_and_an_implausible_voltage_always_warns():
    """Without a guard log the report evaluates the model's guards itself (here Rint's R0 floor above z = 0.903 on
    the paper's polynomial, ECM_SPEC §7.1), and a single kilovolt sample is enough for the warning."""
    m = make_model("rint", paper_params("rint"))
    z = np.linspace(1.0, 0.5, 501)
    states = z[:, None]
    cur = np.full(z.size, 22.0)
    d = domain_report(m, states=states, current=cur, time_s=np.arange(z.size, dtype=float))
    floored = np.count_nonzero(m.params["R0"].value_and_deriv(z)[0] < 0.0)
    assert floored > 0
    # the output floors R0 on every such sample, the step evaluates nothing there (Rint's step has no R0)
    assert d["guards"].get("R0_floor") == floored
    assert d["outside"] == 0 and outside_message(d, "rint") is None
    volts = m.output(states, cur)[0]
    volts[100] = 4000.0  # one sample in kilovolts
    d = domain_report(m, states=states, voltage=volts)
    assert d["voltage_implausible"] == 1
    assert "implausible on 1 samples" in outside_message(d, "rint")


def test_a_clamp_counts_as_outside_only_once_the_record_has_gone_a_band_beyond_it():
    """An estimate held at 0 over a constant discharge: the samples after more than 0.05 of the capacity has been
    drawn since it got there are out of the domain; a brief clamp (at 1 at the start of a flight) is not."""
    m = make_model("rint", paper_params("rint"))
    q, dt, amps = m.capacity_ah, 10.0, m.capacity_ah  # 1 C: 1/360 of the capacity per step
    T = 200
    t = np.arange(T) * dt
    i = np.full(T, amps)
    soc = np.linspace(1.0, 0.5, T)
    clamped = np.zeros(T, bool)
    clamped[:3] = True  # at 1 at the start: the count went down, not up
    soc[:3] = 1.0
    soc[60:] = 0.0
    clamped[60:] = True  # held at 0 from sample 60 on
    d = domain_report(m, soc=soc, current=i, time_s=t, clamped=clamped)
    drawn = (np.arange(T) - 60) * amps * dt / (3600.0 * q)  # since sample 60, into each sample
    want = np.count_nonzero((np.arange(T) >= 60) & (drawn > EXCURSION_FLAG))
    assert d["soc_clamped"] == 143 and d["soc_pinned"] == want == T - 60 - 19
    assert d["outside"] == want
    # charging while held at 1 counts the same way; without the current the clamp is only reported
    d_hi = domain_report(m, soc=np.ones(T), current=-i, time_s=t, clamped=np.ones(T, bool))
    assert d_hi["soc_pinned"] == np.count_nonzero(np.arange(T) * amps * dt / (3600.0 * q) > EXCURSION_FLAG)
    assert domain_report(m, soc=soc, clamped=clamped)["outside"] == 0


@pytest.mark.parametrize("store_states", [False, True])
def test_the_domain_report_of_a_batch_in_blocks_equals_the_whole_batch_report(store_states, monkeypatch):
    """estimate_domain evaluates a batch in blocks of runs (cache-sized); whatever the block size, the report is the
    one the whole batch gives in one call: counters, SOC range, guards and key order. Randomised: batches that run
    past empty or full on some runs (clamps, pinned samples, held OCV, implausible voltages), block sizes that do
    and do not divide the runs."""
    import socbench.domain as dom

    rng = np.random.default_rng(17)
    for _ in range(6):
        name = rng.choice(["thevenin", "dp", "shepherd", "esc"])
        m = make_model(name, paper_params(name))
        R, T = int(rng.integers(3, 12)), int(rng.integers(40, 200))
        dt = float(rng.choice([1.0, 10.0, 30.0]))
        t = np.arange(T) * dt
        # each run moves 0.3–1.8 capacities of charge, discharging or charging: many go past empty or full
        sign = rng.choice([-1.0, 1.0, 1.0], size=(R, 1))
        i = sign * rng.uniform(0.3, 1.8, (R, 1)) * 3600.0 * m.capacity_ah / (T * dt) * rng.uniform(0.5, 1.5, (R, T))
        v = m.ocv.voltage[-1] * rng.uniform(0.8, 1.1, (R, T))
        prof = Profile(t, i, voltage_v=v, meta=ProfileMeta(name="blocks", capacity_ah=m.capacity_ah))
        est = make_estimator("coulomb", m, store_states=bool(store_states)).run(
            prof, soc0=rng.uniform(0.0, 1.0, R), segments=False)
        monkeypatch.setattr(dom, "DOMAIN_BLOCK", 1 << 40)
        whole = dom.estimate_domain(m, est, prof)
        assert whole["soc_clamped"] > 0 and whole["outside"] > 0, whole
        for rows in (1, 2, int(rng.integers(3, R + 1))):
            monkeypatch.setattr(dom, "DOMAIN_BLOCK", rows * T)
            blocks = dom.estimate_domain(m, est, prof)
            assert blocks == whole
            assert list(blocks) == list(whole)
            assert list(blocks["guards"]) == list(whole["guards"])
