"""`socbench estimate`: files and keys on success; one-line errors with exit code 2 on bad input."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from socbench.cli import main
from socbench.estimators import estimator_names
from socbench.models import make_model, paper_params
from socbench.profile import Profile


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    """A 5-minute noisy record of the paper Thevenin pack, with and without the true SOC column."""
    d = tmp_path_factory.mktemp("est")
    rng = np.random.default_rng(4)
    t = np.arange(300.0)
    i = np.repeat(rng.uniform(0.0, 40.0, 10), 30)
    sim = make_model("thevenin", paper_params("thevenin")).simulate(Profile(t, i), soc0=0.8)
    frame = pd.DataFrame({"time_s": t, "current_a": i + 0.1 * rng.standard_normal(t.size),
                          "voltage_v": sim.voltage_v + 0.01 * rng.standard_normal(t.size), "soc_ref": sim.soc})
    with_ref = d / "run.csv"
    frame.to_csv(with_ref, index=False)
    no_ref = d / "noref.csv"
    frame.drop(columns="soc_ref").to_csv(no_ref, index=False)
    bad = d / "bad.csv"
    frame.rename(columns={"voltage_v": "volts"}).to_csv(bad, index=False)
    for path in (with_ref, no_ref, bad):  # the paper pack: 6 cells in series, 22 Ah
        path.with_suffix(".json").write_text(json.dumps({"capacity_ah": 22.0, "n_series": 6}))
    return {"ref": with_ref, "noref": no_ref, "bad": bad, "soc": sim.soc}


@pytest.mark.parametrize("estimator", estimator_names())  # every registered estimator, without edits here
def test_estimate_writes_csv_and_metrics(record, tmp_path, capsys, estimator):
    out = tmp_path / estimator
    rc = main(["estimate", "--data", str(record["ref"]), "--params", "paper:thevenin", "--estimator", estimator,
               "--soc0", "0.7", "--particles", "200", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    assert estimator in capsys.readouterr().out
    frame = pd.read_csv(out / "estimate.csv")
    assert list(frame.columns[:5]) == ["time_s", "soc", "soc_std", "v_pred", "innovation"]
    assert len(frame) == 300 and frame.notna().all().all()
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("soc_rmse", "soc_max_abs", "rmse_v", "nis_mean", "nees_mean", "frac_within_3sigma"):
        assert isinstance(metrics[key], float), key
    # the metrics are those of the CSV against the data file, recomputed here
    err = frame["soc"].to_numpy() - record["soc"]
    assert metrics["soc_rmse"] == pytest.approx(np.sqrt(np.mean(err**2)))
    assert metrics["soc_max_abs"] == pytest.approx(np.abs(err).max())
    if estimator != "coulomb":
        assert abs(err[-1]) < 0.01  # a filter pulled it in within 5 minutes
    else:
        assert frame["soc"].iloc[0] == 0.7  # it starts from the guess, not from the truth
        assert abs(err[-1]) > 0.09  # and keeps its initial error


def test_estimate_without_reference_soc(record, tmp_path, capsys):
    rc = main(["estimate", "--data", str(record["noref"]), "--params", "paper:thevenin", "--estimator", "ekf",
               "--out", str(tmp_path)])
    assert rc == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["soc_rmse"] is None and metrics["nees_mean"] is None
    assert isinstance(metrics["rmse_v"], float) and isinstance(metrics["nis_mean"], float)


@pytest.mark.parametrize("args, needle", [
    (["--data", "MISSING.csv"], "file not found"),
    (["--data", "BAD"], "voltage_v"),
    (["--soc0", "1.5"], "soc0"),
    (["--estimator", "kalman"], "unknown estimator 'kalman'"),
    (["--params", "paper:nosuchmodel"], "nosuchmodel"),
])
def test_bad_input_is_one_line_exit_2(record, tmp_path, capsys, args, needle):
    base = {"--data": str(record["ref"]), "--params": "paper:thevenin", "--estimator": "ekf", "--out": str(tmp_path)}
    given = dict(zip(args[::2], args[1::2]))
    if given.get("--data") == "BAD":
        given["--data"] = str(record["bad"])
    if given.get("--data") == "MISSING.csv":
        given["--data"] = str(tmp_path / "missing.csv")
    argv = ["estimate"] + [x for k, v in {**base, **given}.items() for x in (k, v)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err
    assert "\n" not in err and "Traceback" not in err
    assert not (tmp_path / "metrics.json").exists()
