"""Temperature-aware identification on the real Panasonic HPPC tests (25, 10, 0, −10, −20 °C).

One five-temperature fit per test session (thevenin, paper mode: SOC polynomials, clamped to a cold record's SOC
range) serves the interpolation checks; the command-line test fits two temperatures with rint (fast) and estimates on
the −20 °C US06. Plus the pieces that need no data: temperatures from records, refusals, the single-temperature form.
"""

from __future__ import annotations

import json
from functools import lru_cache

import numpy as np
import pytest

from socbench.cli import main
from socbench.datasets.panasonic import CAPACITY_AH, find_panasonic, load_panasonic
from socbench.errors import DataError
from socbench.identify.temperature import extend_ocv, fit_temperatures, record_temperature
from socbench.models import load_params, make_model, paper_params, save_params
from socbench.models.params import CapacityTable, Lookup, TemperatureTable, params_to_dict
from socbench.ocv import OCVCurve, TemperatureOCV
from socbench.profile import Profile, ProfileMeta

TAGS = ("25degC", "10degC", "0degC", "n10degC", "n20degC")


@lru_cache(maxsize=1)
def _five_temperature_fit(data_dir: str):
    return fit_temperatures("thevenin", [load_panasonic(find_panasonic(data_dir, t, "HPPC")[0]) for t in TAGS])


def test_five_temperature_fit_is_exact_at_its_temperatures_bounded_between_and_held_outside(data_dir):
    res = _five_temperature_fit(str(data_dir))
    p = res.params
    # temperatures: the median of each HPPC's cell thermocouple, coldest first
    assert np.allclose(res.temps, (-19.9, -9.7, 0.6, 10.8, 25.8), atol=0.5)
    assert p.temperatures == res.temps
    # one SOC axis: the warmest capacity; each record's own discharge kept as data
    assert p.capacity_ah == pytest.approx(CAPACITY_AH["25degC"], rel=1e-4) == res.capacity_ref
    assert isinstance(p.capacity_by_temperature, CapacityTable)
    assert p.capacity_by_temperature.at(-19.9) == pytest.approx(CAPACITY_AH["n20degC"], rel=1e-3)
    z = np.linspace(0.0, 1.0, 201)
    rng = np.random.default_rng(0)
    for name, table in p.values.items():
        assert isinstance(table, TemperatureTable)
        for t, fit in zip(res.temps, res.fits):  # exact at every fitted temperature
            np.testing.assert_array_equal(table(z, np.full(z.shape, t)), fit.params[name](z))
        for lo, hi in zip(res.temps[:-1], res.temps[1:]):  # between its two neighbours
            t = rng.uniform(lo, hi, z.size)
            a, b = table(z, np.full(z.shape, lo)), table(z, np.full(z.shape, hi))
            v = table(z, t)
            assert np.all(v >= np.minimum(a, b) - 1e-12) and np.all(v <= np.maximum(a, b) + 1e-12)
        np.testing.assert_array_equal(table(z, np.full(z.shape, -40.0)), table(z, np.full(z.shape, res.temps[0])))
        np.testing.assert_array_equal(table(z, np.full(z.shape, 60.0)), table(z, np.full(z.shape, res.temps[-1])))
        # the −20 °C record reaches only z ≈ 0.21 of the axis: below it the node holds its end value, no blow-up
        cold = table.nodes[0]
        z_lo = 1.0 - CAPACITY_AH["n20degC"] / CAPACITY_AH["25degC"]
        assert isinstance(cold, Lookup) and cold.soc[0] == pytest.approx(z_lo, abs=0.01)
        below = cold(np.linspace(0.0, cold.soc[0], 20))
        np.testing.assert_array_equal(below, np.full(20, cold.value[0]))
        if name.startswith(("R", "C")):
            assert table.scale == "log" and table.range_on_unit()[0] > 0
    for t in np.linspace(-25.0, 30.0, 12):  # the OCV: monotone in SOC at every temperature, bounded by neighbours
        v = p.ocv(z, np.full(z.shape, t))
        assert np.all(np.diff(v) >= 0)
    np.testing.assert_array_equal(p.ocv(z, np.full(z.shape, res.temps[-1])), p.ocv.curves[-1](z))


def test_five_temperature_set_runs_on_a_cold_drive_cycle_and_survives_json(data_dir, tmp_path):
    res = _five_temperature_fit(str(data_dir))
    us06 = load_panasonic(find_panasonic(data_dir, "n20degC", "US06")[0])
    m = make_model("thevenin", res.params)
    sim = m.simulate(us06, soc0=1.0)
    assert np.all(np.isfinite(sim.voltage_v))
    save_params(tmp_path / "p.json", "thevenin", res.params)
    name, back = load_params(tmp_path / "p.json")
    d = json.loads((tmp_path / "p.json").read_text())
    assert d["capacity_by_temperature"]["capacity_ah"][0] == pytest.approx(CAPACITY_AH["n20degC"], rel=1e-3)
    np.testing.assert_array_equal(make_model(name, back).simulate(us06, soc0=1.0).voltage_v, sim.voltage_v)


def test_fit_and_estimate_commands_with_two_temperatures(data_dir, tmp_path, capsys):
    h25 = find_panasonic(data_dir, "25degC", "HPPC")[0]
    h20 = find_panasonic(data_dir, "n20degC", "HPPC")[0]
    out = tmp_path / "rint.json"
    assert main(["fit", "--data", str(h25), str(h20), "--model", "rint", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "at 2 temperatures" in text and "temperature = median of the temperature column" in text
    assert "noise recipe on the 2 identification record(s)" in text
    d = json.loads(out.read_text())
    assert len(d["capacity_by_temperature"]["temps"]) == 2 and "by_temperature" in d["ocv"]
    assert all("by_temperature" in v for v in d["params"].values())
    assert len(d["model_error"]["temps"]) == 2 and len(d["fit"]["by_temperature"]) == 2
    us06 = find_panasonic(data_dir, "n20degC", "US06")[0]
    est = tmp_path / "est"
    assert main(["estimate", "--data", str(us06), "--params", str(out), "--estimator", "coulomb", "--soc0", "1.0",
                 "--out", str(est)]) == 0
    line = capsys.readouterr().out
    assert "within 3σ" in line and "NIS" in line
    metrics = json.loads((est / "metrics.json").read_text())
    assert metrics["soc_axis"]["ratio"] == pytest.approx(CAPACITY_AH["25degC"] / CAPACITY_AH["n20degC"], rel=1e-3)
    # counting on the model's axis from the true start, reported on the data's: the reference to the counter's digits
    assert metrics["soc_rmse"] < 0.003
    assert metrics["noise"]["mode"] == "sensor"  # the coulomb counter never reads the voltage


def test_fit_command_with_the_charge_transfer_term(data_dir, tmp_path, capsys):
    h25 = find_panasonic(data_dir, "25degC", "HPPC")[0]
    h20 = find_panasonic(data_dir, "n20degC", "HPPC")[0]
    out = tmp_path / "rint_ct.json"
    assert main(["fit", "--data", str(h25), str(h20), "--model", "rint", "--charge-transfer", "--out", str(out)]) == 0
    assert "Arrhenius law" in capsys.readouterr().out
    d = json.loads(out.read_text())
    (eff,) = d["effects"]
    law = d["fit"]["charge_transfer"]
    assert eff["name"] == "butler_volmer" and eff["values"]["Ea"] == law["ea_j_per_mol"] >= 0.0
    assert law["i0_law_a"][0] <= law["i0_law_a"][1]  # the cold exchange current is not the larger
    name, params = load_params(out)
    assert make_model(name, params).name == "rint+butler_volmer"
    us06 = find_panasonic(data_dir, "n20degC", "US06")[0]
    js = tmp_path / "sim.json"
    assert main(["simulate", "--data", str(us06), "--params", str(out), "--json", str(js)]) == 0
    assert np.isfinite(json.loads(js.read_text())["rmse_v"])
    capsys.readouterr()
    # the law needs two temperatures: one record is a user error (exit 2, one line)
    assert main(["fit", "--data", str(h25), "--model", "rint", "--charge-transfer", "--out", str(out)]) == 2
    assert "at least two" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------- without data
def _record(temp=None, ambient=None):
    meta = ProfileMeta(name="r", extra={} if ambient is None else {"ambient_temperature_c": ambient})
    t = np.arange(10.0)
    return Profile(t, np.ones(10), np.full(10, 3.7), None if temp is None else np.full(10, temp), meta=meta)


def test_record_temperature_and_refusals():
    assert record_temperature(_record(temp=-9.5))[0] == -9.5
    assert "median" in record_temperature(_record(temp=-9.5))[1]
    assert record_temperature(_record(ambient=10.0)) == (10.0, "ambient temperature of the file (no temperature "
                                                               "column)")
    with pytest.raises(DataError, match="no temperature column and no ambient"):
        record_temperature(_record())
    from socbench.datasets import builtin_profile

    a = builtin_profile("hppc")
    b = a.with_(temperature_c=np.full(a.n, 25.3))
    with pytest.raises(DataError, match="same temperature"):
        fit_temperatures("rint", [a.with_(temperature_c=np.full(a.n, 25.0)), b])


def test_a_fit_setting_per_temperature():
    """``per_record``: each record fitted with its own setting; each node is exactly that record's own fit."""
    from socbench.datasets import builtin_profile
    from socbench.identify import fit_model
    from socbench.models.params import Polynomial

    a = builtin_profile("hppc")
    warm, cold = a.with_(temperature_c=np.full(a.n, 25.0)), a.with_(temperature_c=np.full(a.n, 0.0))
    res = fit_temperatures("thevenin", [warm, cold], per_record=[{"mode": "paper"}, {"mode": "lookup"}])
    assert res.temps == (0.0, 25.0) and res.mode == "per temperature"
    assert [f.mode for f in res.fits] == ["lookup", "paper"]  # coldest first: each record kept its own setting
    alone = {"paper": fit_model("thevenin", warm, mode="paper", capacity_ah=res.capacity_ref),
             "lookup": fit_model("thevenin", cold, mode="lookup", capacity_ah=res.capacity_ref)}
    z = np.linspace(0.0, 1.0, 101)
    for name, table in res.params.values.items():
        assert isinstance(table.nodes[0], Lookup)
        assert isinstance(table.nodes[1], Polynomial) or table.nodes[1].is_constant
        np.testing.assert_array_equal(table(z, np.full(z.shape, 0.0)), alone["lookup"].params[name](z))
        np.testing.assert_array_equal(table(z, np.full(z.shape, 25.0)), alone["paper"].params[name](z))
    sim = make_model("thevenin", res.params).simulate(a.with_(temperature_c=np.linspace(-5.0, 30.0, a.n)), soc0=1.0)
    assert np.all(np.isfinite(sim.voltage_v))
    with pytest.raises(DataError, match="1 per-record settings for 2 records"):
        fit_temperatures("thevenin", [warm, cold], per_record=[{"mode": "paper"}])


def test_extended_ocv_meets_the_cold_curve_and_stays_monotone():
    warm = OCVCurve(np.linspace(0, 1, 11), 3.0 + 1.2 * np.linspace(0, 1, 11) ** 0.7)
    cold = OCVCurve([0.3, 0.6, 1.0], [3.55, 3.8, 4.15])
    ext, shift = extend_ocv(cold, warm)
    assert shift == pytest.approx(3.55 - float(warm(0.3)))
    assert ext.soc[0] == 0.0 and float(ext(0.3)) == pytest.approx(3.55)
    np.testing.assert_allclose(ext(np.linspace(0, 0.2, 5)), warm(np.linspace(0, 0.2, 5)) + shift, atol=1e-12)
    assert np.all(np.diff(ext(np.linspace(0, 1, 501))) >= 0)
    assert extend_ocv(warm, warm) == (warm, None)
    TemperatureOCV((-20.0, 25.0), [ext, warm])  # a valid temperature OCV


def test_the_single_temperature_form_is_unchanged():
    p = paper_params("thevenin")
    d = params_to_dict("thevenin", p)
    assert "capacity_by_temperature" not in d and p.capacity_by_temperature is None and p.temperatures == ()
