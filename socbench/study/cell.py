"""The work a study does, as plain top-level functions a worker process (local or Dask) can run.

* :func:`compute_fit`  fit one model on one characterisation test;
* :func:`compute_cell` run one estimator on one fitted model over all seeds of one scenario, as one batch, and reduce
  the batch to one leaderboard row plus a compact trace for the figures.

Both return plain JSON-able dicts and never raise for a failure of the thing they measure (a fit that does not converge,
a filter that throws): the failure is recorded (``error``) and the runs count in ``failed_runs``. Only interrupts and
resource errors propagate.

Aggregates of a cell (DESIGN.md leaderboard columns) pool every sample of every run that did not fail:

* ``soc_rmse`` = √mean((ẑ − z)²), ``soc_max_abs`` = max|ẑ − z| over runs and time, ``nis_mean`` = mean(ν²/S),
  ``nees_mean`` = mean((ẑ − z)²/σ²), ``frac_within_3sigma`` = share of samples with |ẑ − z| ≤ 3σ: from
  :func:`socbench.estimators.scoring.score` on the runs that did not fail;
* ``v_mean, v_rmse, v_sd, v_max``: the voltage error ``v_meas − v_pred`` (the filter's predicted voltage, before the
  update) with :func:`socbench.metrics.voltage_error_stats` (SD with N − 1, max = max|e|);
* ``us_per_step``: wall time of ``estimator.run`` on the batch divided by runs × steps, in µs.

A run fails when the estimator flags it (``Estimate.failed``) or when any of its outputs is not finite. A metric with
nothing to average (every run failed, or the estimator defines no such quantity, e.g. no innovation variance) is
``None``: an empty field in ``leaderboard.csv``, never NaN.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ..metrics import voltage_error_stats

#: points kept per stored trace (enough for a figure, small enough for a JSON file per cell)
TRACE_POINTS = 400

#: the metric columns of a leaderboard row, in the DESIGN.md order
METRIC_COLUMNS = ("soc_rmse", "soc_max_abs", "v_mean", "v_rmse", "v_sd", "v_max", "nis_mean", "nees_mean",
                  "frac_within_3sigma", "us_per_step")
LEADERBOARD_COLUMNS = ("model", "estimator", "scenario", "n_runs") + METRIC_COLUMNS + ("failed_runs",)


class Toolkit:
    """The pieces of socbench a study calls (docs/ARCHITECTURE.md). Picklable; imports happen on first use.

    Tests hand the study a subclass with small stand-ins; the CLI always uses this one.
    """

    def model_names(self) -> list[str]:
        from ..models import model_names

        return list(model_names())

    def estimator_names(self) -> list[str]:
        from .. import estimators

        names = getattr(estimators, "estimator_names", None)
        if names is not None:
            return list(names())
        return list(estimators.ESTIMATORS)

    def scenario_names(self) -> list[str]:
        from ..scenarios import scenario_names

        return list(scenario_names())

    def load_scenario(self, name: str):
        from ..scenarios import load_scenario

        return load_scenario(name)

    def fit_model(self, model: str, profile, mode: str):
        from ..identify import fit_model

        return fit_model(model, profile, mode=mode)

    def make_model(self, model: str, params):
        from ..models import make_model

        return make_model(model, params)

    def make_estimator(self, estimator: str, model, noise, **options):
        from ..estimators import make_estimator

        return make_estimator(estimator, model, noise=noise, **options)

    def score(self, estimate, profile) -> dict:
        from ..estimators.scoring import score

        return score(estimate, profile)


# ---------------------------------------------------------------------- per-process caches
# A worker runs many cells of the same scenario: realize it once per (scenario, seeds), not once per cell.
_SCENARIOS: dict = {}
_REALIZED: dict = {}
_MAX_REALIZED = 4


def _scenario(toolkit: Toolkit, name: str):
    key = (type(toolkit).__qualname__, name)
    if key not in _SCENARIOS:
        _SCENARIOS[key] = toolkit.load_scenario(name)
    return _SCENARIOS[key]


def _realized(toolkit: Toolkit, name: str, seeds: tuple):
    key = (type(toolkit).__qualname__, name, seeds)
    if key not in _REALIZED:
        scen = _scenario(toolkit, name)
        profile = scen.realize(list(seeds))
        soc0 = np.broadcast_to(np.asarray(scen.initial_soc(list(seeds)), dtype=float), (len(seeds),)).copy()
        if len(_REALIZED) >= _MAX_REALIZED:
            _REALIZED.pop(next(iter(_REALIZED)))
        _REALIZED[key] = (scen, profile, soc0)
    return _REALIZED[key]


def _error_text(exc: BaseException) -> str:
    text = f"{type(exc).__name__}: {exc}".strip()
    return text.splitlines()[0][:300] if text else type(exc).__name__


# ---------------------------------------------------------------------- fits
def compute_fit(toolkit: Toolkit, model: str, characterisation, mode: str) -> dict:
    """Fit ``model`` on ``characterisation``: ``{"model", "params" (JSON form) | None, "rmse_v", "error", ...}``."""
    from ..models.params import params_to_dict

    t0 = time.perf_counter()
    try:
        res = toolkit.fit_model(model, characterisation, mode)
        params = params_to_dict(model, res.params)
        rec = {"model": model, "params": params, "rmse_v": _finite_or_none(getattr(res, "rmse_v", None)),
               "warnings": [str(w) for w in getattr(res, "warnings", ())], "error": None}
    except (KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:  # a fit that fails is a result: its cells count all their runs as failed
        rec = {"model": model, "params": None, "rmse_v": None, "warnings": [], "error": _error_text(exc)}
    rec["seconds"] = time.perf_counter() - t0
    return rec


# ---------------------------------------------------------------------- cells
def compute_cell(toolkit: Toolkit, job: dict) -> dict:
    """Run one cell (module docstring). ``job``: model, estimator, scenario, seeds, fit (record), options, seed."""
    from ..models.params import params_from_dict

    t0 = time.perf_counter()
    seeds = tuple(int(s) for s in job["seeds"])
    n_runs = len(seeds)
    row = _empty_row(job, n_runs)
    rec = {"row": row, "error": None, "trace": None, "run_soc_rmse": None, "run_failed": [True] * n_runs}
    try:
        fit = job["fit"]
        if fit.get("params") is None:
            raise RuntimeError(f"fit of {job['model']} failed: {fit.get('error')}")
        scen, profile, soc0 = _realized(toolkit, job["scenario"], seeds)
        _, params = params_from_dict(fit["params"])
        model = toolkit.make_model(job["model"], params)
        est = toolkit.make_estimator(job["estimator"], model, scen.sensor_noise(), **job.get("options", {}))
        t1 = time.perf_counter()
        estimate = est.run(profile, soc0, seed=int(job["seed"]))
        elapsed = time.perf_counter() - t1
        rec.update(reduce_cell(estimate, profile, elapsed, toolkit.score))
        rec["row"] = {**row, **rec["row"]}
    except (KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:  # the estimator (or model) threw: every run of the batch failed
        rec["error"] = _error_text(exc)
    rec["seconds"] = time.perf_counter() - t0
    return rec


def _empty_row(job: dict, n_runs: int) -> dict:
    row = {"model": job["model"], "estimator": job["estimator"], "scenario": job["scenario"], "n_runs": n_runs}
    row.update({c: None for c in METRIC_COLUMNS})
    row["failed_runs"] = n_runs
    return row


def _finite_or_none(x):
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


def _as_runs(a, n_runs: int, T: int):
    if a is None:
        return None
    a = np.asarray(a, dtype=float)
    return np.broadcast_to(a, (n_runs, T)) if a.ndim < 2 else a.reshape(n_runs, T)


def reduce_cell(estimate, profile, elapsed_s: float, score=None) -> dict:
    """One leaderboard row (metric columns + failed_runs), per-run SOC RMSE and a compact trace from a batch.

    ``score`` is :func:`socbench.estimators.scoring.score` (SOC, NIS and NEES aggregates over the runs that did not
    fail); the voltage columns come from :func:`socbench.metrics.voltage_error_stats` on the same runs.
    """
    if score is None:
        from ..estimators.scoring import score
    T = profile.n
    R = profile.n_runs
    truth = _as_runs(profile.get("soc_ref"), R, T)
    meas = _as_runs(profile.voltage_v, R, T)
    soc = _as_runs(estimate.soc, R, T)
    std = _as_runs(estimate.soc_std, R, T)
    vpred = _as_runs(estimate.v_pred, R, T)

    failed = np.broadcast_to(np.asarray(estimate.failed, dtype=bool), (R,)).copy()
    for arr in (soc, std, vpred, _as_runs(estimate.innovation, R, T), _as_runs(estimate.innovation_var, R, T)):
        failed |= ~np.isfinite(arr).all(axis=1)  # belt and braces: a non-finite output is a failed run
    ok = ~failed

    row = {c: None for c in METRIC_COLUMNS}
    row["failed_runs"] = int(failed.sum())
    row["us_per_step"] = 1e6 * elapsed_s / (R * T)
    run_rmse = [None] * R
    trace = None
    if ok.any():
        with np.errstate(all="ignore"):  # failed runs may hold anything; they are masked out of every aggregate
            sc = score(dataclasses.replace(estimate, failed=failed), profile)
        for k in ("soc_rmse", "soc_max_abs", "nis_mean", "nees_mean", "frac_within_3sigma"):
            row[k] = sc.get(k)
        per_run = sc.get("runs", {}).get("soc_rmse")
        if per_run is not None:
            run_rmse = [float(per_run[r]) if ok[r] else None for r in range(R)]
        vs = voltage_error_stats(meas[ok].ravel(), vpred[ok].ravel())
        row.update(v_mean=vs["mean_v"], v_rmse=vs["rmse_v"], v_sd=vs["sd_v"], v_max=vs["max_v"])
        r0 = int(np.argmax(ok))
        trace = make_trace(profile.time_s, soc[r0] - truth[r0], std[r0], meas[r0], vpred[r0])
        trace["run"] = r0
    row = {k: (v if k == "failed_runs" else _finite_or_none(v)) for k, v in row.items()}
    return {"row": row, "trace": trace, "run_soc_rmse": [_finite_or_none(x) for x in run_rmse],
            "run_failed": failed.tolist()}


def _compact(a) -> list[float]:
    return [float(f"{x:.6g}") for x in np.asarray(a, dtype=float)]


def make_trace(time_s, soc_err, soc_std=None, v_meas=None, v_pred=None, points: int = TRACE_POINTS) -> dict:
    """Downsample one run's traces to at most ``points`` samples (evenly spaced in index, ends kept)."""
    n = len(time_s)
    idx = np.unique(np.round(np.linspace(0, n - 1, min(points, n))).astype(int))
    out = {"time_s": _compact(np.asarray(time_s)[idx]), "soc_err": _compact(np.asarray(soc_err)[idx])}
    for name, arr in (("soc_std", soc_std), ("v_meas", v_meas), ("v_pred", v_pred)):
        out[name] = None if arr is None else _compact(np.asarray(arr)[idx])
    return out
