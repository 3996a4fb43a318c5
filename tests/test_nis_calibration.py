"""NIS calibration of the noise recipe (socbench.estimators.nis_calibration).

On the planted-error draws of tests/test_model_error.py (a known model error: Gauss–Markov, a wrong resistance, white
noise; randomised around four configurations), the recipe is measured on validation draws and then deliberately
mis-sized (its variances × 2.5 or × 1/2.5, whichever takes its NIS further from 1: what a recipe pooled over records of
other kinds does). Calibrated on further
validation draws, the filter's NIS mean on fresh draws must come back within a factor 1.5 of 1 — and without the
calibration it must not be (so the test can fail).
"""

from __future__ import annotations

import numpy as np
import pytest

from socbench.errors import ConfigError
from socbench.estimators import make_estimator, nis_calibration
from socbench.estimators import model_error as recipe
from socbench.estimators.scoring import score
from tests.test_model_error import _draws, calibration_case


def _nis(model, sensor, stats, test, form="states") -> float:
    m, n = recipe.apply(model, sensor, stats, test, form=form)
    s = score(make_estimator("ekf", m, n, soc0_sd=0.02).run(test, soc0=test.soc_ref[:, 0]), test)
    assert s["failed_runs"] == 0
    return float(s["nis_mean"])


@pytest.mark.parametrize("cfg", range(4))
def test_calibration_brings_a_mis_sized_recipe_back_to_nis_one(cfg):
    rng = np.random.default_rng(900 + cfg)
    model, err, stats, test, sensor, _ = calibration_case(rng, cfg, 12, "validation")
    # mis-sized away from consistency: ×2.5 where the recipe as measured is already cautious, ×1/2.5 where not
    factor = 2.5 if _nis(model, sensor, stats, test) < 1.0 else 1.0 / 2.5
    wrong = stats.scaled(factor)
    calib = _draws(model, rng, 6, err)
    fixed = nis_calibration.calibrate(model, sensor, wrong, [calib.run(r) for r in range(calib.n_runs)])
    alpha = fixed.scale_for("states")
    assert fixed.scale_for("inflated") == 1.0  # one form calibrated at a time
    before, after = _nis(model, sensor, wrong, test), _nis(model, sensor, fixed, test)
    assert not 1 / 1.5 <= before <= 1.5, (factor, before)  # mis-sized: the test can fail
    assert 1 / 1.5 <= after <= 1.5, (factor, alpha, before, after)
    assert (alpha - 1.0) * (factor - 1.0) < 0  # it undoes the mis-sizing, not something else


def test_calibration_needs_validation_records_and_stays_within_its_bounds():
    rng = np.random.default_rng(950)
    model, err, stats, test, sensor, _ = calibration_case(rng, 0, 4, "identification")
    calib = _draws(model, rng, 3, err)
    records = [calib.run(r) for r in range(calib.n_runs)]
    assert nis_calibration.calibrate(model, sensor, stats, records) is stats  # measured in sample: left alone
    val = recipe.ModelErrorStats.from_dict({**stats.to_dict(), "measured_on": "validation"})
    assert nis_calibration.calibrate(model, sensor, val, []) is val
    far = nis_calibration.calibrate(model, sensor, val.scaled(100.0), records)  # 100× too large: NIS ≪ 1
    assert far.scale_for("states") == pytest.approx(nis_calibration.ALPHA_MIN)


def test_the_factor_scales_every_model_error_variance_and_survives_json():
    rng = np.random.default_rng(960)
    model, err, stats, test, sensor, _ = calibration_case(rng, 1, 2, "validation")
    sensor = sensor.__class__(voltage_sd=1e-6, current_sd=sensor.current_sd)  # no floor from the sensor
    scaled = stats.with_nis_scale("states", 4.0).with_nis_scale("inflated", 0.25)
    m1, n1 = recipe.apply(model, sensor, stats, test)
    m4, n4 = recipe.apply(model, sensor, scaled, test)
    e1, e4 = m1.effects[-1].values, m4.effects[-1].values
    for key in ("sd_slow", "sd_fast", "sd_r"):
        np.testing.assert_allclose(np.asarray(e4[key]), 2.0 * np.asarray(e1[key]), rtol=1e-12)
    assert n4.voltage_sd == pytest.approx(2.0 * n1.voltage_sd, rel=1e-12)
    _, i1 = recipe.apply(model, sensor, stats, test, form="inflated")
    _, i4 = recipe.apply(model, sensor, scaled, test, form="inflated")
    assert i4.voltage_sd == pytest.approx(0.5 * i1.voltage_sd, rel=1e-12)
    back = recipe.ModelErrorStats.from_dict(scaled.to_dict())
    assert back.scale_for("states") == 4.0 and back.scale_for("inflated") == 0.25
    with pytest.raises(ConfigError, match="nis_scale"):
        recipe.ModelErrorStats.from_dict({**stats.to_dict(), "nis_scale": {"states": -1.0}})
    with pytest.raises(ConfigError, match="nis_scale"):
        recipe.ModelErrorStats.from_dict({**stats.to_dict(), "nis_scale": {"bands": 2.0}})


def test_a_shrinking_factor_applies_only_at_the_calibration_records_temperatures():
    """Calibrated below 1 on records at 25 °C, the factor applies to a record at 25 °C and not to one at 0 °C (the
    error met there is not the one measured); a factor above 1 applies everywhere."""
    rng = np.random.default_rng(970)
    model, err, stats, test, sensor, _ = calibration_case(rng, 0, 2, "validation")
    warm = test.with_(temperature_c=np.full(test.n, 25.0))
    cold = test.with_(temperature_c=np.full(test.n, 0.0))
    for alpha, at_cold in ((0.5, 1.0), (2.0, 2.0)):
        s = stats.with_nis_scale("states", alpha)
        assert recipe.nis_factor(s, "states", warm) == alpha
        assert recipe.nis_factor(s, "states", cold) == at_cold
        assert recipe.nis_factor(s, "inflated", warm) == 1.0
