"""The diagnosis on measured data (SOCBENCH_DATA_DIR): it must find, from the data alone, the effect each set is known
for — temperature for the Panasonic 18650PF driven cold after a 25 °C fit, hysteresis for the A123 LFP cell.

Nothing but the files and the base model is given; no effect name is in any metadata the diagnosis reads (the
measured cell temperature column is data). About ten seconds each (whole-record simulation).
"""

from __future__ import annotations

import pytest

from socbench.datasets import load
from socbench.diagnose import diagnose

pytestmark = [pytest.mark.realdata, pytest.mark.slow]

PAN = "panasonic_18650pf"
CALCE = "calce_a123_lfp"


def test_panasonic_cold_drive_cycles_need_temperature(data_dir):
    fit = [load(data_dir / PAN / "25degC" / "03-11-17_08.47_25degC_5Pulse_HPPC_Pan18650PF.mat")]
    evals = [load(data_dir / PAN / "0degC" / "06-02-17_04.58_0degC_US06_Pan18650PF.mat"),
             load(data_dir / PAN / "n10degC" / "06-07-17_08.39_n10degC_US06_Pan18650PF.mat")]
    d = diagnose("dp", fit, evals, soc=False)
    assert d.split.method == "by_profile"  # fitted at 0 °C, judged at −10 °C
    assert d.effects_added[0] == "temperature", [(c.effect, c.score) for c in d.rounds[0]["candidates"]]
    assert d.after["rmse_v"] <= 0.6 * d.before["rmse_v"]


def test_calce_lfp_drive_cycles_need_hysteresis(data_dir):
    fit = [load(data_dir / CALCE / "A1-00x_20degC_lowcurrent_OCV_C22_discharge_charge.csv"),
           load(data_dir / CALCE / "A1-00x_20degC_DST_from_full.csv")]
    evals = [load(data_dir / CALCE / "A1-00x_20degC_FUDS_from_full.csv"),
             load(data_dir / CALCE / "A1-00x_20degC_US06_from_full.csv")]
    d = diagnose("thevenin", fit, evals, slow_ocv="discharge", soc=False)
    assert "discharge branch" in d.fit["ocv"]
    assert "hysteresis" in d.effects_added, [(c.effect, c.score) for c in d.rounds[0]["candidates"]]
    assert d.after["rmse_v"] < d.before["rmse_v"]
