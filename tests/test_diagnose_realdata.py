"""The diagnosis on measured data (SOCBENCH_DATA_DIR).

* Panasonic 18650PF fitted at 25 °C and driven at 0 °C and −10 °C: the temperature effect is what the data lack, and
  the closed loop gets within 1.5 × of the "oracle" (the same base model fitted the same way on the −10 °C HPPC)
  on the −10 °C record;
* the same across temperature pairs the case above does not use (fitted at 25, 10 or 0 °C and driven colder, or
  fitted in the cold and driven at 25 °C; one US06 record each): the temperature effect is named first, the loop
  gets within 1.5 × of the oracle, and neither filter's held-out SOC error, on the record's own SOC axis, grows;
* CALCE A123 LFP: the held-out SOC error of the EKF and the UKF after the loop is not worse than before;
* the Panasonic cell's own ageing over its campaign: a fade named on its last 1C capacity test, of the size the charge
  it delivered measures, and none on its first;
* the Panasonic records whose cell warms by tens of kelvin as they run: the temperature named first.

Nothing but the files and the base model is given; no effect name is in any metadata the diagnosis reads (the measured
cell temperature column is data). Tens of CPU seconds each (a shared CI machine: wall time varies).
"""

from __future__ import annotations

import numpy as np
import pytest

from socbench.datasets import load
from socbench.datasets.panasonic import find_panasonic
from socbench.diagnose import diagnose, fit_base
from socbench.diagnose.report import reference_count_sentence
from socbench.diagnose.search import initial_soc
from socbench.socaxis import reference_capacity

pytestmark = [pytest.mark.realdata, pytest.mark.slow]

PAN = "panasonic_18650pf"
CALCE = "calce_a123_lfp"


def test_panasonic_cold_drive_cycles_need_temperature_and_match_the_oracle(data_dir):
    fit = [load(data_dir / PAN / "25degC" / "03-11-17_08.47_25degC_5Pulse_HPPC_Pan18650PF.mat")]
    evals = [load(data_dir / PAN / "0degC" / "06-02-17_04.58_0degC_US06_Pan18650PF.mat"),
             load(data_dir / PAN / "n10degC" / "06-07-17_08.39_n10degC_US06_Pan18650PF.mat")]
    d = diagnose("dp", fit, evals, soc=False)
    assert d.split.describe()["method"] == "blocked_cv" and len(d.split.records) == 2  # both records, in folds
    assert d.effects_added[0] == "temperature", [(c.effect, c.score) for c in d.rounds[0]["candidates"]]
    assert d.after["rmse_v"] <= 0.6 * d.before["rmse_v"]
    cold = d.split.records[1]
    hppc_cold = load(data_dir / PAN / "n10degC" / "06-07-17_12.29_n10degC_5pulse_HPPC_Pan18650PF.mat")
    oracle, _ = fit_base("dp", [hppc_cold], "auto", validation=[cold])
    e = cold.voltage_v - oracle.simulate(cold, soc0=initial_soc(oracle, cold)).voltage_v
    assert d.after["rmse_v_per_record"][cold.name] <= 1.5 * float(np.sqrt(np.mean(e * e)))


#: every pair of docs/closing_the_loop.md's temperature-pair table (benchmarks/closing_the_loop.py TEMPERATURE_PAIRS)
#: whose ambients lie 20 K or more apart. Fitted at −20 °C and driven at 25 °C, the loop stays 1.84 × the oracle: a
#: known miss, asserted as one
PAIRS = [(25, 0), (25, -10), (25, -20), (10, -10), (10, -20), (0, -20), (0, 25), (-10, 25),
         pytest.param(-20, 25, marks=pytest.mark.xfail(strict=True, reason="the loop 1.84 x the oracle"))]


@pytest.mark.parametrize("t_fit,t_eval", PAIRS)
def test_panasonic_other_temperature_pairs_name_temperature_match_the_oracle_and_keep_the_soc(data_dir, t_fit,
                                                                                                 t_eval):
    fit = [load(find_panasonic(data_dir, f"{t_fit}degC", "HPPC")[0])]
    rec = load(find_panasonic(data_dir, f"{t_eval}degC", "US06")[0])
    d = diagnose("dp", fit, [rec])
    assert d.effects_added and d.effects_added[0] == "temperature", d.effects_added
    scored = d.split.records[0]  # the bins the loop's held-out error is on
    oracle, _ = fit_base("dp", [load(find_panasonic(data_dir, f"{t_eval}degC", "HPPC")[0])], "auto",
                         validation=[scored])
    e = scored.voltage_v - oracle.simulate(scored, soc0=initial_soc(oracle, scored)).voltage_v
    assert d.after["rmse_v"] <= 1.5 * float(np.sqrt(np.mean(e * e)))
    for name in ("ekf", "ukf"):
        assert d.after["soc"][name]["soc_rmse"] <= d.before["soc"][name]["soc_rmse"], (d.before["soc"], d.after["soc"])


def test_calce_lfp_soc_is_not_worse_after_the_loop(data_dir):
    fit = [load(data_dir / CALCE / "A1-00x_20degC_lowcurrent_OCV_C22_discharge_charge.csv"),
           load(data_dir / CALCE / "A1-00x_20degC_DST_from_full.csv")]
    evals = [load(data_dir / CALCE / "A1-00x_20degC_FUDS_from_full.csv"),
             load(data_dir / CALCE / "A1-00x_20degC_US06_from_full.csv")]
    d = diagnose("thevenin", fit, evals, slow_ocv="discharge")
    assert "discharge branch" in d.fit["ocv"]
    assert d.after["rmse_v"] <= d.before["rmse_v"]
    for name in ("ekf", "ukf"):
        assert d.after["soc"][name]["soc_rmse"] <= d.before["soc"][name]["soc_rmse"], d.after["soc"]
    # the loader's reference is its count of the same current on the capacity it declares: read back as that count,
    # no current left out, and the report says the scoring converts to its axis
    rc = d.soc["reference_count"]
    assert rc["records"] == 2 and rc["declared_capacity_ah"] == [reference_capacity(p) for p in evals]
    assert rc["capacity_ah"] == pytest.approx(rc["declared_capacity_ah"][0], rel=1e-6)
    assert abs(rc["uncounted_current_a"]) < 1e-6 * rc["capacity_ah"] and rc["residual_soc_rms"] < 1e-6
    assert "converted to that axis" in reference_count_sentence(rc)


@pytest.mark.parametrize("record", ["03-09-17_17.59_3349_Dis1C_1.mat", "07-22-17_22.44_4020_Dis1C_1.mat"])
def test_panasonic_ageing_is_named_on_the_last_capacity_test_only(data_dir, record):
    """The cell aged over its campaign (PROVENANCE: 1C capacity 2.80 → 2.43 Ah). The DP fitted on the campaign's
    first 25 °C HPPC names no fade on the first 1C test (two days before it) and names one on the last, within 3
    points of the fade the charge it delivered measures against the HPPC's capacity; the SOC is not made worse."""
    fit = [load(data_dir / PAN / "25degC" / "03-11-17_08.47_25degC_5Pulse_HPPC_Pan18650PF.mat")]
    rec = load(data_dir / PAN / "25degC" / record)
    d = diagnose("dp", fit, [rec])
    measured = 1.0 - rec.amp_hours()[-1] / d.base_model.capacity_ah
    if measured < 0.0:  # the first test: it delivers more than the HPPC's count
        assert "capacity" not in d.effects_added, d.effects_added
    else:
        assert "capacity" in d.effects_added, d.effects_added
        cap0 = next(st.params["cap0"] for st in d.steps if st.effect == "capacity")
        assert abs((1.0 - 1.0 / cap0) - measured) < 0.03, (cap0, measured)
        assert d.after["rmse_v"] <= 0.5 * d.before["rmse_v"]
    for name in ("ekf", "ukf"):
        assert d.after["soc"][name]["soc_rmse"] <= d.before["soc"][name]["soc_rmse"], (d.before["soc"], d.after["soc"])


@pytest.mark.parametrize("record", ["n20degC_Trise/07-01-17_19.59_n20degC_trise_US06_Pan18650PF.mat",
                                    "10degC_Trise/07-09-17_19.11_10degC_trise_Cycle_1_Pan18650PF.mat"])
def test_panasonic_rising_temperature_names_the_temperature_first(data_dir, record):
    """A record whose cell warms by 17–33 °C as it runs (the chamber starts cold and drifts), the DP fitted at 25 °C:
    the temperature is named first, the held-out voltage error falls by a quarter, and both filters' SOC error falls."""
    fit = [load(data_dir / PAN / "25degC" / "03-11-17_08.47_25degC_5Pulse_HPPC_Pan18650PF.mat")]
    rec = load(data_dir / PAN / record)
    assert np.ptp(rec.temperature_c) > 15.0
    d = diagnose("dp", fit, [rec])
    assert d.effects_added and d.effects_added[0] == "temperature", d.effects_added
    assert d.after["rmse_v"] <= 0.75 * d.before["rmse_v"]
    for name in ("ekf", "ukf"):
        assert d.after["soc"][name]["soc_rmse"] < d.before["soc"][name]["soc_rmse"], (d.before["soc"], d.after["soc"])
