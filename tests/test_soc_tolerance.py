"""Reference SOC tolerance (DESIGN.md, Reliability; issue 13): a reference a few points outside [0, 1] — counted from
a nominal capacity — is kept with one warning; further out it is an error, raised only where the reference is used.

The records are simulated on the paper Thevenin pack (6S, 22 Ah): the true SOC is exact, and the "counted"
references below are that truth rescaled the way a count from a wrong capacity is (``1 − (1 − z)·Q/Q_nominal``).
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest

from socbench.cli import main
from socbench.datasets import load
from socbench.errors import DataError, SocbenchWarning
from socbench.estimators import SensorNoise, make_estimator
from socbench.estimators.scoring import score
from socbench.identify import analyze_hppc
from socbench.models import make_model, paper_params
from socbench.profile import SOC_WARN_MARGIN, Profile, ProfileMeta


def _meta(name="ref.csv"):
    return ProfileMeta(name=name, source=name, capacity_ah=22.0, n_series=6)


def _counted(z, ratio):
    """A reference counted with a capacity ``ratio`` × the true one: ends at ``1 − 1/ratio`` when z reaches 0."""
    return 1.0 - (1.0 - z) / ratio


# ------------------------------------------------------------------------------------------------ the Profile
def test_a_few_points_out_is_kept_with_one_warning():
    z = np.linspace(1.0, 0.0, 101)
    ref = _counted(z, 0.993)  # ends at -0.7 %
    with pytest.warns(SocbenchWarning) as caught:
        p = Profile(np.arange(101.0), np.ones(101), soc_ref=ref, meta=_meta())
    assert len(caught) == 1
    msg = str(caught[0].message)
    # one line naming the file, the column and the row of the furthest value, and the value
    assert "\n" not in msg and msg.startswith("ref.csv, column 'soc_ref', row 101: reference SOC reaches -0.00")
    assert float(msg.split("reaches ")[1].split(",")[0]) == pytest.approx(ref.min(), rel=1e-3)
    np.testing.assert_array_equal(p.soc_ref, ref)  # kept as is, not clipped
    assert p.soc_ref_error is None
    # derived profiles (slices, copies, runs) carry the check: no second warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p.slice(50).require("soc_ref")
        p.with_(current_a=np.zeros(101)).get("soc_ref")
        p.with_(soc_ref=p.soc_ref[::-1].copy())
    # the margin is 5 points: both sides, the edge included
    for lo, hi in ((-SOC_WARN_MARGIN, 1.0), (0.0, 1.0 + SOC_WARN_MARGIN)):
        with pytest.warns(SocbenchWarning):
            assert Profile(np.arange(3.0), np.zeros(3), soc_ref=np.array([hi, 0.5, lo])).soc_ref is not None
    # inside [0, 1] up to rounding: nothing said
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Profile(np.arange(3.0), np.zeros(3), soc_ref=np.array([1.0 + 1e-7, 0.5, -1e-7]))


def test_far_out_is_refused_lazily_where_used():
    z = np.linspace(1.0, 0.0, 101)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # refused, not warned about
        p = Profile(np.arange(101.0), np.ones(101), soc_ref=z - 0.3, meta=_meta())
    assert p.soc_ref is None  # for every caller: the record has no reference...
    first_bad = int(np.argmax(z - 0.3 < -SOC_WARN_MARGIN)) + 1
    for use in (lambda: p.require("soc_ref"), lambda: p.get("soc_ref"), lambda: p.slice(10).get("soc_ref")):
        with pytest.raises(DataError) as e:  # ...until it is used
            use()
        assert (e.value.file, e.value.column, e.value.row) == ("ref.csv", "soc_ref", first_bad)
        assert "\n" not in str(e.value) and "points outside [0, 1]" in str(e.value)
    p.require("current_a")  # the other columns are untouched
    assert p.with_(soc_ref=z).get("soc_ref") is not None  # a valid reference replaces the refused one


# ------------------------------------------------------------------------------------------------ files and commands
@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A 10-minute noisy discharge of the paper pack from 34 % to 3 % with three reference columns: true, counted from
    a capacity 4 % short (−1 % at the end), and 30 points off."""
    d = tmp_path_factory.mktemp("socref")
    rng = np.random.default_rng(13)
    t = np.arange(600.0)
    i = np.repeat(rng.uniform(30.0, 50.0, 20), 30)  # ~2C
    sim = make_model("thevenin", paper_params("thevenin")).simulate(Profile(t, i), soc0=0.34)
    z = sim.soc
    base = pd.DataFrame({"time_s": t, "current_a": i + 0.1 * rng.standard_normal(t.size),
                         "voltage_v": sim.voltage_v + 0.005 * rng.standard_normal(t.size)})
    out = {}
    for name, ref in {"true": z, "counted": _counted(z, 0.96), "off": z - 0.3}.items():
        path = d / f"{name}.csv"
        base.assign(soc_ref=ref).to_csv(path, index=False)
        path.with_suffix(".json").write_text(json.dumps({"capacity_ah": 22.0, "n_series": 6}))
        out[name] = path
    out["off_row"] = int(np.argmax(z - 0.3 < -SOC_WARN_MARGIN)) + 1  # the first value more than 5 points out
    assert out["off_row"] > 1
    return out


def test_loader_keeps_or_defers(files):
    with pytest.warns(SocbenchWarning, match="column 'soc_ref'"):
        counted = load(files["counted"])
    assert -0.02 < counted.soc_ref.min() < -0.005
    off = load(files["off"])  # loading never fails on the reference
    assert off.soc_ref is None
    with pytest.raises(DataError) as e:
        off.require("soc_ref")
    assert e.value.file == str(files["off"]) and e.value.column == "soc_ref" and e.value.row == files["off_row"]


def test_scoring_and_hppc_analysis_use_the_reference(files):
    off = load(files["off"])
    model = make_model("thevenin", paper_params("thevenin"))
    est = make_estimator("ekf", model, SensorNoise(voltage_sd=0.005, current_sd=0.1)).run(off, soc0=0.34)
    with pytest.raises(DataError, match="soc_ref"):
        score(est, off)
    with pytest.raises(DataError, match="soc_ref"):  # the analysis reads it for the charge in record gaps
        analyze_hppc(off)


def _run(capsys, argv):
    rc = main(argv)
    return rc, capsys.readouterr().err.strip().splitlines()


def test_commands_fail_only_where_the_reference_is_used(files, tmp_path, capsys):
    est = ["estimate", "--params", "paper:thevenin", "--estimator", "ekf", "--soc0", "0.34"]
    # counted reference at −1 %: the estimate is scored against it, with one warning line
    rc, err = _run(capsys, est + ["--data", str(files["counted"]), "--out", str(tmp_path / "a")])
    assert rc == 0 and len(err) == 1 and err[0].startswith("socbench estimate: warning: ")
    metrics = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert metrics["soc_rmse"] is not None
    # 30 points off: scoring uses it -> exit 2, one line with file, column and row
    rc, err = _run(capsys, est + ["--data", str(files["off"]), "--out", str(tmp_path / "b")])
    assert rc == 2 and len(err) == 1
    assert err[0].startswith(f"socbench estimate: error: {files['off']}, column 'soc_ref', row {files['off_row']}: ")
    # simulate with an explicit initial SOC never reads the reference: it runs; without one it would start from it
    sim = ["simulate", "--params", "paper:thevenin", "--data", str(files["off"])]
    rc, err = _run(capsys, sim + ["--soc0", "0.34"])
    assert rc == 0 and err == []
    rc, err = _run(capsys, sim)
    assert rc == 2 and len(err) == 1 and f"column 'soc_ref', row {files['off_row']}:" in err[0]
