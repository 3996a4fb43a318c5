"""Scenario catalog, the momentum-theory missions, the lab schedule, the truth cell and scenario-file errors."""

from __future__ import annotations

import numpy as np
import pytest

from socbench.cli import main
from socbench.errors import ConfigError
from socbench.estimators.noise import SensorNoise
from socbench.models import paper_pack
from socbench.scenarios import TruthCell, load_scenario, scenario_names
from socbench.scenarios.mission import Mission, Vehicle
from socbench.scenarios.replay import load_template

REQUIRED = {"flight-0kg", "flight-10kg", "dji-m100-replay", "hppc", "clean", "nominal", "harsh", "current-bias",
            "dropout", "cold"}


def flight_stats(name):
    """(mean current under load [A], time under load [s]) from the truth the scenario measured."""
    p = load_scenario(name).realize([0])
    i = p.meta.extra["truth"]["current_a"]
    loaded = i > 0
    return i[loaded].mean(), loaded.sum() * float(np.median(np.diff(p.time_s))), p


def test_catalog_has_the_required_scenarios():
    assert REQUIRED <= set(scenario_names())
    for name in scenario_names():
        assert load_scenario(name).description


def test_10kg_flight_draws_about_twice_the_current_for_less_than_half_the_time():
    i0, t0, p0 = flight_stats("flight-0kg")
    i10, t10, p10 = flight_stats("flight-10kg")
    assert 1.7 <= i10 / i0 <= 2.5
    assert t10 < 0.5 * t0
    for p in (p0, p10):  # both flights run to the pack's under-voltage limit
        v = p.meta.extra["truth"]["voltage_v"]
        assert p.meta.extra["stop_reason"] == "under_voltage"
        assert v[-1] < paper_pack()["under_voltage_v"] <= v[:-1].min()


def test_mission_is_a_constant_power_load_whose_current_rises_as_the_pack_sags():
    sc = load_scenario("clean")
    p = sc.realize([0])
    truth = p.meta.extra["truth"]
    power = truth["current_a"] * truth["voltage_v"]
    ground = [t for name, t in p.meta.extra["phases"] if name == "ground"]
    assert len(ground) >= 3  # the pattern repeats
    idle = sc.spec.vehicle.idle_w
    first = int(ground[0] / 1.0) + 2
    last = int(ground[-1] / 1.0) + 2
    assert power[first] == pytest.approx(idle, rel=1e-9) and power[last] == pytest.approx(idle, rel=1e-9)
    assert truth["current_a"][last] > truth["current_a"][first]
    assert truth["voltage_v"][last] < truth["voltage_v"][first]


def test_momentum_theory_power():
    v = Vehicle()
    weight = v.empty_mass_kg * 9.80665
    ideal = weight**1.5 / np.sqrt(2 * v.air_density * v.disk_area_m2)  # T^{3/2}/√(2ρA)
    hover = v.electrical_power(0.0, 0.0)
    assert hover == pytest.approx(ideal / v.figure_of_merit / v.drive_efficiency + v.avionics_w)
    assert v.electrical_power(0.0, 0.0, climb_rate=2.0) > hover > v.electrical_power(0.0, 0.0, climb_rate=-1.5)
    # translational lift: at moderate speed the induced power falls faster than the drag power grows
    assert v.electrical_power(0.0, 8.0, forward=True) < hover
    # the same power for the same gust stream: the mission is deterministic
    m = Mission()
    assert np.array_equal(m.power(v, 3)[0], m.power(v, 3)[0])
    assert not np.array_equal(m.power(v, 3)[0], m.power(v, 4)[0])


def test_realize_returns_the_measured_batch_with_the_true_soc():
    sc = load_scenario("flight-10kg")
    p = sc.realize([0, 1])
    assert p.current_a.shape == (2, p.n) and p.soc_ref.shape == (2, p.n)
    assert p.meta.capacity_ah == pytest.approx(22.0)  # lab scenario: declared = true
    dt = np.diff(p.time_s)
    assert np.all(dt == 1.0)
    z = p.soc_ref[0]
    assert z[0] > 0.95 and z[-1] < 0.1  # from CC-CV full to the under-voltage limit
    assert np.all(np.diff(z[60:]) < 0)  # true SOC falls all flight
    # SOC reference is the coulomb count of the *true* current on the true capacity
    ah = np.cumsum(p.meta.extra["truth"]["current_a"][:-1]) / 3600.0
    assert np.allclose(z[1:], z[0] - ah / sc.true_capacity_ah, atol=1e-9)
    noise = sc.sensor_noise()
    assert isinstance(noise, SensorNoise) and noise.dt == 1.0 and noise.voltage_sd > 0 and noise.current_sd > 0


def test_characterisation_is_the_hppc_of_the_same_truth_cell():
    cold = load_scenario("cold")
    hp = cold.characterisation(seed=0)
    assert not hp.batched and hp.n < 11000 and np.all(np.diff(hp.time_s) == 1.0)
    assert hp.current_a.min() < -10 and hp.current_a.max() > 20  # charge and discharge pulses at ~1 C
    assert hp.soc_ref[0] == pytest.approx(1.0) and hp.soc_ref[-1] < 0.01
    # 11 long rests (the OCV points)
    rest = np.abs(hp.meta.extra["truth"]["current_a"]) == 0
    edges = np.flatnonzero(np.diff(np.r_[0, rest.astype(int), 0]))
    lengths = edges[1::2] - edges[::2]
    assert (lengths >= 500).sum() == 11
    # at 25 °C in the lab even for the cold scenario, whose flight is at -5 °C
    assert abs(np.mean(hp.meta.extra["truth"]["temperature_c"]) - 25.0) < 2.0
    assert cold.realize([0]).meta.extra["truth"]["temperature_c"][0] == pytest.approx(-5.0)
    # the same truth cell: the discharged charge is the cell's capacity
    ah = np.sum(hp.meta.extra["truth"]["current_a"][:-1]) / 3600.0
    assert ah == pytest.approx(cold.true_capacity_ah, rel=0.01)
    # measured with the same sensors but without timed faults
    bias = load_scenario("current-bias")
    hb = bias.characterisation()
    err = hb.current_a - hb.meta.extra["truth"]["current_a"]
    assert abs(err[1000:].mean() - err[:300].mean()) < 0.5  # no 2 A jump at 300 s
    flight = bias.realize([0])
    gain = 1.0 + bias.spec.sensors.current.gain
    ef = flight.current_a[0] - gain * flight.meta.extra["truth"]["current_a"]  # offsets, drift and noise
    # a 2 A jump at 300 s; the slack covers the nominal random-walk drift (0.002 A/√s: SD ≈ 0.06 A at 1000 s)
    assert ef[400:].mean() - ef[:290].mean() == pytest.approx(2.0, abs=0.3)


def test_truth_cell_effects():
    cell = TruthCell()
    p = cell.params
    # hysteresis: relaxed voltage after a long charge vs after a long discharge at the same SOC differs by ≈ 2M
    up = cell.initial_state(0.5, 25.0, hyst=1.0)
    down = cell.initial_state(0.5, 25.0, hyst=-1.0)
    up[..., 4] = down[..., 4] = 0.0  # the same instantaneous-hysteresis sign: only the one-state term differs
    assert cell.voltage(up, 0.0) - cell.voltage(down, 0.0) == pytest.approx(2 * p.hyst_m_v)
    x = cell.initial_state(0.5, 25.0, hyst=0.0)
    for _ in range(200):  # discharging drives h towards -1
        x = cell.step(x, 22.0, 1.0, 25.0)
    assert x[..., 3] < -0.9
    # Arrhenius: a cold pack drops more under load
    warm, cold = cell.initial_state(0.5, 25.0), cell.initial_state(0.5, -5.0)
    drop_w = cell.voltage(warm, 0.0) - cell.voltage(warm, 50.0)
    drop_c = cell.voltage(cold, 0.0) - cell.voltage(cold, 50.0)
    assert drop_c > 2.0 * drop_w
    # Butler-Volmer: the apparent resistance falls with the current amplitude
    # (from 1 A, so that the instantaneous-hysteresis sign is the same at both ends)
    r_small = (cell.voltage(warm, 1.0) - cell.voltage(warm, 10.0)) / 9.0
    r_large = (cell.voltage(warm, 1.0) - cell.voltage(warm, 150.0)) / 149.0
    assert r_large < 0.95 * r_small
    # self-heating under load, cooling towards ambient at rest
    hot = cell.initial_state(0.8, 25.0)
    for _ in range(600):
        hot = cell.step(hot, 100.0, 1.0, 25.0)
    assert hot[..., 5] > 30.0
    cool = cell.step(hot, 0.0, 600.0, 25.0)
    assert 25.0 < cool[..., 5] < hot[..., 5]
    # batched: one call advances many runs
    xb = cell.initial_state(np.array([0.3, 0.6, 0.9]), 25.0)
    assert cell.step(xb, np.array([10.0, 20.0, 30.0]), 1.0, 25.0).shape == (3, 6)


def test_mission_stops_at_the_landing_reserve(tmp_path):
    path = write(tmp_path, 'extends = "flight-10kg"\n[mission]\nreserve_soc = 0.5\n', "reserve.toml")
    p = load_scenario(path).realize([0])
    z = p.soc_ref[0]
    assert p.meta.extra["stop_reason"] == "reserve_soc"
    assert z[-1] < 0.5 <= z[-2]


def test_cc_cv_charge_ends_full_and_rested():
    p = load_scenario("flight-0kg").realize([0])
    z0 = p.soc_ref[0, 0]
    assert 0.97 < z0 <= 1.0
    # the recorded rest before the flight: no current, voltage near the OCV at that SOC
    assert np.all(p.meta.extra["truth"]["current_a"][:60] == 0.0)


def test_dji_template_scenario_runs_without_the_data_dir(monkeypatch):
    monkeypatch.delenv("SOCBENCH_DATA_DIR", raising=False)
    sc = load_scenario("dji-m100-replay")
    p = sc.realize([0, 1])
    i = p.meta.extra["truth"]["current_a"]
    flying = i > 5.0 / 5.5 * 22.0  # in flight: above the DJI ground current threshold at C-rate
    c_rate = i[flying].mean() / sc.true_capacity_ah
    # PROVENANCE: in-flight segment medians 14.3–20.7 A on ≈ 5.5 Ah -> 2.6–3.8 C
    assert 2.4 < c_rate < 4.0
    assert p.meta.extra["stop_reason"] == "under_voltage"
    t = load_template()
    assert set(t.columns) == {"segment", "t_s", "c_rate", "phase"} and 2 <= t["segment"].nunique() <= 5
    from importlib import resources

    text = resources.files("socbench").joinpath("data", "dji_m100_template.csv").read_text()
    assert len(text) < 8000 and "PROVENANCE" in text


# ------------------------------------------------------------------------------------------------ file errors
def write(tmp_path, text, name="bad.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("text, key", [
    ('kind = "mission"\nspeed = 3\n', "speed"),
    ('[mission]\npayload_kgs = 3.0\n', "mission.payload_kgs"),
    ('[mission]\npayload_kg = -1.0\n', "mission.payload_kg"),
    ('[mission]\nreserve_soc = 1.5\n', "mission.reserve_soc"),
    ('[vehicle]\nfigure_of_merit = 1.4\n', "vehicle.figure_of_merit"),
    ('[truth]\nr0_ohm = "small"\n', "truth.r0_ohm"),
    ('[truth]\ntau1_s = 0.0\n', "truth.tau1_s"),
    ('kind = "rocket"\n', "kind"),
    ('[sensors]\ndt = 0.5\n', "sensors.dt"),
    ('[sensors.voltage]\nbits = 40\nrange = [0.0, 30.0]\n', "sensors.voltage.bits"),
    ('[sensors.voltage]\nrange = [30.0, 0.0]\n', "sensors.voltage.range"),
    ('[schedule]\nambient_c = 400.0\n', "schedule.ambient_c"),
    ('[replay]\nsource = "data"\n', "replay.segments"),
])
def test_bad_scenario_file_is_a_one_line_error_naming_file_and_key(tmp_path, text, key):
    path = write(tmp_path, 'extends = "flight-0kg"\n' + text)
    with pytest.raises(ConfigError) as e:
        load_scenario(path)
    msg = str(e.value)
    assert str(path) in msg and f"'{key}'" in msg and "\n" not in msg


def test_cli_lists_the_catalog_and_rejects_a_bad_file(tmp_path, capsys):
    assert main(["scenarios"]) == 0
    out = capsys.readouterr().out
    for name in REQUIRED:
        assert f"\n{name} " in out
    bad = write(tmp_path, '[mission]\npayload = 3\n')
    assert main(["scenarios", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(bad) in err and "mission.payload" in err
    assert main(["scenarios", "no-such-scenario"]) == 2


def test_a_scenario_file_can_extend_the_catalog(tmp_path):
    path = write(tmp_path, 'extends = "nominal"\ndescription = "mine"\n[mission]\npayload_kg = 5.0\n'
                           '[sensors.current]\nnoise_sd = 0.0\nbits = 0\noffset = 0.0\ngain = 0.0\ndrift_sd = 0.0\n',
                 "mine.toml")
    sc = load_scenario(path)
    assert sc.name == "mine" and sc.spec.mission.payload_kg == 5.0
    assert sc.spec.sensors.voltage.noise_sd == load_scenario("nominal").spec.sensors.voltage.noise_sd
    p = sc.realize([0])
    assert np.array_equal(p.current_a[0], p.meta.extra["truth"]["current_a"])  # ideal current channel
    with pytest.raises(ConfigError, match="circular"):
        load_scenario(write(tmp_path, 'extends = "loop.toml"\n', "loop.toml"))
