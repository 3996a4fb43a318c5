"""The sensor model: reproducibility, declared statistics, onsets, combinations, quantisation, initial-SOC errors.

Statistical bounds are 5 standard errors (two-sided false-alarm probability ≈ 6e-7 per check): the SE of a sample mean
is σ/√N, of a sample SD about σ/√(2(N−1)), of a sample correlation of independent series about 1/√N.
"""

from __future__ import annotations

import numpy as np
import pytest

from socbench.errors import ConfigError
from socbench.scenarios import Channel, Fault, SensorSpec, load_scenario
from socbench.scenarios.sensors import apply_channel, initial_soc_guess

T = np.arange(2000.0)  # 1 s samples
TRUTH = 20.0 + 0.001 * T  # a slow ramp (V)
KEY = 12345


def measure(channel, seeds=(0,), truth=TRUTH, t=T):
    return apply_channel(truth, t, channel, list(seeds), KEY, 1)


def within_mean(x, mu, sd):
    return abs(np.mean(x) - mu) < 5 * sd / np.sqrt(np.size(x))


def within_sd(x, sd):
    n = np.size(x)
    return abs(np.std(x, ddof=1) - sd) < 5 * sd / np.sqrt(2 * (n - 1))


# ------------------------------------------------------------------------------------------------ seeds
def test_same_seeds_give_identical_data_and_different_seeds_independent_noise():
    ch = Channel(noise_sd=0.1, drift_sd=0.01)
    a, _ = measure(ch, seeds=(7, 8))
    b, _ = measure(ch, seeds=(7, 8))
    assert np.array_equal(a, b)
    # a run does not depend on which other runs share the batch
    c, _ = measure(ch, seeds=(8,))
    assert np.array_equal(a[1], c[0])
    e0 = np.diff(a[0] - TRUTH)  # white part of the error (differences remove the slow drift)
    e1 = np.diff(a[1] - TRUTH)
    r = np.corrcoef(e0, e1)[0, 1]
    assert abs(r) < 5 / np.sqrt(e0.size)


def test_scenario_realize_is_reproducible_and_batched():
    sc = load_scenario("nominal")
    p1 = sc.realize([3, 4, 5])
    p2 = sc.realize([5])
    assert p1.current_a.shape == p1.voltage_v.shape == p1.temperature_c.shape == p1.soc_ref.shape
    assert p1.n_runs == 3
    assert np.array_equal(p1.voltage_v[2], p2.voltage_v[0])
    assert np.array_equal(p1.current_a[2], p2.current_a[0])
    assert not np.array_equal(p1.voltage_v[0], p1.voltage_v[1])
    ev = p1.voltage_v - p1.meta.extra["truth"]["voltage_v"]
    r = np.corrcoef(ev[0], ev[1])[0, 1]
    assert abs(r) < 5 / np.sqrt(ev.shape[1])


# ------------------------------------------------------------------------------------------------ statistics
def test_white_noise_and_offset_have_the_declared_statistics():
    ch = Channel(noise_sd=0.2, offset=0.5)
    x, _ = measure(ch, seeds=range(5))
    err = (x - TRUTH).ravel()
    assert within_mean(err, 0.5, 0.2)
    assert within_sd(err, 0.2)


def test_scenario_noise_matches_its_file():
    # nominal: voltage noise 10 mV, offset 5 mV, 12-bit ADC over 30 V (LSB 7.3 mV -> adds LSB²/12 of variance)
    sc = load_scenario("nominal")
    p = sc.realize(range(4))
    err = (p.voltage_v - p.meta.extra["truth"]["voltage_v"]).ravel()
    lsb = 30.0 / 2**12
    sd = np.sqrt(0.01**2 + lsb**2 / 12)
    assert within_mean(err, 0.005, sd)
    assert within_sd(err, sd)
    assert sc.sensor_noise().voltage_sd == pytest.approx(sd)
    # temperature-sensor offset: 1.0 °C (noise 0.5 °C, 10-bit over 165 °C)
    et = (p.temperature_c - p.meta.extra["truth"]["temperature_c"]).ravel()
    assert within_mean(et, 1.0, np.sqrt(0.5**2 + (165 / 2**10) ** 2 / 12))


def test_random_walk_drift_variance_grows_linearly_after_onset():
    ch = Channel(faults=(Fault("drift", 0.05, onset_s=500.0),))
    x, _ = measure(ch, seeds=range(400), truth=np.zeros(T.size))
    assert np.all(x[:, :500] == 0.0)
    for k in (700, 1500):  # variance after tau seconds: sd² tau
        assert within_sd(x[:, k], 0.05 * np.sqrt(k - 500))


# ------------------------------------------------------------------------------------------------ onsets
@pytest.mark.parametrize("kind, value", [("offset", 0.3), ("gain", 0.02), ("noise", 0.1)])
def test_each_fault_acts_only_from_its_onset(kind, value):
    ch = Channel(faults=(Fault(kind, value, onset_s=600.0, end_s=1500.0),))
    x, _ = measure(ch, seeds=(1,))
    err = x[0] - TRUTH
    assert np.all(err[:600] == 0.0) and np.all(err[1500:] == 0.0)
    active = err[600:1500]
    if kind == "offset":
        assert np.allclose(active, 0.3)
    elif kind == "gain":
        assert np.allclose(active, 0.02 * TRUTH[600:1500])
    else:
        assert within_sd(active, 0.1) and within_mean(active, 0.0, 0.1)


def test_stuck_at_freezes_the_reading_from_onset():
    ch = Channel(noise_sd=0.01, faults=(Fault("stuck", None, onset_s=800.0, end_s=900.0),))
    x, _ = measure(ch, seeds=(2,))
    assert np.all(x[0, 800:900] == x[0, 800])
    assert np.unique(x[0, 700:800]).size == 100  # noisy before
    assert np.unique(x[0, 900:1000]).size == 100  # and after
    y, _ = measure(Channel(faults=(Fault("stuck", 5.0, onset_s=100.0),)), seeds=(2,))
    assert np.all(y[0, 100:] == 5.0) and np.array_equal(y[0, :100], TRUTH[:100])


def test_dropouts_hold_the_last_value_are_flagged_and_start_at_onset():
    p, length = 0.01, 4
    ch = Channel(noise_sd=0.05, faults=(Fault("dropout", p, onset_s=1000.0, length_s=float(length)),))
    x, flags = measure(ch, seeds=range(20))
    assert not flags[:, :1000].any()
    assert flags.any()
    r, k = np.nonzero(flags)
    assert np.all(x[r, k] == x[r, k - 1])  # held
    # fraction dropped: P(a start within the last `length` samples) = 1 - (1 - p)^length
    frac = flags[:, 1000 + length:].mean()
    expected = 1 - (1 - p) ** length
    n = flags[:, 1000 + length:].size / length  # roughly independent blocks
    assert abs(frac - expected) < 5 * np.sqrt(expected * (1 - expected) / n)


def test_faults_combine():
    ch = Channel(offset=0.1, gain=0.01, faults=(Fault("offset", 0.2, onset_s=1000.0),
                                                 Fault("stuck", None, onset_s=1500.0)))
    x, _ = measure(ch, seeds=(0,))
    assert np.allclose(x[0, :1000], 1.01 * TRUTH[:1000] + 0.1)
    assert np.allclose(x[0, 1000:1500], 1.01 * TRUTH[1000:1500] + 0.3)
    assert np.all(x[0, 1500:] == x[0, 1500])


def test_quantisation_and_saturation():
    ch = Channel(noise_sd=0.003, bits=10, range=(0.0, 21.0))
    x, _ = measure(ch, seeds=(0,))
    q = 21.0 / 1024
    steps = x[0] / q
    assert np.allclose(steps, np.round(steps))  # on the ADC grid
    inside = TRUTH < 21.0 - 0.05
    assert np.all(np.abs(x[0, inside] - TRUTH[inside]) <= q / 2 + 5 * 0.003)
    assert np.all(x[0] <= 21.0) and np.all(x[0, TRUTH > 21.1] == 21.0)  # saturates at the top of the range


# ------------------------------------------------------------------------------------------------ initial errors
def test_initial_soc_error_and_declared_capacity():
    spec = SensorSpec(soc0_error=0.03, soc0_error_sd=0.02)
    z = initial_soc_guess(0.6, spec, range(3000), KEY)
    assert within_mean(z, 0.63, 0.02) and within_sd(z, 0.02)
    sc = load_scenario("nominal")
    p = sc.realize([0])
    assert p.meta.capacity_ah == pytest.approx(1.03 * p.meta.extra["true_capacity_ah"])
    z0 = sc.initial_soc([0, 1, 2])
    assert z0.shape == (3,) and np.all((z0 >= 0) & (z0 <= 1))
    assert np.array_equal(z0, sc.initial_soc([0, 1, 2]))
    clean = load_scenario("clean")
    assert np.all(clean.initial_soc([0, 1]) == clean.realize([0]).soc_ref[0, 0])


def test_jitter_moves_sampling_instants():
    base = load_scenario("clean")
    jit = base.with_sensors(jitter_sd_s=0.2)
    p0, p1 = base.realize([0]), jit.realize([0])
    assert np.array_equal(p0.voltage_v, p0.meta.extra["truth"]["voltage_v"][None, :])
    d = p1.voltage_v[0] - p0.voltage_v[0]
    assert np.any(d != 0)
    # |δ| <= dt/2 and the truth is interpolated between its 1 s samples: the reading moves by at most half the
    # truth's change to the neighbouring sample
    dv = np.abs(np.diff(p0.voltage_v[0]))
    bound = 0.5 * np.maximum(np.r_[0.0, dv], np.r_[dv, 0.0])
    assert np.all(np.abs(d) <= bound + 1e-12)


@pytest.mark.parametrize("bad, key", [
    ({"noise_sd": -0.1}, "sensors.current.noise_sd"),
    ({"bits": 12}, "sensors.current.range"),
    ({"faults": [{"kind": "offset", "value": 1.0, "onset_s": -5.0}]}, "sensors.current.faults[0].onset_s"),
    ({"faults": [{"kind": "wobble", "value": 1.0}]}, "sensors.current.faults[0].kind"),
    ({"faults": [{"kind": "dropout", "value": 1.5}]}, "sensors.current.faults[0].value"),
])
def test_bad_sensor_tables_name_the_key(bad, key):
    with pytest.raises(ConfigError) as e:
        SensorSpec.from_table({"current": bad}, "x.toml")
    msg = str(e.value)
    assert "x.toml" in msg and f"'{key}'" in msg and "\n" not in msg


def test_sample_rate_decimates_the_truth():
    base = load_scenario("clean")
    slow = base.with_sensors(dt=5.0)
    p1, p5 = base.realize([0]), slow.realize([0])
    assert np.all(np.diff(p5.time_s) == 5.0)
    assert p5.n == (p1.n + 4) // 5
    assert np.array_equal(p5.voltage_v[0], p1.voltage_v[0, ::5])
    assert slow.sensor_noise().dt == 5.0
