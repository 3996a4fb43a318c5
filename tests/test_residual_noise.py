"""The voltage noise the diagnosis reads off a record (socbench.diagnose.search.residual_noise) on time stamps that
jitter, as a logger's do (the Panasonic US06 files: 97 % of the sample triples unevenly spaced; CALCE: 96 %).

A generator of this file's own draws field records of the synthetic cell: discharge and charge steps of random
amplitude and length between rests, sampled at a nominal period of 0.1–10 s whose every interval is stretched by a
random ±0–5 %, with a few logging gaps of 5–60 s; the voltage is the cell's own (simulated on the jittered stamps)
plus white noise of 0.5–5 mV. The model the noise is read with is the cell with its resistances 30 % off (the
diagnosis reads the noise on a base model's residual, never the truth's).
"""

from __future__ import annotations

import numpy as np
import pytest

from socbench.diagnose.search import interpolation_deviation, residual_noise, robust_sd
from socbench.diagnose.synthetic import cell
from socbench.models import Constant, ModelParams, make_model
from socbench.profile import Profile

DRAWS = 20


def jittered_record(seed: int):
    """``(truth model, misfitted model, profile, σ)``: one draw of the module docstring."""
    rng = np.random.default_rng([seed, 13])
    name, params = cell("thevenin")
    q = params.capacity_ah
    dt = float(np.exp(rng.uniform(np.log(0.1), np.log(10.0))))
    levels, span = [], 0.0
    while span < 4 * 3600.0:
        seconds = float(rng.uniform(120.0, 900.0))
        levels.append((float(rng.choice([0.0, rng.uniform(0.3, 2.0) * q, -rng.uniform(0.2, 1.0) * q])), seconds))
        span += seconds
    n = int(span / dt)
    step = dt * (1.0 + rng.uniform(-1.0, 1.0, n) * rng.uniform(0.0, 0.05))
    for k in rng.choice(n, 3, replace=False):
        step[k] += rng.uniform(5.0, 60.0)
    t = np.concatenate([[0.0], np.cumsum(step)])
    edges = np.cumsum([s for _, s in levels])
    current = np.array([a for a, _ in levels])[np.minimum(np.searchsorted(edges, t, side="right"), len(levels) - 1)]
    truth = make_model(name, params)
    sigma = float(rng.uniform(0.0005, 0.005))
    v = truth.simulate(Profile(t, current), soc0=0.8).voltage_v + rng.normal(0.0, sigma, t.size)
    off = {k: Constant(c.value * (1.3 if k.startswith("R") else 1.0)) for k, c in params.values.items()}
    misfit = make_model(name, ModelParams(q, params.ocv, off))
    return truth, misfit, Profile(t, current, voltage_v=v), sigma


def test_deviation_from_the_neighbours_line_is_the_second_difference_on_a_uniform_grid():
    rng = np.random.default_rng(5)
    e = rng.normal(size=500)
    d = interpolation_deviation(np.arange(500.0) * 0.7, e)
    np.testing.assert_allclose(d, -(e[2:] - 2 * e[1:-1] + e[:-2]) / np.sqrt(6.0), rtol=0, atol=1e-12)
    t = np.cumsum(rng.uniform(0.1, 3.0, 500))
    assert np.max(np.abs(interpolation_deviation(t, 2.0 + 0.5 * t))) < 1e-9  # a line leaves nothing


@pytest.mark.parametrize("seed", range(DRAWS))
def test_noise_read_on_jittered_stamps(seed):
    truth, misfit, p, sigma = jittered_record(seed)
    got = residual_noise(misfit, [p], soc0s=[0.8])
    assert got == pytest.approx(sigma, rel=0.15), (got, sigma)
    # the deviations are white noise of sd σ: their plain and robust sd agree on the truth's residual
    d = interpolation_deviation(p.time_s, p.voltage_v - truth.simulate(p, soc0=0.8).voltage_v)
    assert robust_sd(d) == pytest.approx(sigma, rel=0.1) and np.std(d) == pytest.approx(sigma, rel=0.1)


@pytest.mark.parametrize("seed", range(8))
def test_noise_read_on_a_voltage_in_adc_steps_larger_than_the_noise(seed):
    """The same records read in ADC steps of 2–6 σ: the deviations lie on a lattice and their median deviation jumps
    with it (0.6 q, or 0). The noise read is the reading's error: at least the rounding's q/√12, and the white noise
    and the rounding together within 25 % (the plain sd of the bulk also takes up the misfitted model's error at the
    current's steps: up to +18 % on these draws, where the truth's own residual gives 0.95–1.06 ×)."""
    truth, misfit, p, sigma = jittered_record(100 + seed)
    q = float(np.random.default_rng(seed).uniform(2.0, 6.0)) * sigma
    read = Profile(p.time_s, p.current_a, voltage_v=q * np.round(p.voltage_v / q))
    got = residual_noise(misfit, [read], soc0s=[0.8])
    assert q / np.sqrt(12.0) * 0.999 <= got <= 1.25 * np.hypot(sigma, q / np.sqrt(12.0)), (got, sigma, q)
