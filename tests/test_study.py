"""The study machinery: grid, store, resume, failure accounting, and the same table on every backend.

The scenario, identification and estimator pieces are small stand-ins defined here (real socbench models, rint and
thevenin on their paper parameters), so these tests exercise the machinery without depending on the speed or the
numbers of the real filters. tests/test_leaderboard_cli.py runs the real pieces end to end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from socbench.estimators import Estimate
from socbench.models import make_model, paper_params
from socbench.profile import Profile, ProfileMeta
from socbench.study import Toolkit

T = 240
DT = 5.0


@dataclass(frozen=True)
class Fit:
    params: object
    rmse_v: float


@dataclass(frozen=True)
class StandinScenario:
    """A constant 1 C discharge of the paper pack with noisy voltage; ``amps`` sets the load."""

    name: str
    amps: float = 22.0
    char_amps: float = 22.0
    soc0_error: float = 0.05

    def characterisation(self, seed: int = 0) -> Profile:
        t = np.arange(100) * 10.0
        i = np.where((np.arange(100) // 10) % 2 == 0, self.char_amps, 0.0)
        return Profile(t, i, voltage_v=22.0 - 0.01 * i, meta=ProfileMeta(name=f"{self.name}-hppc", capacity_ah=22.0))

    def realize(self, seeds) -> Profile:
        t = np.arange(T) * DT
        cur, volt = [], []
        model = make_model("thevenin", paper_params("thevenin"))
        for s in seeds:
            rng = np.random.default_rng(1000 + int(s))
            i = self.amps * (1.0 + 0.1 * rng.standard_normal(T))
            cur.append(i)
        cur = np.array(cur)
        sim = model.simulate(Profile(t, cur), soc0=np.full(len(seeds), 0.95))
        for r, s in enumerate(seeds):
            rng = np.random.default_rng(2000 + int(s))
            volt.append(sim.voltage_v[r] + 0.005 * rng.standard_normal(T))
        return Profile(t, cur, voltage_v=np.array(volt), soc_ref=sim.soc.clip(0, 1),
                       meta=ProfileMeta(name=self.name, capacity_ah=22.0))

    def initial_soc(self, seeds):
        return np.full(len(seeds), 0.95 - self.soc0_error)

    def sensor_noise(self):
        return {"voltage_sd": 0.005}


SCENARIOS = {
    "s-light": StandinScenario("s-light", amps=11.0),
    "s-heavy": StandinScenario("s-heavy", amps=33.0, char_amps=30.0),  # another truth cell
    # same truth cell and characterisation as s-light, another load: must share s-light's fits
    "s-light-b": StandinScenario("s-light-b", amps=15.0),
}


class CountingEstimator:
    """Coulomb counting with the model's output as v_pred; ``blend`` pulls SOC towards the voltage (a crude filter)."""

    def __init__(self, model, blend: float = 0.0, fail_runs=(), explode: bool = False):
        self.model, self.blend, self.fail_runs, self.explode = model, blend, tuple(fail_runs), explode

    def run(self, profile, soc0, P0=None, seed=None):
        if self.explode:
            raise FloatingPointError("stand-in estimator diverged on purpose")
        R, n = profile.n_runs, profile.n
        x = self.model.x0(np.asarray(soc0, dtype=float), (R,))
        soc = np.empty((R, n))
        std = np.empty((R, n))
        vp = np.empty((R, n))
        dts = profile.dt
        rng = np.random.default_rng(seed)
        jitter = 1e-9 * rng.standard_normal()  # seeded: must be identical across backends
        for k in range(n):
            y = self.model.output(x, profile.current_a[:, k])[0]
            vp[:, k] = y
            if self.blend:
                x[:, 0] += self.blend * (profile.voltage_v[:, k] - y) / 20.0
            soc[:, k] = x[:, 0] + jitter
            std[:, k] = 0.02 + 0.0001 * k
            if k + 1 < n:
                x = self.model.step(x, profile.current_a[:, k], dts[k])[0]
        failed = np.zeros(R, dtype=bool)
        for r in self.fail_runs:
            if r < R:
                failed[r] = True
                soc[r, n // 2:] = np.nan  # a real diverged run; the study must not let this reach an aggregate
        innov = profile.voltage_v - vp
        return Estimate(profile.time_s, soc, std, vp, innov, np.full((R, n), 0.005**2), failed,
                        np.where(failed, n // 2, -1), np.zeros((R, n), bool), np.zeros((R, n), bool))


#: counts calls in this process (serial backend) so tests can see what was recomputed
CALLS = {"fit": 0, "cell": 0}


class StandinToolkit(Toolkit):
    """Toolkit with the stand-ins; ``fail_fit`` names models whose fit raises."""

    def __init__(self, fail_fit=(), interrupt_after=None):
        self.fail_fit = tuple(fail_fit)
        self.interrupt_after = interrupt_after

    def model_names(self):
        return ["rint", "thevenin"]

    def estimator_names(self):
        return ["count", "blend", "halfbad", "explode"]

    def scenario_names(self):
        return list(SCENARIOS)

    def load_scenario(self, name):
        return SCENARIOS[name]

    def fit_model(self, model, profile, mode):
        CALLS["fit"] += 1
        if model in self.fail_fit:
            raise RuntimeError(f"{model} did not converge")
        # a "fit" that depends on the characterisation: R0 scaled by its peak current
        params = paper_params(model)
        scale = float(np.max(profile.current_a)) / 22.0
        r0 = params["R0"]
        params = params.with_values(R0={"const": float(r0(0.5)) * scale})
        return Fit(params, 0.001 * scale)

    def make_estimator(self, estimator, model, noise, **options):
        CALLS["cell"] += 1
        if self.interrupt_after is not None and CALLS["cell"] > self.interrupt_after:
            raise KeyboardInterrupt
        if estimator == "count":
            return CountingEstimator(model)
        if estimator == "blend":
            return CountingEstimator(model, blend=0.5)
        if estimator == "halfbad":
            return CountingEstimator(model, fail_runs=(0,))
        if estimator == "explode":
            return CountingEstimator(model, explode=True)
        raise KeyError(estimator)


# ====================================================================== tests
import json  # noqa: E402
import os  # noqa: E402

import pandas as pd  # noqa: E402
import pytest  # noqa: E402

from socbench.errors import ConfigError  # noqa: E402
from socbench.metrics import voltage_error_stats  # noqa: E402
from socbench.report import write_report  # noqa: E402
from socbench.study import LEADERBOARD_COLUMNS, METRIC_COLUMNS, Store, StudyConfig, parse_names, run_study  # noqa: E402

SEEDS = (0, 1, 2)


def small_config(estimators=("count", "blend"), scenarios=("s-light", "s-heavy"), models=("rint", "thevenin")):
    return StudyConfig(models=models, estimators=estimators, scenarios=scenarios, seeds=SEEDS)


def comparable(frame: pd.DataFrame) -> pd.DataFrame:
    """The table without the wall-time column (the only column that is not a function of the configuration)."""
    return frame.drop(columns=["us_per_step"]).reset_index(drop=True)


@pytest.fixture(autouse=True)
def _reset_counters():
    CALLS.update(fit=0, cell=0)


def test_rows_have_the_design_columns_and_match_an_independent_computation(tmp_path):
    res = run_study(small_config(), tmp_path / "store", toolkit=StandinToolkit(), progress=False)
    frame = res.frame()
    assert list(frame.columns) == list(LEADERBOARD_COLUMNS)
    assert len(frame) == 8 and set(frame["n_runs"]) == {3} and set(frame["failed_runs"]) == {0}
    # counting from a SOC guess 0.05 low, with the truth's own current: the SOC error is -0.05 all the way
    counted = frame[frame.estimator == "count"]
    assert np.allclose(counted["soc_rmse"], 0.05, atol=1e-6) and np.allclose(counted["soc_max_abs"], 0.05, atol=1e-6)
    # voltage stats of thevenin+count on s-light, recomputed here from the scenario and the model directly
    scen = SCENARIOS["s-light"]
    prof = scen.realize(SEEDS)
    model = make_model("thevenin", StandinToolkit().fit_model("thevenin", scen.characterisation(), "paper").params)
    sim = model.simulate(prof.with_(soc_ref=None), soc0=scen.initial_soc(SEEDS))
    want = voltage_error_stats(prof.voltage_v.ravel(), sim.voltage_v.ravel())
    row = frame[(frame.model == "thevenin") & (frame.estimator == "count") & (frame.scenario == "s-light")].iloc[0]
    assert row.v_rmse == pytest.approx(want["rmse_v"], rel=1e-9)
    assert row.v_mean == pytest.approx(want["mean_v"], rel=1e-9)
    assert row.v_sd == pytest.approx(want["sd_v"], rel=1e-9)
    assert row.v_max == pytest.approx(want["max_v"], rel=1e-9)
    # NIS with S = (5 mV)^2, NEES and 3-sigma share with the stand-in's sigma = 0.02 + 1e-4 k
    assert row.nis_mean == pytest.approx(np.mean((prof.voltage_v - sim.voltage_v) ** 2) / 0.005**2, rel=1e-9)
    sd = 0.02 + 1e-4 * np.arange(prof.n)
    assert row.nees_mean == pytest.approx(np.mean(0.05**2 / sd**2), rel=1e-5)
    assert row.frac_within_3sigma == pytest.approx(np.mean(0.05 <= 3 * sd), abs=1e-12)


def test_fits_are_computed_once_per_characterisation_and_model(tmp_path):
    cfg = small_config(scenarios=("s-light", "s-light-b", "s-heavy"))
    res = run_study(cfg, tmp_path / "store", toolkit=StandinToolkit(), progress=False)
    # s-light and s-light-b share their characterisation: 2 models × 2 distinct characterisations
    assert CALLS["fit"] == 4
    assert len(list((tmp_path / "store" / "fits").glob("*.json"))) == 4
    assert res.fits[("s-light", "rint")]["key"] == res.fits[("s-light-b", "rint")]["key"]
    assert res.fits[("s-light", "rint")]["key"] != res.fits[("s-heavy", "rint")]["key"]
    # a second run finds everything in the store: nothing fitted, nothing run
    CALLS.update(fit=0, cell=0)
    again = run_study(cfg, tmp_path / "store", toolkit=StandinToolkit(), progress=False)
    assert CALLS == {"fit": 0, "cell": 0} and not again.computed and len(again.reused) == cfg.n_cells
    pd.testing.assert_frame_equal(again.frame(), res.frame())


def test_interrupted_study_resumes_without_recomputing_finished_cells(tmp_path):
    store = tmp_path / "store"
    with pytest.raises(KeyboardInterrupt):
        run_study(small_config(), store, toolkit=StandinToolkit(interrupt_after=3), progress=False)
    cells = sorted((store / "cells").glob("*.json"))
    assert len(cells) == 3
    before = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in cells}
    fits_before = len(list((store / "fits").glob("*.json")))
    assert 1 <= fits_before < 4
    first_log = Store(store).run_logs()[0]
    assert first_log["interrupted"] is True and len(first_log["computed"]) == 3

    CALLS.update(fit=0, cell=0)
    resumed = run_study(small_config(), store, toolkit=StandinToolkit(), progress=False)
    assert CALLS["fit"] == 4 - fits_before  # stored fits are not fitted again
    assert CALLS["cell"] == 5 and len(resumed.computed) == 5 and len(resumed.reused) == 3
    assert set(resumed.reused) == {k.removesuffix(".json") for k in before}
    for p in cells:
        assert (p.stat().st_mtime_ns, p.read_bytes()) == before[p.name]
    assert not list(store.rglob("*.tmp"))

    fresh = run_study(small_config(), tmp_path / "fresh", toolkit=StandinToolkit(), progress=False)
    pd.testing.assert_frame_equal(comparable(resumed.frame()), comparable(fresh.frame()))


def test_results_of_other_code_are_reported_stale_and_recomputed_on_request(tmp_path):
    store = tmp_path / "store"
    first = run_study(small_config(), store, toolkit=StandinToolkit(), progress=False)
    assert not first.stale
    victim = store / "cells" / f"{first.computed[0]}.json"
    rec = json.loads(victim.read_text())
    victim.write_text(json.dumps({**rec, "code": "older code"}))  # as if a filter had been edited since
    CALLS.update(fit=0, cell=0)
    again = run_study(small_config(), store, toolkit=StandinToolkit(), progress=False)
    assert again.stale == [first.computed[0]] and CALLS["cell"] == 0 and not again.computed
    fresh = run_study(small_config(), store, toolkit=StandinToolkit(), progress=False, recompute_stale=True)
    assert fresh.computed == [first.computed[0]] and CALLS["cell"] == 1 and not fresh.stale
    assert json.loads(victim.read_text())["code"] != "older code"


def test_a_corrupt_or_stray_store_file_is_ignored_and_recomputed(tmp_path):
    store = tmp_path / "store"
    first = run_study(small_config(), store, toolkit=StandinToolkit(), progress=False)
    victim = store / "cells" / f"{first.computed[0]}.json"
    victim.write_text('{"key": "trunc')  # what a non-atomic writer could leave behind
    (store / "cells" / ".abc.json.123.tmp").write_text("half")
    CALLS.update(fit=0, cell=0)
    again = run_study(small_config(), store, toolkit=StandinToolkit(), progress=False)
    assert again.computed == [first.computed[0]] and CALLS["cell"] == 1
    assert not list(store.rglob("*.tmp"))
    pd.testing.assert_frame_equal(comparable(again.frame()), comparable(first.frame()))


def test_failed_runs_are_counted_and_no_aggregate_is_nan(tmp_path):
    cfg = small_config(estimators=("count", "halfbad", "explode"), scenarios=("s-light",))
    res = run_study(cfg, tmp_path / "store", toolkit=StandinToolkit(fail_fit=("rint",)), progress=False)
    frame = res.frame().set_index(["model", "estimator"])
    metrics = list(METRIC_COLUMNS)
    # thevenin: halfbad loses run 0 (it turns NaN half-way); the aggregates come from runs 1, 2 and are finite
    assert frame.loc[("thevenin", "halfbad"), "failed_runs"] == 1
    # ... and the cell record says where and with what state (the stand-in gives no reason: "diverged")
    half = next(r for r in res.cells if r["row"]["model"] == "thevenin" and r["row"]["estimator"] == "halfbad")
    (f,) = half["failures"]
    assert (f["run"], f["seed"], f["step"], f["reason"]) == (0, SEEDS[0], T // 2, "diverged")
    assert f["time_s"] == (T // 2) * DT and np.isfinite(f["soc"]) and np.isfinite(f["current_a"])
    assert np.isfinite(frame.loc[("thevenin", "halfbad"), metrics].astype(float)).all()
    assert frame.loc[("thevenin", "halfbad"), "soc_rmse"] == pytest.approx(0.05, abs=1e-6)
    # explode throws: every run failed, metrics empty
    assert frame.loc[("thevenin", "explode"), "failed_runs"] == 3
    assert frame.loc[("thevenin", "explode"), metrics].isna().all()
    # rint's fit failed: all its cells count all runs as failed and say why
    for est in cfg.estimators:
        assert frame.loc[("rint", est), "failed_runs"] == 3
    assert all("did not converge" in r["error"] for r in res.cells if r["row"]["model"] == "rint")

    out = tmp_path / "out"
    write_report(res, out, figures=False)
    text = (out / "leaderboard.csv").read_text()
    assert "nan" not in text.lower() and "inf" not in text.lower()
    csv = pd.read_csv(out / "leaderboard.csv")
    partial = csv[csv.failed_runs < csv.n_runs]
    assert len(partial) == 2 and np.isfinite(partial[metrics].to_numpy(dtype=float)).all()
    # work that raised is kept for the report but retried next time: a fixed fit now succeeds, the thrower throws again
    CALLS.update(fit=0, cell=0)
    again = run_study(cfg, tmp_path / "store", toolkit=StandinToolkit(), progress=False)
    assert CALLS["fit"] == 1  # rint only; thevenin's fit was fine and is reused
    retried = {(r["row"]["model"], r["row"]["estimator"]) for r in again.cells if r["key"] in again.computed}
    assert retried == {("rint", "count"), ("rint", "halfbad"), ("rint", "explode"), ("thevenin", "explode")}
    assert again.frame().set_index(["model", "estimator"]).loc[("rint", "halfbad"), "failed_runs"] == 1

    # the stored records are strict JSON (no NaN tokens)
    def no_constants(c):
        raise AssertionError(f"a stored record holds {c}")

    for p in (tmp_path / "store" / "cells").glob("*.json"):
        json.loads(p.read_text(), parse_constant=no_constants)


def test_process_backend_gives_the_serial_table(tmp_path):
    serial = run_study(small_config(), tmp_path / "a", toolkit=StandinToolkit(), progress=False)
    proc = run_study(small_config(), tmp_path / "b", backend="process", jobs=2, toolkit=StandinToolkit(),
                     progress=False)
    pd.testing.assert_frame_equal(comparable(proc.frame()), comparable(serial.frame()))
    assert sorted(os.listdir(tmp_path / "a" / "cells")) == sorted(os.listdir(tmp_path / "b" / "cells"))


def test_dask_local_cluster_gives_the_serial_table(tmp_path):
    distributed = pytest.importorskip("distributed")
    serial = run_study(small_config(), tmp_path / "a", toolkit=StandinToolkit(), progress=False)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://",
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        dask = run_study(small_config(), tmp_path / "b", backend="dask", scheduler=cluster.scheduler_address,
                         toolkit=StandinToolkit(), progress=False)
    pd.testing.assert_frame_equal(comparable(dask.frame()), comparable(serial.frame()))


def test_unknown_names_are_config_errors():
    with pytest.raises(ConfigError, match="unknown model 'nope'"):
        parse_names("rint,nope", ["rint", "thevenin"], "model", ())
    with pytest.raises(ConfigError, match="listed twice"):
        parse_names("rint,rint", ["rint"], "model", ())
    assert parse_names(None, ["a", "b"], "model", ("b",)) == ("b",)


def test_report_names_the_best_cell_and_draws_the_figures(tmp_path):
    res = run_study(small_config(), tmp_path / "store", toolkit=StandinToolkit(), progress=False)
    out = tmp_path / "out"
    rep = write_report(res, out)
    csv = pd.read_csv(out / "leaderboard.csv")
    md = (out / "leaderboard.md").read_text()
    for scen in ("s-light", "s-heavy"):
        sub = csv[csv.scenario == scen]
        best = sub.loc[sub.soc_rmse.idxmin()]
        assert f"On {scen} the best combination is {best.model} + {best.estimator}" in md
        for prefix in ("heatmap", "soc_error", "voltage"):
            png = out / f"{prefix}_{scen}.png"
            assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(rep["figures"]) == 6


def test_scenarios_of_one_cell_and_lab_share_one_measured_noise_recipe(tmp_path, monkeypatch):
    """The recipe and its calibration are keyed by what their records hold: the two default flight scenarios (same
    truth cell, lab tests and validation flights) measure the model's error once; a scenario with other validation
    flights measures it again."""
    from socbench.estimators import model_error, nis_calibration
    from socbench.scenarios import load_scenario
    from socbench.study import cell

    calls = {"estimate": 0, "calibrate": 0}

    def counted(name, fn):
        def wrapper(*a, **k):
            calls[name] += 1
            return fn(*a, **k)
        return wrapper

    monkeypatch.setattr(model_error, "estimate", counted("estimate", model_error.estimate))
    monkeypatch.setattr(nis_calibration, "calibrate", counted("calibrate", nis_calibration.calibrate))
    monkeypatch.setattr(cell, "_MODEL_ERROR", {})
    monkeypatch.setattr(cell, "_RECORDS", {})
    other = tmp_path / "other.toml"
    other.write_text('extends = "flight-0kg"\n[validation]\npayloads_kg = [3.0]\n')
    model = make_model("thevenin", paper_params("thevenin"))
    tk = Toolkit()
    seen = []
    for name in ("flight-0kg", "flight-10kg", str(other)):
        scen = load_scenario(name)
        _, noise, stats = tk.filter_noise("ekf", model, scen, scen.realize([0]), "model", cache_key="fit")
        seen.append((calls["estimate"], calls["calibrate"], stats["records"]))
    assert [s[:2] for s in seen] == [(1, 1), (1, 1), (2, 2)]
    assert seen[0][2] == seen[1][2] != seen[2][2]
