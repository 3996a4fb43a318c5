"""The iterated EKF (socbench.estimators.iekf): one iteration is the EKF; iterated, one update reaches the maximum a
posteriori state of the prior and the sample (Gauss–Newton), where the EKF's single step stops short on a bent OCV;
numpy only, with the reason given."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from socbench.errors import ConfigError
from socbench.estimators import SensorNoise, make_estimator
from socbench.models import make_model, paper_params
from socbench.profile import Profile, ProfileMeta


def _record(model, T=400, R=3, seed=4):
    rng = np.random.default_rng(seed)
    cur = np.repeat(rng.uniform(-10.0, 40.0, size=T), rng.integers(5, 30, size=T))[:T]
    t = np.arange(T, dtype=float)
    sim = model.simulate(Profile(t, cur), soc0=0.9)
    v = sim.voltage_v + 0.01 * rng.standard_normal((R, T))
    return Profile(t, cur + 0.2 * rng.standard_normal((R, T)), voltage_v=v, soc_ref=np.tile(sim.soc, (R, 1)),
                   meta=ProfileMeta(name="iekf", capacity_ah=model.capacity_ah))


def test_one_iteration_is_the_ekf():
    model = make_model("dp", paper_params("dp"))
    p = _record(model)
    noise = SensorNoise(voltage_sd=0.01, current_sd=0.2)
    a = make_estimator("ekf", model, noise, engine="numpy").run(p, soc0=0.6)
    b = make_estimator("iekf", model, noise, iterations=1).run(p, soc0=0.6)
    np.testing.assert_array_equal(a.soc, b.soc)
    np.testing.assert_array_equal(a.soc_std, b.soc_std)
    assert b.info["engine"] == "numpy" and "measurement_update" in b.info["engine_note"]


@pytest.mark.parametrize("z_true,z_prior", [(0.98, 0.78), (0.15, 0.35), (0.05, 0.30)])
def test_the_iterated_update_reaches_the_map_where_the_ekf_stops_short(z_true, z_prior):
    """One sample at rest (I = 0, so y = OCV(z)) on the one-state rint model: the posterior mean of a Gaussian prior
    and the sample is the minimiser of (z − z⁻)²/P + (v − OCV(z))²/σ²; the EKF takes one linearised step toward it."""
    model = make_model("rint", paper_params("rint"))
    sd, p0 = 0.005, 0.1 ** 2
    noise = SensorNoise(voltage_sd=sd, current_sd=1e-9)
    v = float(model.ocv(z_true))
    x, P = np.array([[z_prior]]), np.array([[[p0]]])

    def update(name):
        est = make_estimator(name, model, noise, iterations=50) if name == "iekf" else make_estimator(name, model,
                                                                                                        noise)
        y, H, D = model.output(x, np.zeros(1), None, jac=True)
        Rk = est.noise.R(D, (1,))
        S = np.einsum("ri,rij,rj->r", H, P, H) + Rk
        e = v - y
        return est.measurement_update(x, P, H, Rk, S, e, np.zeros(1, bool), np.array([v]), np.zeros(1), None)[0]

    def cost(z):
        return (z - z_prior) ** 2 / p0 + (v - float(model.ocv(z))) ** 2 / sd ** 2

    z_map = minimize_scalar(cost, bounds=(0.0, 1.0), method="bounded", options={"xatol": 1e-12}).x
    z_ekf, z_iekf = float(update("ekf")[0, 0]), float(update("iekf")[0, 0])
    assert abs(z_iekf - z_map) < 1e-6, (z_iekf, z_map)
    assert abs(z_ekf - z_map) > 1e-3, (z_ekf, z_map)  # the case is one the single step gets wrong


def test_options_are_checked():
    model = make_model("rint", paper_params("rint"))
    for bad in ({"iterations": 0}, {"iterations": 2.5}, {"iteration_tol": -1.0}):
        with pytest.raises(ConfigError):
            make_estimator("iekf", model, **bad)
