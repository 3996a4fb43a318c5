"""What `socbench estimate` says about a run it cannot trust: a filter that has lost the measurement, and a
single-temperature parameter set used far from the temperature it was fitted at (found by an outside sweep: both
were silent, with SOC errors of 20-50 points)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from socbench.cli import main
from socbench.estimators.scoring import LOST_MIN_S
from socbench.metrics import longest_stretch
from socbench.models import make_model, paper_params
from socbench.profile import Profile
from tests.hppc_records import ISSUE_CELL, Cell, Instrument, drive_record, issue_record, write_canonical


def test_longest_stretch_by_hand():
    t = np.arange(8.0)
    assert longest_stretch(t, [0, 1, 1, 0, 1, 1, 1, 0]) == (3.0, 4.0)  # samples 4-6, to the sample after (t=7)
    assert longest_stretch(t, [1, 1, 0, 0, 0, 0, 1, 1]) == (2.0, 0.0)  # the first of two equal runs; the last one
    # runs to the record's end and lasts t[7] − t[6] = 1 s
    d, start = longest_stretch(t, np.zeros(8, dtype=bool))
    assert d == 0.0 and np.isnan(start)
    assert longest_stretch(np.array([0.0, 0.5, 10.0, 10.5]), [1, 1, 0, 0]) == (10.0, 0.0)  # by time, not samples


@pytest.fixture(scope="module")
def pack_records(tmp_path_factory):
    """The paper Thevenin pack (6 cells, 22 Ah) for 5 minutes, and the same record with a voltage-sensor fault of
    +3 V from t = 150 s: above the pack's OCV at full, which no SOC can explain."""
    d = tmp_path_factory.mktemp("health")
    rng = np.random.default_rng(4)
    t = np.arange(300.0)
    i = np.repeat(rng.uniform(0.0, 40.0, 10), 30)
    sim = make_model("thevenin", paper_params("thevenin")).simulate(Profile(t, i), soc0=0.8)
    v = sim.voltage_v + 0.01 * rng.standard_normal(t.size)
    out = {}
    for name, fault in (("clean", 0.0), ("fault", 3.0)):
        path = d / f"{name}.csv"
        pd.DataFrame({"time_s": t, "current_a": i, "voltage_v": v + np.where(t >= 150.0, fault, 0.0),
                      "soc_ref": sim.soc}).to_csv(path, index=False)
        path.with_suffix(".json").write_text(json.dumps({"capacity_ah": 22.0, "n_series": 6}))
        out[name] = path
    return out


@pytest.mark.parametrize("estimator", ["ekf", "ukf"])
def test_a_filter_that_lost_the_measurement_says_so(pack_records, tmp_path, capsys, estimator):
    """From the fault on every innovation is far outside the filter's own band: the run is reported (one warning,
    ``lost_s`` and ``lost_from_s`` in metrics.json) where the clean record's run is not."""
    for name in ("clean", "fault"):
        out = tmp_path / name
        rc = main(["estimate", "--data", str(pack_records[name]), "--params", "paper:thevenin", "--estimator",
                   estimator, "--soc0", "0.7", "--out", str(out)])
        err = capsys.readouterr().err
        metrics = json.loads((out / "metrics.json").read_text())
        assert rc == 0
        if name == "clean":
            assert metrics["lost_s"] < LOST_MIN_S and "lost the measurement" not in err
        else:
            assert metrics["lost_s"] >= 140.0 and metrics["lost_from_s"] == pytest.approx(150.0, abs=2.0)
            assert err.count("lost the measurement") == 1 and "from t = 150 s" in err


@pytest.fixture(scope="module")
def fitted_at_25(tmp_path_factory):
    """``socbench fit`` on the issue-13 HPPC logged at 25 °C (a temperature column): the set has no temperature
    dependence and records where it was fitted."""
    d = tmp_path_factory.mktemp("t25")
    rec = issue_record(seed=3)
    prof = rec.profile.with_(temperature_c=np.full(rec.profile.n, 25.0))
    hppc = write_canonical(prof, d / "hppc.csv")
    params = d / "p.json"
    assert main(["fit", "--data", str(hppc), "--model", "thevenin", "--out", str(params)]) == 0
    return params


@pytest.mark.parametrize("temp_c, warned", [(27.0, False), (0.0, True)])
def test_a_single_temperature_set_warns_far_from_its_temperature(fitted_at_25, tmp_path, capsys, temp_c, warned):
    fit = json.loads(fitted_at_25.read_text())["fit"]
    assert fit["temperature_c"] == pytest.approx(25.0)
    drive = drive_record(ISSUE_CELL, Instrument(dt=1.0, v_noise=1e-3), seed=5, duration_s=1800.0).profile
    data = write_canonical(drive.with_(temperature_c=np.full(drive.n, temp_c)), tmp_path / "drive.csv")
    capsys.readouterr()
    for command in (["estimate", "--estimator", "ekf", "--out", str(tmp_path / "est")],
                    ["simulate", "--json", str(tmp_path / "sim.json")]):
        rc = main([command[0], "--data", str(data), "--params", str(fitted_at_25), *command[1:]])
        err = capsys.readouterr().err
        assert rc == 0
        assert ("more than 5 K from the 25.0 °C" in err) == warned, err
    metrics = json.loads((tmp_path / "est" / "metrics.json").read_text())
    assert metrics["temperature_range"]["away"] == (1.0 if warned else 0.0)


@pytest.mark.parametrize("resistance_factor, warned", [(1.0, False), (3.0, True)])
def test_error_states_held_far_out_say_the_recipe_is_exceeded(fitted_at_25, tmp_path, capsys, resistance_factor,
                                                             warned):
    """The noise recipe's error states are unit Gauss–Markov states. On a drive record of the cell the set was fitted
    on they stay within a few SDs; on the same drive with the cell's resistances tripled (an aged or cold cell the
    set knows nothing of) the miss is far beyond what the HPPC residual showed, the states take it up and stay many
    SDs out: one warning, and ``error_state_beyond_s`` in metrics.json says for how long."""
    c = ISSUE_CELL
    cell = Cell(c.capacity_ah, c.ocv_shape, c.r0 * resistance_factor,
                tuple((r * resistance_factor, tau) for r, tau in c.branches))
    drive = drive_record(cell, Instrument(dt=1.0, v_noise=1e-3), seed=5, duration_s=1800.0).profile
    data = write_canonical(drive.with_(temperature_c=np.full(drive.n, 25.0)), tmp_path / "drive.csv")
    capsys.readouterr()
    assert main(["estimate", "--data", str(data), "--params", str(fitted_at_25), "--estimator", "ekf", "--out",
                 str(tmp_path / "E")]) == 0
    err = capsys.readouterr().err
    held = json.loads((tmp_path / "E" / "metrics.json").read_text())["error_state_beyond_s"]
    assert set(held) == {"eps_slow", "eps_fast", "eps_r", "eps_mid"}
    assert ("model-error state" in err) == warned, err
    if warned:
        assert max(held.values()) >= LOST_MIN_S
    else:
        assert max(held.values()) == 0.0
