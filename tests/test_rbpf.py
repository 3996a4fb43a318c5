"""The Rao–Blackwellised particle filter (socbench.estimators.rbpf).

Two behaviours: on a record its model describes exactly, it is the Kalman filter's answer (particles on the SOC, the
other states in closed form); with a known model error planted in the voltage (the noise recipe's calibration records of
``tests/test_model_error.py``: a Gauss–Markov error of random size and correlation time, a wrong resistance, white
noise), it carries the recipe's coloured states and its ±3σ band holds the truth 90–100 % of the time, where a
bootstrap PF that weighs its particles as if the error were white (the recipe's inflated form without
``SensorNoise.weight_extra_var``) does not.
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
from socbench.profile import Profile

from .test_model_error import calibration_case


@pytest.mark.parametrize("cfg", [1, 3])  # an ordinary error, and one more persistent than the record
def test_rbpf_band_holds_the_truth_with_a_known_model_error(cfg):
    model, err, stats, test, sensor, guess = calibration_case(np.random.default_rng(200 + cfg), cfg, 16)
    covered = {}
    for name, form in (("rbpf", "states"), ("pf", "inflated")):
        m, n = recipe.apply(model, sensor, stats, test, noise="model", form=form)
        if name == "pf":
            n = replace(n, weight_extra_var=0.0)  # white weights
        s = score(make_estimator(name, m, n, soc0_sd=0.05, n_particles=100).run(test, soc0=guess, seed=4), test)
        assert s["failed_runs"] == 0
        covered[name] = s["frac_within_3sigma"]
        if name == "rbpf":
            assert 0.9 <= covered[name] <= 1.0, (err, covered)
            assert np.mean(s["runs"]["frac_within_3sigma"] >= 0.8) >= 0.85  # not a few perfect draws hiding bad ones
            assert 0.2 < s["nis_mean"] < 3.0
    assert covered["pf"] < 0.9  # white weights on the same draws: overconfident, so the test can fail


def test_rbpf_gives_the_kalman_answer_on_a_record_its_model_describes():
    """dp truth, the filter's model exact, white sensor noise: the two solve the same problem (the OCV is nearly linear
    over the posterior's width), so the RBPF's SOC lies within the EKF's own 1σ of the EKF's, with a like SD and a like
    error. (Not to zero: the RBPF carries the current noise that drives the SOC and the RC states jointly per particle,
    the EKF through a Gaussian Q and R that leave out their correlation; measured at 200–4000 particles, the median gap
    is 0.55–0.65 σ and does not shrink with N.)"""
    rng = np.random.default_rng(12)
    m = make_model("dp", paper_params("dp"))
    q = m.capacity_ah
    t = np.arange(3000.0)
    i = np.repeat(rng.uniform(-0.2, 1.0, 60) * q, 50)
    sim = m.simulate(Profile(t, i), soc0=0.9)
    R = 4
    noise = SensorNoise(voltage_sd=0.004, current_sd=0.01 * q)
    v = sim.voltage_v + rng.normal(0.0, 0.004, (R, t.size))
    cur = i + rng.normal(0.0, 0.01 * q, (R, t.size))
    prof = Profile(t, cur, voltage_v=v, soc_ref=sim.soc)
    ekf = make_estimator("ekf", m, noise, soc0_sd=0.05).run(prof, soc0=0.85)
    rb = make_estimator("rbpf", m, noise, soc0_sd=0.05, n_particles=400).run(prof, soc0=0.85, seed=2)
    late = slice(300, None)  # after both have converged from the 5-point start
    gap = np.abs(rb.soc[:, late] - ekf.soc[:, late]) / ekf.soc_std[:, late]
    assert np.median(gap) < 1.0, np.median(gap)
    ratio = rb.soc_std[:, late] / ekf.soc_std[:, late]
    assert 0.6 < np.median(ratio) < 1.6, np.median(ratio)
    # and it is a filter, not a counter: from the 5-point start it converges like the EKF
    assert np.sqrt(np.mean((rb.soc[:, late] - sim.soc[late]) ** 2)) < 1.5 * np.sqrt(
        np.mean((ekf.soc[:, late] - sim.soc[late]) ** 2))


def test_rbpf_is_reproducible_and_checks_its_options():
    m = make_model("thevenin", paper_params("thevenin"))
    t = np.arange(200.0)
    sim = m.simulate(Profile(t, np.full(t.size, 10.0)), soc0=0.8)
    prof = Profile(t, np.full(t.size, 10.0), voltage_v=sim.voltage_v, soc_ref=sim.soc)
    a = make_estimator("rbpf", m, n_particles=64).run(prof, soc0=0.7, seed=9)
    b = make_estimator("rbpf", m, n_particles=64).run(prof, soc0=0.7, seed=9)
    np.testing.assert_array_equal(a.soc, b.soc)
    assert a.info["engine"] == "numpy" and a.info["engine_note"]
    for bad in ({"n_particles": 1}, {"kernel_h": 1.0}, {"resample_threshold": 2.0}):
        with pytest.raises(ConfigError, match="rbpf"):
            make_estimator("rbpf", m, **bad)
