"""The estimators SOC papers compare (aekf, ckf, srukf, hinf, dual): batched engines against their references,
SRUKF ≡ UKF when well conditioned and finite where the UKF needs repair, convergence from a 20-point error (synthetic
and the measured Panasonic record), joint capacity tracking on an aged cell, noise adaptation under sensor faults,
pick-up by the leaderboard."""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from socbench.estimators import SensorNoise, make_estimator, make_reference
from socbench.estimators.scoring import score
from socbench.models import make_model, paper_params
from socbench.models.params import Polynomial
from socbench.profile import Profile, ProfileMeta

from .test_estimators import FIELDS, NOISE, _model, _p0, _realize

NEW = ("aekf", "ckf", "srukf", "hinf", "dual")


# ----------------------------------------------------------------------------------------------- references
@pytest.mark.parametrize("model_name", ["thevenin", "dp", "esc"])
@pytest.mark.parametrize("name", NEW)
def test_batched_equals_reference(name, model_name):
    m = _model(model_name)
    p = _realize(m, 80, 3, seed=5)
    soc0 = np.array([0.7, 0.8, 0.95])
    batched = make_estimator(name, m, NOISE, store_states=True).run(p, soc0=soc0, P0=_p0(m, 0.1))
    ref = make_reference(name, m, NOISE, store_states=True).run(p, soc0=soc0, P0=_p0(m, 0.1))
    for f in FIELDS + ("x", "P_diag"):
        np.testing.assert_allclose(getattr(batched, f), getattr(ref, f), rtol=0, atol=1e-9, err_msg=f)
    np.testing.assert_array_equal(batched.gated, ref.gated)
    np.testing.assert_array_equal(batched.clamped, ref.clamped)
    assert not batched.failed.any()
    assert np.ptp(batched.innovation[:, 60]) > 1e-3  # three different runs, not one compared thrice
    if name == "dual":
        for key in ("capacity_ah", "capacity_ah_3sigma", "r0_ohm", "r0_ohm_3sigma"):
            np.testing.assert_allclose(batched.info[key], ref.info[key], rtol=1e-9, err_msg=key)


@pytest.mark.parametrize("name, like", [("aekf", "ekf"), ("hinf", "ekf"), ("ckf", "ukf")])
def test_new_filters_are_not_their_parents(name, like):
    """The references check the algebra; this checks that the filter does something of its own on this case."""
    m = _model("thevenin")
    p = _realize(m, 300, 3, noise=SensorNoise(voltage_sd=0.01, current_sd=0.2))
    # hinf at θ = 1e3 per SOC²: its default 1e2 is chosen for the recipe's error states, with which θ = 1e3 runs away
    # (hinf module docstring); on this sensor-noise case 1e2 stays within 2e-6 of the EKF's band
    options = {"theta": 1e3} if name == "hinf" else {}
    a = make_estimator(name, m, NOISE, **options).run(p, soc0=0.7, P0=_p0(m, 0.1))
    b = make_estimator(like, m, NOISE).run(p, soc0=0.7, P0=_p0(m, 0.1))
    assert np.abs(a.soc_std - b.soc_std).max() > 1e-5


def test_hinf_theta_zero_is_the_ekf_and_theta_is_capped_where_infeasible():
    m = _model("dp")
    p = _realize(m, 200, 3)
    ekf = make_estimator("ekf", m, NOISE).run(p, soc0=0.7, P0=_p0(m, 0.1))
    h0 = make_estimator("hinf", m, NOISE, theta=0.0).run(p, soc0=0.7, P0=_p0(m, 0.1))
    for f in FIELDS:
        np.testing.assert_allclose(getattr(h0, f), getattr(ekf, f), rtol=0, atol=1e-12, err_msg=f)
    big = make_estimator("hinf", m, NOISE, theta=1e7).run(p, soc0=0.7, P0=_p0(m, 0.1))
    assert big.info["theta_capped"].min() > 0  # θ = 1e7 per SOC² is beyond the Riccati bound: capped
    assert np.all(np.isfinite(big.soc)) and not big.failed.any()
    # with the margin ρ = 0.5 the H∞ Riccati matrix never exceeds twice the Kalman one on the SOC
    assert np.all(big.soc_std[:, 0] ** 2 <= 2.0 * ekf.soc_std[:, 0] ** 2 * (1 + 1e-9))


def test_the_hinf_prior_cap_leaves_no_soc_wider_than_its_prior():
    """``hinf_posterior`` with the priors' SOC variances: ``P⁺_zz ≤ P⁻_zz`` on random Kalman posteriors, θ_k within
    both older caps, and θ_k = 0 where the update brought no information on the SOC (``P_K = P⁻``)."""
    from socbench.estimators.hinf import hinf_posterior

    rng = np.random.default_rng(4)
    for _ in range(100):
        R, n = 40, int(rng.integers(1, 5))
        A = rng.normal(size=(R, n, n))
        PK = A @ np.swapaxes(A, 1, 2) * 10.0 ** rng.uniform(-8, -1) + 1e-12 * np.eye(n)
        prior = PK[:, 0, 0] * rng.choice([1.0, 1.0 + 1e-3, 2.0, 1e3], R)
        theta, margin = 10.0 ** rng.uniform(0, 7), rng.uniform(0.1, 0.9)
        P, th = hinf_posterior(PK, theta, margin, prior)
        assert np.all(P[:, 0, 0] <= prior * (1.0 + 1e-9))
        assert np.all(th <= np.minimum(theta, margin / PK[:, 0, 0]) * (1.0 + 1e-12)) and np.all(th >= 0.0)
        np.testing.assert_array_equal(th[prior == PK[:, 0, 0]], 0.0)
        _, old = hinf_posterior(PK, theta, margin)
        assert np.any(th < old)  # the cap binds on some of the draws


def test_hinf_keeps_the_soc_on_fast_records_with_the_prior_cap():
    """Ten random draws of benchmarks/hinf_fast_records.py (the paper's DP, PNGV or GNL pack, 0.1–1 s samples, 30 min
    of random steps, 5–30 mV voltage noise, the filter 5–20 points off with SD 0.1): with the prior cap the second
    half's SOC RMSE is above 2 % in at most one (measured over 60 draws, ``--draws 30 --seed 2`` and ``--seed 3``:
    none; the EKF none), without it in three or more (measured: 31 of 60). Without the cap, each update where
    ``θ P_K,zz`` passes the margin doubles the SOC's Riccati term, and at a fast rate one sample's information does not
    undo that: the gain grows and the estimate is thrown about."""
    from benchmarks.hinf_fast_records import draw, second_half_rmse

    rng = np.random.default_rng(61)
    on, off = [], []
    for _ in range(10):
        m, p, z, noise, s0 = draw(rng)
        for cap, out in ((True, on), (False, off)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                e = make_estimator("hinf", m, noise, soc0_sd=0.1, prior_cap=cap).run(p, soc0=s0, segments=False)
            out.append(second_half_rmse(e, z))
    assert sum(r > 0.02 for r in on) <= 1, np.round(on, 4)
    assert sum(r > 0.02 for r in off) >= 3, np.round(off, 4)


# ----------------------------------------------------------------------------------------------- square root
@pytest.mark.parametrize("model_name", ["thevenin", "dp", "pngv", "esc"])
def test_srukf_equals_ukf_when_well_conditioned(model_name):
    m = _model(model_name)
    p = _realize(m, 300, 4, seed=3)
    soc0 = np.array([0.6, 0.75, 0.85, 0.95])
    ukf = make_estimator("ukf", m, NOISE, store_states=True).run(p, soc0=soc0, P0=_p0(m, 0.1))
    sr = make_estimator("srukf", m, NOISE, store_states=True).run(p, soc0=soc0, P0=_p0(m, 0.1))
    for f in FIELDS + ("x", "P_diag"):
        np.testing.assert_allclose(sr.x if f == "x" else getattr(sr, f), getattr(ukf, f), rtol=0, atol=1e-9,
                                   err_msg=f)


def test_srukf_stays_finite_where_the_ukf_needs_psd_repair():
    """A 1 µV voltage sensor on a 20 V pack and a 30-point SOC prior: each update shrinks the SOC variance by ~10 orders
    of magnitude, ``P − K S Kᵀ`` cancels catastrophically and the UKF's covariance loses definiteness (repaired);
    the square-root filter's factor never needs it."""
    m = _model("dp")
    noise = SensorNoise(voltage_sd=1e-6, current_sd=1e-4)
    p = _realize(m, 300, 4, noise=noise)
    ukf = make_estimator("ukf", m, noise, store_states=True).run(p, soc0=0.6, P0=_p0(m, 0.3))
    sr = make_estimator("srukf", m, noise, store_states=True).run(p, soc0=0.6, P0=_p0(m, 0.3))
    assert ukf.info["psd_repairs"].min() > 100  # the UKF needed the repair on most steps of every run
    assert sr.info["psd_repairs"].sum() == 0 and sr.info["downdate_floors"].sum() == 0
    assert not sr.failed.any()
    for f in FIELDS + ("x", "P_diag"):
        assert np.all(np.isfinite(getattr(sr, f))), f
    assert np.all(sr.P_diag > 0)
    err = np.abs(sr.soc - p.soc_ref)
    assert err[:, 100:].max() < 1e-5  # and it is as accurate as such a sensor allows
    assert err[:, 100:].max() < 10 * np.abs(ukf.soc - p.soc_ref)[:, 100:].max()


# ----------------------------------------------------------------------------------------------- convergence
@pytest.fixture(scope="module")
def matched():
    m = _model("thevenin")
    return m, _realize(m, 1200, 60)


@pytest.mark.parametrize("name", NEW)
def test_converges_from_a_20_point_error(matched, name):
    m, p = matched
    est = make_estimator(name, m, NOISE).run(p, soc0=0.7, P0=_p0(m))  # the truth starts at 0.9
    assert not est.failed.any()
    err = np.abs(est.soc - p.soc_ref)
    assert err[:, 600:].max() < 0.01  # every run within 1 % after 10 minutes
    s = score(est, p, skip_s=600.0)
    assert s["frac_within_3sigma"] > 0.9


def _short_us06(data_dir: Path):
    from socbench.datasets import load
    from socbench.identify import fit_model

    base = data_dir / "panasonic_18650pf" / "25degC"
    hppc = load(sorted(base.glob("*HPPC*.mat"))[0], "panasonic-mat")
    us06 = load(sorted(base.glob("*US06*.mat"))[0], "panasonic-mat")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = make_model("dp", fit_model("dp", hppc, mode="paper").params)
    return model, us06.slice(0, 6000)  # the first 10 minutes at 10 Hz


@pytest.fixture(scope="module")
def us06_head(data_dir):
    return _short_us06(data_dir)


@pytest.mark.parametrize("name", NEW)
def test_converges_on_the_measured_panasonic_drive_cycle(us06_head, name):
    """A measured 18650 record (Panasonic 25 °C US06, first 10 min), a model fitted on the same cell's HPPC, the
    filter started 20 points low: within 3 % from minute 5 on (the model's own voltage error is ~20 mV)."""
    model, p = us06_head
    z0 = float(p.soc_ref[0]) - 0.2
    est = make_estimator(name, model, SensorNoise(voltage_sd=0.01, current_sd=0.1, dt=0.1)).run(p, soc0=z0)
    err = np.abs(est.soc[0] - p.soc_ref)
    assert not est.failed.any()
    assert err[3000:].max() < 0.03


# ----------------------------------------------------------------------------------------------- joint estimation
def _aged_case(seed, runs=4, loss=0.15, r0_growth=0.2):
    fresh = paper_params("dp")
    vals = dict(fresh.values)
    vals["R0"] = Polynomial(np.asarray(fresh.values["R0"].coeffs) * (1 + r0_growth))
    aged = replace(fresh, capacity_ah=fresh.capacity_ah * (1 - loss), values=vals)
    rng = np.random.default_rng(seed)
    T = 5000
    cur = np.repeat(rng.uniform(-5.0, 35.0, T), rng.integers(5, 60, T))[:T]
    t = np.arange(T, dtype=float)
    sim = make_model("dp", aged).simulate(Profile(t, cur), soc0=0.95)
    T = int(np.argmax(sim.soc < 0.15)) if (sim.soc < 0.15).any() else T  # one discharge, 0.95 down to 0.15
    t, cur = t[:T], cur[:T]
    sim_soc, sim_v = sim.soc[:T], sim.voltage_v[:T]
    v = sim_v + 0.01 * rng.standard_normal((runs, T))
    i = cur + 0.2 * rng.standard_normal((runs, T))
    p = Profile(t, i, voltage_v=v, soc_ref=np.tile(sim_soc, (runs, 1)), meta=ProfileMeta(name="aged",
                                                                                         capacity_ah=22.0))
    return make_model("dp", fresh), aged, p


@pytest.mark.parametrize("seed, loss", [(0, 0.15), (1, 0.10), (3, 0.20)])
def test_dual_tracks_capacity_of_an_aged_cell_and_beats_the_ekf(seed, loss):
    m, aged, p = _aged_case(seed, loss=loss)
    assert p.soc_ref[0, -1] < 0.3  # one (nearly) full discharge
    dual = make_estimator("dual", m, NOISE).run(p, soc0=0.75)
    ekf = make_estimator("ekf", m, NOISE).run(p, soc0=0.75)
    cap = dual.info["capacity_ah"]
    assert np.all(np.abs(cap / aged.capacity_ah - 1.0) < 0.02), cap
    assert np.mean(np.abs(cap - aged.capacity_ah) <= dual.info["capacity_ah_3sigma"]) >= 0.75
    assert score(dual, p)["soc_rmse"] < score(ekf, p)["soc_rmse"]
    # R0 moved from the fresh model's value toward the aged one
    z = p.soc_ref[0, -1]
    r0_fresh, r0_aged = m.p("R0", z)[0], aged.values["R0"].value_and_deriv(z)[0]
    assert np.all(np.abs(dual.info["r0_ohm"] - r0_aged) < np.abs(dual.info["r0_ohm"] - r0_fresh))
    # the capacity path starts at the model's capacity and its 3σ shrinks as the discharge reveals it
    path, sd3 = dual.info["capacity_ah_path"], dual.info["capacity_ah_3sigma_path"]
    assert np.allclose(path[:, 0], 22.0, rtol=0.02) and np.all(sd3[:, -1] < 0.2 * sd3[:, 0])
    assert dual.x is None  # the parameter states are kept internally, not handed out unasked


def test_dual_accepts_a_full_size_p0_and_reports_its_state_names():
    m = _model("thevenin")
    p = _realize(m, 50, 2)
    est = make_estimator("dual", m, NOISE, store_states=True).run(p, soc0=0.8, P0=np.diag([0.01, 1e-6, 0.04, 1e-6]))
    assert est.state_names == ("z", "U1", "cap", "dR0")
    assert est.P_diag[0, 0, 2] == pytest.approx(0.04)  # the capacity variance the caller gave


# ----------------------------------------------------------------------------------------------- adaptation
@pytest.fixture(scope="module")
def fault_scenarios():
    from socbench.identify import fit_model
    from socbench.scenarios import load_scenario

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ch = load_scenario("flight-0kg").characterisation(0)
        model = make_model("dp", fit_model("dp", ch, mode="paper").params)
    out = {}
    for name in ("current-bias", "harsh"):
        scen = load_scenario(name)
        seeds = list(range(6))
        out[name] = (scen, scen.realize(seeds), scen.initial_soc(seeds))
    return model, out


@pytest.mark.parametrize("scenario", ["current-bias", "harsh"])
def test_aekf_nis_is_closer_to_one_than_the_ekf(fault_scenarios, scenario):
    model, cases = fault_scenarios
    scen, p, soc0 = cases[scenario]
    nis = {}
    for name in ("ekf", "aekf"):
        est = make_estimator(name, model, scen.sensor_noise()).run(p, soc0)
        assert not est.failed.any()
        nis[name] = score(est, p)["nis_mean"]
    assert nis["ekf"] > 2.0  # the faults make the EKF's innovations too large for its noise model
    assert abs(nis["aekf"] - 1.0) < abs(nis["ekf"] - 1.0)
    assert abs(nis["aekf"] - 1.0) < 1.0


# ----------------------------------------------------------------------------------------------- pick-up
def test_a_tiny_leaderboard_runs_every_registered_estimator(tmp_path, capsys):
    import pandas as pd

    from socbench.cli import main
    from socbench.estimators import estimator_names

    names = ",".join(estimator_names())
    rc = main(["leaderboard", "--models", "thevenin", "--estimators", names, "--scenarios", "flight-10kg",
               "--seeds", "2", "--backend", "serial", "--no-figures", "--out", str(tmp_path / "lb")])
    assert rc == 0, capsys.readouterr().err
    board = pd.read_csv(tmp_path / "lb" / "leaderboard.csv")
    assert sorted(board["estimator"]) == sorted(estimator_names())
    assert (board["failed_runs"] == 0).all()
    assert board["soc_rmse"].notna().all()
    assert (board.set_index("estimator").loc[list(NEW), "soc_rmse"] < 0.05).all()
