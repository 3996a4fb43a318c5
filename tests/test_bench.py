"""``socbench bench``: the JSON contract on tiny sizes, the identical-results check, option errors. No timing thresholds
(the machines are shared and noisy: speed targets live in the benchmark itself, see docs/performance.md)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from socbench.bench import TINY, compare, monte_carlo_sweep
from socbench.cli import main
from socbench.estimators import SensorNoise, make_estimator
from socbench.models import make_model, paper_params

REQUIRED = [f"{n}_{k}" for n in ("ekf", "ukf", "pf")
            for k in ("batched_us_per_run_step", "filterpy_us_per_step", "speedup")] + ["fit_all_models_s"]


@pytest.fixture(scope="module")
def quick_json(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "bench.json"
    rc = main(["bench", "--quick", "--tiny", "--json", str(out)])
    return rc, json.loads(out.read_text())


def test_quick_bench_writes_every_required_key_finite_and_positive(quick_json):
    rc, res = quick_json
    assert rc == 0
    for key in REQUIRED:
        assert isinstance(res[key], float) and math.isfinite(res[key]) and res[key] > 0, key
        if key.endswith("_speedup"):  # the ratio of the two timings it is derived from
            name = key.split("_")[0]
            ratio = res[f"{name}_filterpy_us_per_step"] / res[f"{name}_batched_us_per_run_step"]
            assert res[key] == pytest.approx(ratio, rel=1e-12)
    assert res["default_leaderboard_s"] is None  # quick mode skips the leaderboard
    m = res["machine"]
    assert m["cpu_count"] >= 1 and m["numpy_version"] == np.__version__ and m["python_version"].count(".") == 2
    assert res["repeats"] >= 3 and res["complete"] is True
    for name in ("ekf", "ukf", "pf"):  # every repeat is kept, each figure is their median
        rows = res[f"{name}_scaling_rows"]
        engines = {r["engine"] for r in rows}
        assert engines == {"bare filterpy", "socbench numpy", "socbench compiled"}
        runs = res["sizes"]["pf_runs" if name == "pf" else "scale_runs"]
        for row in rows:
            assert len(row["repeats_s"]) == res["repeats"] and row["runs"] in runs
            assert row["us_per_run_step"] == pytest.approx(float(np.median(row["repeats_s"])) * 1e6, rel=1e-12)
        for engine in ("numpy", "compiled"):
            for R, us in res[f"{name}_{engine}_us_per_run_step"].items():
                assert res[f"{name}_{engine}_speedup_vs_bare"][R] == pytest.approx(
                    res[f"{name}_bare_us_per_step"] / us, rel=1e-12)
        head = str(res[f"{name}_headline_runs"])
        assert res[f"{name}_batched_us_per_run_step"] == res[f"{name}_compiled_us_per_run_step"][head]
        assert res[f"{name}_filterpy_us_per_step"] == res[f"{name}_bare_us_per_step"]


def test_quick_bench_checks_identical_results(quick_json):
    _, res = quick_json
    assert res["identical_results"] is True
    for name in ("ekf", "ukf", "pf"):
        assert res[f"{name}_identical"] is True
        assert 0 <= res[f"{name}_max_abs_diff"] <= res["tolerance"] == 1e-9


def test_compare_reports_a_difference_and_a_flag_mismatch():
    m = make_model("thevenin", paper_params("thevenin"))
    profile, soc0, P0 = monte_carlo_sweep(m, TINY.runs, TINY.steps, seed=3)
    est = make_estimator("ekf", m, SensorNoise(0.01, 0.2)).run(profile, soc0=soc0, P0=P0)
    same = compare(est, est)
    assert same == {"max_abs_diff": 0.0, "flags_equal": True, "identical": True}
    est.v_pred[1, 5] += 1e-6
    off = compare(est, make_estimator("ekf", m, SensorNoise(0.01, 0.2)).run(profile, soc0=soc0, P0=P0))
    assert off["max_abs_diff"] == pytest.approx(1e-6, rel=1e-6) and off["identical"] is False
    est.v_pred[1, 5] -= 1e-6
    est.gated[0, 3] = ~est.gated[0, 3]
    flag = compare(est, make_estimator("ekf", m, SensorNoise(0.01, 0.2)).run(profile, soc0=soc0, P0=P0))
    assert flag["flags_equal"] is False and flag["identical"] is False


def test_sweep_runs_differ_and_start_from_their_own_guess():
    m = make_model("dp", paper_params("dp"))
    profile, soc0, P0 = monte_carlo_sweep(m, 4, 30, seed=1)
    assert profile.current_a.shape == profile.voltage_v.shape == (4, 30)
    assert np.ptp(profile.voltage_v[:, 10]) > 0 and np.ptp(soc0) > 0
    assert P0.shape == (m.n_states,) and np.all(P0 > 0)


@pytest.mark.parametrize("argv", [["--repeats", "2"], ["--estimators", "kf"]])
def test_bad_options_are_user_errors(tmp_path, capsys, argv):
    assert main(["bench", "--quick", "--tiny", "--json", str(tmp_path / "b.json"), *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("socbench bench: error:") and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "b.json").exists()
