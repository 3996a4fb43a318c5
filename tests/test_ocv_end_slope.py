"""The OCV curve's linear extension past its last rest point is never flatter than its end segment (socbench.ocv).

PCHIP's end derivative is set to 0 where the two end secants differ enough to overshoot: the top of a flat LFP curve
read by a part-charged HPPC. Extended with that slope, every SOC past the last rest point reads one voltage, and a
filter whose estimate goes there cannot be told where it is. The records here are drawn independently of the fit code:
an LFP-like truth (plateau, step near 60 %, rise to full) read at rest points spaced 10–20 % from a top of 0.80–0.92,
the cell charged a little past that top, discharged at 1–3C to 20 %; the filter model has the truth's own resistances
(a lookup fit's 4 % dip of R0 across the range in the second test) and its OCV only at the rest points.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator

from socbench.estimators import SensorNoise, make_estimator
from socbench.models import make_model
from socbench.models.params import ModelParams
from socbench.ocv import OCVCurve
from socbench.profile import Profile, ProfileMeta


def _lfp(z):
    return (3.20 + 0.06 * z + 0.03 * np.tanh((z - 0.62) / 0.04) - 0.25 * np.exp(-z / 0.03)
            + 0.25 * np.exp((z - 1.0) / 0.025))


def test_end_slopes_are_the_interpolants_unless_flatter_than_the_end_segment():
    rng = np.random.default_rng(2054)
    flattened = 0
    for _ in range(200):
        k = int(rng.integers(3, 12))
        z = np.sort(rng.uniform(0.0, 1.0, k))
        if np.min(np.diff(z)) < 1e-3:
            continue
        v = 3.0 + np.cumsum(rng.uniform(0.0, 0.2, k) ** rng.uniform(1.0, 4.0))
        ocv = OCVCurve(z, v)
        d = PchipInterpolator(z, v).derivative()
        secant = np.diff(v) / np.diff(z)
        ends = ((z[0], ocv.slope(z[0] - 1e-6), secant[0]), (z[-1], ocv.slope(z[-1] + 1e-6), secant[-1]))
        for end, inner, sec in ends:
            assert inner == pytest.approx(max(float(d(end)), sec), rel=1e-12, abs=1e-12)
            flattened += float(d(end)) < sec - 1e-9
    assert flattened >= 50  # the rule acts on a good share of these curves (measured: 153 of their 382 ends)


def _flat_top_record(rng, lookup_dip: bool):
    q = rng.uniform(1.0, 30.0)
    r0, r1, tau = rng.uniform(0.01, 0.03) * 2.5 / q, rng.uniform(0.005, 0.02) * 2.5 / q, rng.uniform(10.0, 60.0)
    zs = np.linspace(0.0, 1.0, 201)
    vals = {"R0": {"const": r0}, "R1": {"const": r1}, "C1": {"const": tau / r1}}
    truth = make_model("thevenin", ModelParams(q, OCVCurve(zs, _lfp(zs)), vals))
    top, step = rng.uniform(0.80, 0.92), rng.uniform(0.1, 0.2)
    points = np.arange(top, 0.1, -step)[::-1]
    if lookup_dip:
        dip = {"soc": list(np.sort([points[0], top - 0.2, top])), "value": [r0, 0.96 * r0, r0]}
        vals = dict(vals, R0={"lookup": dip})
    model = make_model("thevenin", ModelParams(q, OCVCurve(points, _lfp(points)), vals))
    z0 = min(top + rng.uniform(0.0, 0.06), 0.99)
    dt = float(rng.choice([0.5, 1.0, 2.0, 5.0]))
    rest = np.zeros(int(600 / dt))
    c = rng.uniform(1.0, 3.0) * q
    n = int((z0 - 0.2) * 3600 * q / (c * dt))
    i = np.r_[rest, c * (1 + 0.3 * np.sin(np.arange(n) * dt / 30.0)), rest]
    t = np.arange(i.size) * dt
    sim = truth.simulate(Profile(t, i, meta=ProfileMeta(name="flat-top", capacity_ah=q)), soc0=z0)
    v = sim.voltage_v + rng.normal(0.0, 0.002, i.size)
    i_meas = i + rng.normal(0.0, 0.003 * q, i.size)
    meas = Profile(t, i_meas, voltage_v=v, meta=ProfileMeta(name="flat-top", capacity_ah=q))
    return model, meas, sim.soc


def _soc_errors(lookup_dip: bool, pchip_ends: bool, draws: int = 30):
    rng = np.random.default_rng(77)
    errors = {"ekf": [], "ukf": []}
    for _ in range(draws):
        model, meas, z_true = _flat_top_record(rng, lookup_dip)
        if pchip_ends:  # the extension before: PCHIP's own end derivatives
            c = model.params.ocv
            d = PchipInterpolator(c.soc, c.voltage).derivative()
            object.__setattr__(c, "_slope_lo", float(d(c.soc[0])))
            object.__setattr__(c, "_slope_hi", float(d(c.soc[-1])))
        soc0 = float(model.ocv.inverse(meas.voltage_v[0]))  # read off the first rest, as a user would
        for name in errors:
            est = make_estimator(name, model, SensorNoise(voltage_sd=0.003, current_sd=0.01 * model.capacity_ah))
            errors[name].append(float(np.sqrt(np.mean((est.run(meas, soc0=soc0).soc[0] - z_true) ** 2))))
    return {k: np.array(v) for k, v in errors.items()}


#: SOC RMSE above 5 points in at most this many of the 30 draws, for each filter
MISSES = 5


@pytest.mark.parametrize("lookup_dip", [False, True])
def test_filters_find_a_cell_charged_past_the_top_rest_point_of_a_flat_curve(lookup_dip):
    """EKF and UKF SOC RMSE above 5 points in at most 5 of 30 draws each (measured: EKF 0 and 0, UKF 1 and 4, without
    and with the dip; the UKF's misses with the dip are the dip's own error: 4 % of R0 at 3C is some 6 mV, ten points
    of SOC on a plateau of 0.06 V per unit). With PCHIP's own end derivatives (the extension before) the same draws
    miss more than that: the UKF in 7 with constant resistances, with the dip the EKF in 16 (its 90th percentile at
    49 points) and the UKF in 9."""
    now = _soc_errors(lookup_dip, pchip_ends=False)
    before = _soc_errors(lookup_dip, pchip_ends=True)
    for name in ("ekf", "ukf"):
        assert np.count_nonzero(now[name] > 0.05) <= MISSES, (name, np.round(now[name], 3))
    assert any(np.count_nonzero(before[k] > 0.05) > MISSES for k in before)
