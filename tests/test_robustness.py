"""The robustness sweep (benchmarks/robustness.py) on a small slice in CI, and the failure accounting it reads."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from socbench.estimators import estimator_names, make_estimator
from socbench.estimators.safety import DIVERGENCE_REASONS, diverged
from socbench.models import make_model, paper_params
from socbench.study.cell import nonfinite_soc, reduce_cell

REPO = Path(__file__).resolve().parents[1]


def _sweep_module():
    spec = importlib.util.spec_from_file_location("robustness", REPO / "benchmarks" / "robustness.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_ci_slice_of_the_robustness_sweep_has_no_nan_or_inf(tmp_path, capsys):
    """Every registered estimator on rint and fang (whose log term once sent every UKF run to NaN), three seeds of
    the short flight; the sweep's own analysis must find no NaN/inf, and writes its JSON and report."""
    sweep = _sweep_module()
    doc = tmp_path / "reliability.md"
    code = sweep.main(["--seeds", "3", "--models", "rint,fang", "--scenarios", "flight-10kg", "--backend", "serial",
                       "--out", str(tmp_path / "out"), "--doc", str(doc)])
    capsys.readouterr()
    assert code == 0
    an = json.loads((tmp_path / "out" / "robustness.json").read_text())
    n_cells = 2 * len(estimator_names())  # every registered estimator
    assert an["cells"] == n_cells and an["runs"] == 3 * n_cells
    assert an["nan_inf"] == {"outputs": 0, "metrics": 0, "table": 0}
    assert an["failed_runs"] == 0 and not an["cells_that_threw"]
    text = doc.read_text()
    assert "**NaN/inf: 0**" in text and f"{n_cells} cells, {3 * n_cells} runs" in text
    # rerunning the same command resumes: nothing is recomputed
    assert sweep.main(["--seeds", "3", "--models", "rint,fang", "--scenarios", "flight-10kg", "--backend", "serial",
                       "--out", str(tmp_path / "out"), "--no-doc"]) == 0
    assert f"{n_cells} in the store, 0 to run" in capsys.readouterr().err


def test_divergence_reasons_are_coded_in_order():
    x = np.array([[0.5, 0.0], [np.nan, 0.0], [0.5, 0.0], [0.5, 0.0], [0.5, 0.0], [0.5, 0.0]])
    P = np.tile(np.eye(2) * 1e-4, (6, 1, 1))
    P[2, 1, 1] = np.inf
    P[3, 0, 0] = 2.0
    nis = np.array([1.0, 1.0, 1.0, 1.0, np.nan, 1e12])
    codes = diverged(x, P, nis, var_max=1.0, nis_max=1e10)
    assert codes.tolist() == [0, 1, 2, 3, 4, 5]
    assert [DIVERGENCE_REASONS[c] for c in codes[1:]] == ["non-finite state", "non-finite covariance",
                                                          "SOC variance above var_max", "non-finite NIS",
                                                          "NIS above nis_max"]


@pytest.mark.parametrize("estimator", ["ekf", "ukf", "pf"])
def test_a_diverged_run_is_described_with_its_reason_step_and_state(estimator):
    """A NIS ceiling no real innovation passes: every run fails at the first update, and the cell record says so."""
    from socbench.loads import constant_current

    m = make_model("thevenin", paper_params("thevenin"))
    prof = constant_current(m.capacity_ah, 1.0, soc_span=0.03)
    v = m.simulate(prof, soc0=1.0).voltage_v
    prof = prof.with_(voltage_v=np.stack([v + 0.05, v - 0.05]), soc_ref=None)
    opts = {"nis_max": 1e-6, **({"n_particles": 50} if estimator in ("pf", "rbpf") else {})}
    est = make_estimator(estimator, m, **opts).run(prof, soc0=0.8, seed=0)
    assert est.failed.all() and (est.failed_at == 0).all()
    assert est.failure_reasons() == ["NIS above nis_max"] * 2
    rec = reduce_cell(est, prof, 1.0)
    assert rec["row"]["failed_runs"] == 2 and rec["nonfinite"]["outputs"] == 0
    for r, f in enumerate(rec["failures"]):
        assert (f["run"], f["step"], f["reason"]) == (r, 0, "NIS above nis_max")
        assert f["soc"] == pytest.approx(0.8) and f["voltage_v"] == pytest.approx(prof.voltage_v[r, 0])
        assert nonfinite_soc(m, f) is None  # the model is fine there: the filter was told to fail


def test_the_model_probe_finds_where_a_model_is_undefined():
    """Fang as the fit once left it (τ2 = 0.007, so ln(τ2 + 1 − z) is undefined above z = 1.007), probed across a
    UKF's spread at SOC 1 ± 0.1: unguarded, the probe names the undefined range; with the B6 floor (static_terms.py)
    the model is finite all across."""
    from socbench.models.params import Constant
    from socbench.models.static_terms import Fang

    p = paper_params("fang")
    p = p.__class__(**{**p.__dict__, "values": {**p.values, "tau2": Constant(0.007)}})

    class UnguardedFang(Fang):
        def term(self, z, temp=None, guards=None):
            k0, k1 = self.p("K0", z)[0], self.p("K1", z)[0]
            t1, t2 = self.p("tau1", z)[0], self.p("tau2", z)[0]
            with np.errstate(all="ignore"):
                return -k0 * np.log(t1 + z) + k1 * np.log(t2 + 1.0 - z), np.zeros_like(z)

    failure = {"soc": 1.0, "soc_std": 0.1, "current_a": 0.0}
    lo, hi = nonfinite_soc(UnguardedFang(p), failure)
    assert 1.007 <= lo <= 1.007 + 0.6 / 60 + 1e-9 and hi == pytest.approx(1.3)
    assert nonfinite_soc(make_model("fang", p), failure) is None
