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

Beside the row a cell record keeps, for the reliability report:

* ``failures``: per failed run, why (the estimator's divergence reason, ``Estimate.failed_reason``, or "non-finite
  output"), the sample and time where it failed, and what the run looked like there (last good SOC and its SD, true
  SOC, measured current and voltage, predicted voltage, innovation and its variance);
* ``domain``: the estimate's domain report (:func:`socbench.domain.estimate_domain`), whose ``outside_fraction`` is
  the ``out_of_domain`` column (share of samples with the estimate outside the model's domain; an extra column).
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
#: columns beyond the DESIGN.md set (more keys are welcome there)
EXTRA_COLUMNS = ("out_of_domain",)
LEADERBOARD_COLUMNS = (("model", "estimator", "scenario", "n_runs") + METRIC_COLUMNS + ("failed_runs",)
                       + EXTRA_COLUMNS)
#: failed runs described per cell record (the rest are counted)
MAX_FAILURES_LISTED = 20


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

    def scenario_group(self, group: str) -> list[str]:
        """Catalog scenarios of a group (``measured``); empty for an unknown group."""
        from ..scenarios.catalog import group_names

        return group_names(group)

    def scenario_missing(self, name: str) -> str | None:
        """Why scenario ``name`` cannot run here (its data is missing), or None."""
        missing = getattr(self.load_scenario(name), "missing", None)
        return missing() if missing is not None else None

    def fit_model(self, model: str, profile, mode: str):
        """Fit ``model`` on a characterisation: a test record, or a measured scenario's
        :class:`~socbench.scenarios.measured.Characterisation` (which knows how it is fitted)."""
        if hasattr(profile, "fit"):
            return profile.fit(model, mode)
        from ..identify import fit_model

        return fit_model(model, profile, mode=mode)

    def filter_noise(self, estimator: str, model, scenario, profile, noise: str, cache_key=None):
        """``(model, noise, model-error dict or None)`` the estimator runs with: the noise recipe
        (:mod:`socbench.estimators.model_error`) measured on the scenario's noise records with this fitted model and
        calibrated on its validation loads (:mod:`socbench.estimators.nis_calibration`, for the estimator's form),
        unless ``noise == "sensor"``, the estimator is the coulomb counter (it never reads the voltage) or the
        scenario has no records to measure it on (then its sensor noise alone)."""
        sensor = scenario.sensor_noise()
        records = getattr(scenario, "noise_records", None)
        if noise == "sensor" or estimator == "coulomb" or records is None:
            return model, sensor, None
        from ..estimators import estimator_class, model_error, nis_calibration

        measured_on = getattr(scenario, "noise_measured_on", lambda: "")()
        noise_records, fingerprint = _records(scenario, "noise_records")
        # keyed by what the records hold, not by the scenario: scenarios of one cell and lab share one measurement
        key = (cache_key if fingerprint is not None else None, fingerprint, measured_on)
        stats = _cached(key, lambda: model_error.estimate(model, noise_records, measured_on=measured_on))
        form = estimator_class(estimator).model_error_form
        if getattr(scenario, "calibration_records", None) is not None:
            # the recipe's size checked on the validation loads: NIS mean 1 there
            calibration, calibration_key = _records(scenario, "calibration_records")
            stats = _cached(key + (calibration_key, form, sensor),
                            lambda: nis_calibration.calibrate(model, sensor, stats, calibration, form))
        run_model, tuned = model_error.apply(model, sensor, stats, profile,
                                             extra_voltage_sd=getattr(scenario, "added_voltage_sd", 0.0), form=form)
        return run_model, tuned, stats.to_dict()

    def run_estimator(self, estimator, profile, soc0, params, seed):
        """Run on the data's SOC axis when the record counts its reference with its own capacity
        (:func:`socbench.socaxis.run_on_data_axis`), else exactly ``estimator.run(profile, soc0, seed=seed)``."""
        from ..socaxis import run_on_data_axis, soc_axis

        axis = soc_axis(params, profile)
        if axis.identity:
            return estimator.run(profile, soc0, seed=seed)
        return run_on_data_axis(estimator, profile, axis, soc0=soc0, seed=seed)

    def make_model(self, model: str, params):
        from ..models import make_model

        return make_model(model, params)

    def make_estimator(self, estimator: str, model, noise, **options):
        from ..estimators import make_estimator

        # the posterior states are kept so that the cell's domain report counts the model's guards along them
        return make_estimator(estimator, model, noise=noise, **{"store_states": True, **options})

    def score(self, estimate, profile) -> dict:
        from ..estimators.scoring import score

        return score(estimate, profile)


# ---------------------------------------------------------------------- per-process caches
# A worker runs many cells of the same scenario: realize it once per (scenario, seeds), not once per cell.
_SCENARIOS: dict = {}
_REALIZED: dict = {}
_MAX_REALIZED = 4
# the model error a fitted model makes on a scenario's noise records, and its calibration: once per (fit, records'
# fingerprints) per process, so scenarios that share their records share one measurement
_MODEL_ERROR: dict = {}
_MAX_MODEL_ERROR = 64
# a scenario's noise and calibration records with their fingerprints: once per (scenario, method) per process
_RECORDS: dict = {}
_MAX_RECORDS = 8


def _memo(cache: dict, key, compute, limit: int | None = None):
    """``compute()`` once per ``key`` in ``cache`` (this process); at ``limit`` entries the oldest one goes first."""
    if key not in cache:
        if limit is not None and len(cache) >= limit:
            cache.pop(next(iter(cache)))
        cache[key] = compute()
    return cache[key]


def _cached(key: tuple, compute):
    """``compute()`` once per ``key`` in this process (:data:`_MODEL_ERROR`; a key led by None: never kept)."""
    return compute() if key[0] is None else _memo(_MODEL_ERROR, key, compute, _MAX_MODEL_ERROR)


def _records(scenario, method: str):
    """``(records, fingerprint)``: ``scenario.<method>()`` once per scenario and method in this process
    (:data:`_RECORDS`), with the fingerprints of its records (:func:`~socbench.study.grid.profile_fingerprint`);
    a scenario without a name: never kept, fingerprint None."""
    from .grid import profile_fingerprint

    name = getattr(scenario, "name", None)
    if name is None:
        return list(getattr(scenario, method)()), None

    def compute():
        records = list(getattr(scenario, method)())
        return records, tuple(profile_fingerprint(p) for p in records)

    return _memo(_RECORDS, (name, method), compute, _MAX_RECORDS)


def _scenario(toolkit: Toolkit, name: str):
    return _memo(_SCENARIOS, (type(toolkit).__qualname__, name), lambda: toolkit.load_scenario(name))


def _realized(toolkit: Toolkit, name: str, seeds: tuple):
    def compute():
        scen = _scenario(toolkit, name)
        soc0 = np.broadcast_to(np.asarray(scen.initial_soc(list(seeds)), dtype=float), (len(seeds),)).copy()
        return scen, scen.realize(list(seeds)), soc0

    return _memo(_REALIZED, (type(toolkit).__qualname__, name, seeds), compute, _MAX_REALIZED)


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
    rec = {"row": row, "error": None, "trace": None, "run_soc_rmse": None, "run_failed": [True] * n_runs,
           "failures": [], "domain": None, "model_error": None, "nis_band": None}
    try:
        fit = job["fit"]
        if fit.get("params") is None:
            raise RuntimeError(f"fit of {job['model']} failed: {fit.get('error')}")
        scen, profile, soc0 = _realized(toolkit, job["scenario"], seeds)
        _, params = params_from_dict(fit["params"])
        model = toolkit.make_model(job["model"], params)
        run_model, noise, stats = toolkit.filter_noise(job["estimator"], model, scen, profile,
                                                       job.get("noise", "model"), job.get("fit_key"))
        est = toolkit.make_estimator(job["estimator"], run_model, noise, **job.get("options", {}))
        t1 = time.perf_counter()
        estimate = toolkit.run_estimator(est, profile, soc0, params, int(job["seed"]))
        # the filter's time: without the post-hoc domain report computed in run()
        elapsed = time.perf_counter() - t1 - float((getattr(estimate, "domain", None) or {}).get("seconds", 0.0))
        rec.update(reduce_cell(estimate, profile, elapsed, toolkit.score))
        rec["row"] = {**row, **rec["row"]}
        for f in rec["failures"]:
            f["seed"] = seeds[f["run"]]
            f["model_nonfinite_soc"] = nonfinite_soc(model, f)
        rec["model_error"] = stats
        rec["nis_band"] = _nis_band(rec["row"], profile)
    except (KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:  # the estimator (or model) threw: every run of the batch failed
        rec["error"] = _error_text(exc)
    rec["seconds"] = time.perf_counter() - t0
    return rec


def _nis_band(row: dict, profile):
    """The two-sided 95 % χ² band of the cell's NIS mean (every sample of the runs that did not fail)."""
    from ..metrics import chi2_band

    ok = row["n_runs"] - row["failed_runs"]
    return list(chi2_band(1, ok * profile.n)) if ok > 0 and row.get("nis_mean") is not None else None


def _empty_row(job: dict, n_runs: int) -> dict:
    row = {"model": job["model"], "estimator": job["estimator"], "scenario": job["scenario"], "n_runs": n_runs}
    row.update({c: None for c in METRIC_COLUMNS})
    row["failed_runs"] = n_runs
    row.update({c: None for c in EXTRA_COLUMNS})
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

    flagged = np.broadcast_to(np.asarray(estimate.failed, dtype=bool), (R,)).copy()
    failed = flagged.copy()
    nonfinite_outputs = 0
    for arr in (soc, std, vpred, _as_runs(estimate.innovation, R, T), _as_runs(estimate.innovation_var, R, T)):
        bad = ~np.isfinite(arr)
        nonfinite_outputs += int(bad.sum())
        failed |= bad.any(axis=1)  # belt and braces: a non-finite output is a failed run
    ok = ~failed

    row = {c: None for c in METRIC_COLUMNS + EXTRA_COLUMNS}
    row["failed_runs"] = int(failed.sum())
    domain = getattr(estimate, "domain", None) or None
    if domain:
        row["out_of_domain"] = domain.get("outside_fraction")
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
    # a metric that came out NaN/inf is stored empty (JSON has no NaN) but named here: the sweep reports them
    nonfinite_metrics = sorted(k for k, v in row.items() if v is not None and k != "failed_runs"
                               and not np.isfinite(float(v)))
    row = {k: (v if k == "failed_runs" else _finite_or_none(v)) for k, v in row.items()}
    return {"row": row, "trace": trace, "run_soc_rmse": [_finite_or_none(x) for x in run_rmse],
            "run_failed": failed.tolist(), "failures": describe_failures(estimate, profile, failed, flagged),
            "domain": domain, "nonfinite": {"outputs": nonfinite_outputs, "metrics": nonfinite_metrics}}


def nonfinite_soc(model, failure: dict, sigmas: float = 3.0, points: int = 61):
    """``[lowest, highest]`` SOC within ``soc ± sigmas·soc_std`` of a failure where the model itself gives a
    non-finite voltage or next state (other states at rest, the failure's current), or None: tells a model that is
    undefined where the filter's spread reaches (a sigma point or particle beyond its domain) from a filter that
    diverged on its own."""
    z, sd = failure.get("soc"), failure.get("soc_std")
    if z is None or sd is None:
        return None
    zs = z + np.linspace(-sigmas, sigmas, points) * sd
    i = np.full(points, failure.get("current_a") or 0.0)
    try:
        with np.errstate(all="ignore"):
            x = model.x0(zs, (points,))
            y = model.output(x, i)[0]
            xn = model.step(x, i, 1.0)[0]
        bad = ~np.isfinite(y) | ~np.all(np.isfinite(xn), axis=-1)
    except Exception as exc:  # a model that raises there (strict mode) is undefined there too
        return {"error": _error_text(exc)}
    return [float(zs[bad].min()), float(zs[bad].max())] if bad.any() else None


def describe_failures(estimate, profile, failed, flagged, limit: int = MAX_FAILURES_LISTED) -> list[dict]:
    """Why and where each failed run failed (module docstring), for the first ``limit`` failed runs."""
    R, T = profile.n_runs, profile.n
    reasons = estimate.failure_reasons() if hasattr(estimate, "failure_reasons") else ["diverged"] * R
    at = np.broadcast_to(np.asarray(getattr(estimate, "failed_at", np.full(R, -1))), (R,))

    def value(a, r, k):
        if a is None:
            return None
        return _finite_or_none(_as_runs(a, R, T)[r, k])

    out = []
    for r in np.flatnonzero(failed)[:limit]:
        r = int(r)
        if flagged[r] and at[r] >= 0:
            k, why = int(at[r]), reasons[r] or "diverged"
        else:  # not flagged by the estimator: the first non-finite output
            bad = ~np.isfinite(_as_runs(estimate.soc, R, T)[r]) | ~np.isfinite(_as_runs(estimate.v_pred, R, T)[r])
            k, why = (int(np.argmax(bad)) if bad.any() else 0), "non-finite output"
        last = max(k - 1, 0)  # outputs from the failure on repeat the last good values
        out.append({"run": r, "step": k, "time_s": float(profile.time_s[k]), "reason": why,
                    "soc": value(estimate.soc, r, last), "soc_std": value(estimate.soc_std, r, last),
                    "soc_true": value(profile.soc_ref, r, k), "current_a": value(profile.current_a, r, k),
                    "voltage_v": value(profile.voltage_v, r, k), "v_pred": value(estimate.v_pred, r, last),
                    "innovation": value(estimate.innovation, r, last),
                    "innovation_var": value(estimate.innovation_var, r, last)})
    return out


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
