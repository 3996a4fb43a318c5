"""Real cells at every temperature: temperature-aware models, the noise recipe, and the measured-data scenarios.

Writes ``docs/real_data.md`` (every number in it comes from this run) and ``docs/figures/real_data_*.png``:

1. **Identification** — every registered model fitted on the five Panasonic 18650PF HPPC tests (25, 10, 0, −10,
   −20 °C) on one SOC axis (:func:`socbench.identify.temperature.fit_temperatures`, paper mode), and on the 25 °C
   HPPC alone.
2. **Best model** — the lowest mean open-loop voltage RMSE on the *validation* records, the Cycle_1 runs at the five
   temperatures (never a US06: the US06 runs are scored below).
3. **Noise recipe** — the model error of each fit measured on the validation records
   (:mod:`socbench.estimators.model_error`): the five Cycle_1 runs for the five-temperature fit, the 25 °C Cycle_1
   alone for the 25 °C fit (a characterisation campaign at 25 °C only).
4. **The US06 at each temperature** — EKF and UKF from a guess 20 SOC points below the reference (every run starts
   full), ``soc0_sd`` 0.1, on the record at its own 10 Hz, SOC on the data's axis (:mod:`socbench.socaxis`): the best
   model with both fits, the next two models with the five-temperature fit, and coulomb counting.
5. **Leaderboard of the measured group** (``socbench leaderboard --scenarios measured``: Panasonic, CALCE, DJI) on the
   two best models (``--lb-models``), coulomb/EKF/UKF, 3 seeds; and the default flight scenarios' NIS with the recipe
   (every model, the default estimators, 10 seeds) beside the sensor-only covariance on two models.

Every step is cached in ``--cache`` (JSON per fit and per run): an interrupted run resumes, a finished one rewrites
the document in seconds.

    SOCBENCH_DATA_DIR=/work/shared/data python benchmarks/real_data.py [--cache real-data-cache] [--jobs 2]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from socbench.datasets.panasonic import find_panasonic, load_panasonic  # noqa: E402
from socbench.estimators import SensorNoise, estimator_class, make_estimator, nis_calibration  # noqa: E402
from socbench.estimators import model_error as recipe  # noqa: E402
from socbench.estimators.scoring import score  # noqa: E402
from socbench.identify.select import FIT_SETTINGS, PER_TEMPERATURE, select_temperature_fit  # noqa: E402
from socbench.metrics import voltage_error_stats  # noqa: E402
from socbench.models import load_params, make_model, model_names, save_params  # noqa: E402
from socbench.socaxis import run_on_data_axis, soc_axis  # noqa: E402

TAGS = ("25degC", "10degC", "0degC", "n10degC", "n20degC")
LABEL = {"25degC": "25 °C", "10degC": "10 °C", "0degC": "0 °C", "n10degC": "−10 °C", "n20degC": "−20 °C"}
SOC0_ERROR = -0.20
SOC0_SD = 0.1
VALIDATION_FILTERS = ("ekf", "ukf")
#: seeds of each particle-filter run on the US06 (section 4f)
PF_SEEDS = 5
#: the recording instruments, as declared by the measured scenarios (catalog/measured/panasonic.toml)
SENSOR = SensorNoise(voltage_sd=0.002, current_sd=0.02)
TARGET = {"soc_rmse": 0.015, "coverage": 0.9, "ekf_ukf": 0.005}
CITE = {
    "panasonic": "P. Kollmeyer, *Panasonic 18650PF Li-ion Battery Data*, Mendeley Data, doi:10.17632/wykht8y7tg.1 "
                 "(2018), University of Wisconsin-Madison (`panasonic_18650pf/PROVENANCE.md`)",
    "calce": "CALCE Battery Research Group, University of Maryland, A123 LiFePO4 dynamic and low-current OCV tests "
             "(https://calce.umd.edu/battery-data), third-party CSV exports (`calce_a123_lfp/PROVENANCE.md`)",
    "dji": "K. Shah, G. Ballard, A. Schmidt, M. Schwager, *Multidrone aerial surveys of penguin colonies in "
           "Antarctica*, Sci. Robot. 5, eabc3000 (2020): WADL flight logs, k2shah/wadl (`uav_dji_m100/PROVENANCE.md`)",
}


# ------------------------------------------------------------------------------------------------ data & cache
def _record(tag: str, test: str):
    return load_panasonic(find_panasonic(os.environ["SOCBENCH_DATA_DIR"], tag, test)[0])


class Cache:
    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)

    def path(self, *parts) -> Path:
        p = self.folder.joinpath(*parts)
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def json(self, name: str, compute):
        p = self.path(name)
        if p.exists():
            return json.loads(p.read_text())
        out = compute()
        tmp = p.with_suffix(".tmp")
        tmp.write_text(json.dumps(out, default=_jsonable))
        tmp.replace(p)
        return out


def _jsonable(v):
    if hasattr(v, "tolist"):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    raise TypeError(type(v).__name__)


# ------------------------------------------------------------------------------------------------ 1-2: fits
def _validation_rmse(m, tags) -> dict:
    """Open-loop voltage RMSE of model ``m`` on the Cycle_1 run of each temperature in ``tags``."""
    out = {}
    for t in tags:
        e = recipe.residual(m, _record(t, "Cycle"))
        out[t] = float(np.sqrt(np.mean(e * e)))
    return out


def fit_job(args) -> dict:
    """Fit ``model`` on the HPPCs of ``tags``, the setting chosen by validation on the Cycle_1 runs of those
    temperatures (a 25 °C campaign validates on the 25 °C run alone; :func:`socbench.identify.select_temperature_fit`:
    every setting of :data:`~socbench.identify.FIT_SETTINGS`, and over several temperatures a setting per temperature
    and the charge-transfer term, each kept if it lowers the mean); save its PARAMS.json; its RMSE on every Cycle_1
    run."""
    model, tags, params_path = args
    t0 = time.perf_counter()
    sel = select_temperature_fit(model, [_record(t, "HPPC") for t in tags], [_record(t, "Cycle") for t in tags])
    tried = {label: ({**out, "rmse_v": dict(zip(tags, out["rmse_v"]))} if "rmse_v" in out else out)
             for label, out in sel.tried.items()}
    if PER_TEMPERATURE in tried and "per_temperature" in tried[PER_TEMPERATURE]:
        tried[PER_TEMPERATURE]["per_temperature"] = dict(zip(tags, tried[PER_TEMPERATURE]["per_temperature"]))
    res = sel.fit
    save_params(params_path, model, res.params, fit=res.fit_summary())
    val = _validation_rmse(make_model(model, res.params), TAGS)
    return {"model": model, "seconds": time.perf_counter() - t0, "validation_rmse_v": val, "setting": sel.chosen,
            "settings": tried, "fit": res.fit_summary(), "temps": list(res.temps), "capacities": list(res.capacities),
            "notes": list(res.notes)}


#: `socbench fit` as a user without --mode auto runs it (section 4g): variant -> (extra arguments, what it is)
DEFAULT_VARIANTS = {
    "hppc-only": ((), "the defaults: the paper's mode, the noise recipe on the HPPCs"),
    "paper-validated": (("--validation", "Cycle"), "the noise recipe on the drive cycles, the paper's mode kept"),
}


def cli_fit(cache: Cache, model: str, variant: str) -> dict:
    """Run ``socbench fit`` on the five HPPCs (and the variant's extra arguments, "Cycle" standing for the five
    Cycle_1 files) into the cache: ``{"params": path, "model_error": the file's block, "command", "stdout"}``."""
    import subprocess

    def files(test):
        return [str(find_panasonic(os.environ["SOCBENCH_DATA_DIR"], t, test)[0]) for t in TAGS]

    extra = []
    for a in DEFAULT_VARIANTS[variant][0]:
        extra += files(a) if a == "Cycle" else [a]
    out = cache.path("defaults", f"{model}_{variant}.json")
    cmd = [sys.executable, "-m", "socbench.cli", "fit", "--data", *files("HPPC"), "--model", model, *extra,
           "--out", str(out)]
    done = subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True, text=True)
    block = json.loads(out.read_text())["model_error"]
    shown = " ".join(["socbench fit --data $HPPCS --model", model]
                     + ["$CYCLES" if a == "Cycle" else a for a in DEFAULT_VARIANTS[variant][0]]
                     + [f"--out {model}.json"])
    return {"params": str(out), "model_error": block, "stdout": done.stdout, "command": shown}


# ------------------------------------------------------------------------------------------------ 4: runs
def run_job(args) -> dict:
    """One filter on one record (default the US06): the recipe's noise in the form the filter takes, a guess 20 points
    low, SOC on the data's axis; the record bin-averaged to ``resolution`` seconds (0: as recorded). Optional: the
    record, the guess error, and a number of seeds (the record run that many times as one batch, each with its own
    random numbers: the particle filters; the per-run SOC RMSE and 3σ coverage are kept)."""
    model, params_path, stats_dict, tag, est_name, noise_mode, trace_path, resolution, *rest = args
    test, soc0_error, n_seeds = (list(rest) + ["US06", SOC0_ERROR, 1][len(rest):])[:3]
    name, params = load_params(params_path)
    m = make_model(name, params)
    prof = _record(tag, test)
    if resolution > 0:
        prof = recipe.bin_average(prof, resolution)
    stats = recipe.ModelErrorStats.from_dict(stats_dict) if stats_dict else None
    unscheduled = noise_mode == "model-unscheduled"  # the ablation: the recipe with the full Jacobian
    no_mid = noise_mode == "model-no-mid"  # the ablation: the recipe without its mid-period state
    run_model, noise = recipe.apply(m, SENSOR, stats, prof, noise="sensor" if est_name == "coulomb" else
                                    "model" if unscheduled or no_mid else noise_mode,
                                    form=estimator_class(est_name).model_error_form)
    if unscheduled:
        run_model.schedule_soc = False
    if no_mid:
        run_model, noise = recipe.without_mid(run_model, noise)
    est = make_estimator(est_name, run_model, noise, soc0_sd=SOC0_SD)
    axis = soc_axis(params, prof)
    one = prof
    if n_seeds > 1:
        prof = prof.with_(current_a=np.tile(prof.current_a, (n_seeds, 1)),
                          voltage_v=np.tile(prof.voltage_v, (n_seeds, 1)))
    t0 = time.perf_counter()
    r = run_on_data_axis(est, prof, axis, soc0=float(one.soc_ref[0]) + soc0_error, soc0_sd=SOC0_SD, seed=0)
    seconds = time.perf_counter() - t0
    s = score(r, prof)
    idx = np.unique(np.round(np.linspace(0, one.n - 1, 2500)).astype(int))
    if trace_path:
        np.savez_compressed(trace_path, t=one.time_s[idx], err=(r.soc[0] - one.soc_ref)[idx], sd=r.soc_std[0][idx],
                            temp=one.temperature_c[idx])
    out = {k: s[k] for k in ("soc_rmse", "soc_max_abs", "frac_within_3sigma", "nis_mean", "nis_band", "rmse_v",
                             "nees_mean", "failed_runs")}
    out.update({"seconds": seconds, "n": one.n, "axis": axis.to_dict(), "filter_voltage_sd": noise.voltage_sd,
                "t_start": float(one.temperature_c[0]), "t_max": float(one.temperature_c.max())})
    if n_seeds > 1:
        out.update({"seeds": n_seeds, "runs_soc_rmse": s["runs"]["soc_rmse"],
                    "runs_within_3sigma": s["runs"]["frac_within_3sigma"]})
    return out


def residual_job(args) -> dict:
    """Open-loop voltage error of a fit on the US06 (or ``test``) of ``tag`` (for the figure and the voltage table),
    and how its slow part follows the load: the least-squares line of the 10 s mean error on the 5-minute mean
    current (``load_slope_v_per_a``), the record's mean |current|."""
    params_path, tag, path, *test = args
    name, params = load_params(params_path)
    prof = _record(tag, test[0] if test else "US06")
    e = recipe.residual(make_model(name, params), prof)
    st = voltage_error_stats(prof.voltage_v, prof.voltage_v - e)
    smooth = recipe.moving_average(prof.time_s, e, 10.0)
    if path:
        idx = np.unique(np.round(np.linspace(0, prof.n - 1, 4000)).astype(int))
        np.savez_compressed(path, t=prof.time_s[idx], e=smooth[idx])
    load = recipe.moving_average(prof.time_s, prof.current_a, 300.0)
    slope = float(np.polyfit(load, smooth, 1)[0])
    out = {k: st[k] for k in ("rmse_v", "mean_v", "sd_v", "max_v")}
    out.update({"slow_rms_v": float(np.sqrt(np.mean(smooth ** 2))), "load_slope_v_per_a": slope,
                "mean_abs_current_a": float(np.mean(np.abs(prof.current_a)))})
    return out


def load_warming(tag: str, test: str = "US06") -> list:
    """``[T at the record's start, T when the load starts (|I| above 0.1 A), T's maximum after that]`` [°C] of the
    cell thermocouple: the −10 °C US06 starts after a rest in which the cell cools from 17 °C to the chamber's."""
    p = _record(tag, test)
    k = int(np.argmax(np.abs(p.current_a) > 0.1))
    return [float(p.temperature_c[0]), float(p.temperature_c[k]), float(np.max(p.temperature_c[k:]))]


def pulse_resistance() -> dict:
    """The 10 s discharge-pulse resistance of each HPPC per pulse current (median over the SOC levels where the pulse
    ran its full length), and its instantaneous part (the ohmic jump): how far a linear model is from the cell."""
    from socbench.identify.hppc import analyze_hppc

    out = {}
    for tag in TAGS:
        a = analyze_hppc(_record(tag, "HPPC"))
        rows = {}
        for p in a.pulses:
            if p.current_a <= 0 or p.duration_s < 9.0 or not np.isfinite(p.r_pulse):
                continue
            key = f"{p.current_a:.1f}"
            rows.setdefault(key, {"r10": [], "r0": []})
            rows[key]["r10"].append(p.r_pulse)
            rows[key]["r0"].append(p.r_inst)
        out[tag] = {k: {"current_a": float(k), "r10_ohm": float(np.median(v["r10"])),
                        "r0_ohm": float(np.median(v["r0"])), "levels": len(v["r10"])}
                    for k, v in sorted(rows.items(), key=lambda kv: float(kv[0]))}
    return out


def _pool(jobs: int):
    return ProcessPoolExecutor(max_workers=jobs) if jobs > 1 else None


def _guarded(fn, item):
    """``fn(item)``, or ``{"error": "..."}`` when it raises: one failed run is a result, not the end of the study."""
    try:
        return fn(item)
    except (KeyboardInterrupt, MemoryError):
        raise
    except Exception as exc:  # a model that refuses its state mid-run (a guard), a diverged filter...
        return {"error": f"{type(exc).__name__}: {exc}".splitlines()[0][:300]}


def cached_runs(cache: Cache, folder: str, pool, jobs: dict) -> dict:
    """Every result stored in ``cache/folder`` after running :func:`run_job` for each key of ``jobs`` (key → a
    function giving its arguments, called only for a key not stored yet); each result saved as it finishes."""
    todo = [k for k in jobs if not cache.path(folder, f"{k}.json").exists()]
    for j, out in _each(pool, run_job, [jobs[k]() for k in todo]):
        cache.path(folder, f"{todo[j]}.json").write_text(json.dumps(out, default=_jsonable))
    return {p.stem: json.loads(p.read_text()) for p in cache.path(folder).glob("*.json")}


def _each(pool, fn, items):
    """``(index, result)`` pairs as they finish (each saved at once by the caller: an interrupt loses little)."""
    from concurrent.futures import as_completed

    if pool is None:
        for k, x in enumerate(items):
            yield k, _guarded(fn, x)
        return
    futures = {pool.submit(_guarded, fn, x): k for k, x in enumerate(items)}
    for f in as_completed(futures):
        yield futures[f], f.result()


# ------------------------------------------------------------------------------------------------ 5: studies
def kept_wall(cache: Cache, name: str, seconds: float) -> float:
    """The wall time of study ``name`` in the run that computed its cells: the longest any run on this cache took
    (a later run reuses the stored cells in seconds, which would say nothing about the study's cost)."""
    p = cache.path(name, "wall_s.json")
    seconds = max(float(seconds), json.loads(p.read_text()) if p.exists() else 0.0)
    p.write_text(json.dumps(seconds))
    return seconds


def study(cache: Cache, name: str, models, estimators, scenarios, seeds: int, jobs: int, noise: str = "model"):
    """Run (or resume) a leaderboard study into ``cache/name``; returns the StudyResult and writes its report."""
    from socbench.report import write_report
    from socbench.study import Store, StudyConfig, run_study

    cfg = StudyConfig(models=tuple(models), estimators=tuple(estimators), scenarios=tuple(scenarios),
                      seeds=tuple(range(seeds)), noise=noise)
    res = run_study(cfg, Store(cache.path(name, "store")), backend="process" if jobs > 1 else "serial", jobs=jobs,
                    log=lambda m: print(f"  [{name}] {m}", flush=True))
    write_report(res, cache.path(name), figures=False)
    return res


# ------------------------------------------------------------------------------------------------ figures
def fig_soc(path: Path, cache: Cache, best: str, fits: list[str]):
    fig, axes = plt.subplots(len(TAGS), len(fits), figsize=(5.2 * len(fits), 2.1 * len(TAGS)), sharex="row",
                             squeeze=False)
    for row, tag in enumerate(TAGS):
        for col, fit in enumerate(fits):
            ax = axes[row, col]
            for est, color in (("ekf", "C0"), ("ukf", "C3")):
                p = cache.path("traces", f"{best}_{fit}_{est}_{tag}.npz")
                if not p.exists():
                    continue
                d = np.load(p)
                ax.plot(d["t"] / 60, 100 * d["err"], color=color, lw=0.9, label=f"{est.upper()} error")
                ax.fill_between(d["t"] / 60, -300 * d["sd"], 300 * d["sd"], color=color, alpha=0.15,
                                label=f"{est.upper()} ±3σ")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_ylim(-25, 25)
            ax.set_title(f"US06 {LABEL[tag]}, {best}, {'5-temperature fit' if fit == '5T' else '25 °C fit'}",
                         fontsize=9)
            ax.set_ylabel("SOC error [%]")
            if row == len(TAGS) - 1:
                ax.set_xlabel("time [min]")
            if row == 0 and col == 0:
                ax.legend(fontsize=7, ncol=2, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def fig_voltage(path: Path, cache: Cache, best: str, fits: list[str]):
    fig, axes = plt.subplots(len(TAGS), 1, figsize=(9, 1.9 * len(TAGS)), squeeze=False)
    for row, tag in enumerate(TAGS):
        ax = axes[row, 0]
        for fit, color in zip(fits, ("C0", "C1")):
            p = cache.path("residuals", f"{best}_{fit}_{tag}.npz")
            if p.exists():
                d = np.load(p)
                ax.plot(d["t"] / 60, 1000 * d["e"], color=color, lw=0.8,
                        label="5-temperature fit" if fit == "5T" else "25 °C fit")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("mV")
        ax.set_title(f"US06 {LABEL[tag]}: measured − {best} open loop (10 s mean)", fontsize=9)
        if row == 0:
            ax.legend(fontsize=7)
    axes[-1, 0].set_xlabel("time [min]")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def knee_start(model: str, scenario: str = "calce-dst", seeds=(0, 1, 2)) -> dict:
    """Why the EKF's band collapses on an LFP record that starts full: the scenario's fit and recipe (as the
    leaderboard runs them), the EKF, the iterated EKF and the UKF over ``seeds``; per filter the SOC error and SD
    one minute in, the SOC RMSE and the share within ±3σ; and the record's first voltage against the model's OCV at
    full and the OCV slope at the guess and at full."""
    from socbench.scenarios import load_scenario
    from socbench.study.cell import Toolkit

    tk = Toolkit()
    scen = load_scenario(scenario)
    fit = tk.fit_model(model, scen.characterisation(), "paper")
    m = make_model(model, fit.params)
    prof = scen.realize(list(seeds))
    soc0 = np.broadcast_to(np.asarray(scen.initial_soc(list(seeds)), dtype=float), (len(seeds),)).copy()
    minute = int(np.searchsorted(prof.time_s, prof.time_s[0] + 60.0))
    out = {"model": model, "scenario": scenario, "seeds": list(seeds), "filters": {}}
    for est_name in ("ekf", "iekf", "ukf"):
        run_model, noise, _ = tk.filter_noise(est_name, m, scen, prof, "model")
        est = tk.run_estimator(tk.make_estimator(est_name, run_model, noise), prof, soc0, fit.params, 0)
        s = score(est, prof)
        e = est.soc - prof.soc_ref
        out["filters"][est_name] = {"err_1min": float(np.median(e[:, minute])),
                                    "sd_1min": float(np.median(est.soc_std[:, minute])),
                                    "soc_rmse": s["soc_rmse"], "within_3sigma": s["frac_within_3sigma"]}
    ocv = fit.params.ocv
    zg = float(np.median(soc0))
    out.update({"guess": zg, "v0": float(np.median(prof.voltage_v[:, 0])), "ocv_full": float(ocv(1.0)),
                "slope_guess": float((ocv(zg + 0.01) - ocv(zg - 0.01)) / 0.02),
                "slope_full": float((ocv(1.0) - ocv(0.99)) / 0.01)})
    return out


def fig_dji(path: Path, cache: Cache, model: str) -> list:
    """The two DJI flight scenarios: counted reference, the pack's own SOC, the EKF (recipe) with its ±3σ."""
    from socbench.scenarios import load_scenario
    from socbench.study.cell import Toolkit

    tk = Toolkit()
    rows = []
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.4), squeeze=False)
    for ax, name in zip(axes[0], ("dji-flight-a", "dji-flight-b")):
        scen = load_scenario(name)
        fit = tk.fit_model(model, scen.characterisation(), "paper")
        m = make_model(model, fit.params)
        prof = scen.realize([0])
        run_model, noise, _ = tk.filter_noise("ekf", m, scen, prof, "model")
        est = tk.run_estimator(tk.make_estimator("ekf", run_model, noise), prof, scen.initial_soc([0]), fit.params, 0)
        t = prof.time_s / 60
        ref, bms = prof.soc_ref[0], prof.meta.extra["bms_soc"]
        ax.plot(t, 100 * ref, "k", lw=1.2, label="reference (counted from take-off)")
        ax.plot(t, 100 * bms, "C2--", lw=1.0, label="pack's own SOC (BMS)")
        ax.plot(t, 100 * est.soc[0], "C0", lw=1.0, label=f"EKF ({model}, recipe)")
        ax.fill_between(t, 100 * (est.soc[0] - 3 * est.soc_std[0]), 100 * (est.soc[0] + 3 * est.soc_std[0]),
                        color="C0", alpha=0.15)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("time [min]")
        ax.set_ylabel("SOC [%]")
        ax.legend(fontsize=7)
        e = est.soc[0] - ref
        rows.append({"scenario": name, "ekf_rmse": float(np.sqrt(np.mean(e * e))),
                     "ekf_cov": float(np.mean(np.abs(e) <= 3 * est.soc_std[0])),
                     "bms_rmse": float(np.sqrt(np.mean((bms - ref) ** 2))),
                     "bms_max": float(np.max(np.abs(bms - ref))), "minutes": float(t[-1])})
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return rows


# ------------------------------------------------------------------------------------------------ report helpers
def pc(x, d=2):
    return "—" if x is None else f"{100 * x:.{d}f}"


def mv(x, d=1):
    return "—" if x is None else f"{1000 * x:.{d}f}"


def nis_txt(r):
    if r.get("nis_mean") is None:
        return "—"
    b = r.get("nis_band")
    return f"{r['nis_mean']:.2f}" + (f" [{b[0]:.2f}, {b[1]:.2f}]" if b else "")


def ok(flag: bool) -> str:
    return "yes" if flag else "**no**"


# ------------------------------------------------------------------------------------------------ main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=str(ROOT / "real-data-cache"))
    ap.add_argument("--doc", default=str(ROOT / "docs" / "real_data.md"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seeds", type=int, default=3, help="seeds of the measured-group leaderboard (default 3)")
    ap.add_argument("--models", default=None, help="candidate models (default: every registered model)")
    ap.add_argument("--skip-studies", action="store_true", help="no leaderboard studies (sections 6-7 left out)")
    ap.add_argument("--lb-models", type=int, default=2,
                    help="models in the measured-group leaderboard: the best N on validation (default 2)")
    ap.add_argument("--lb-scenarios", default="*",
                    help="measured-group scenarios of the leaderboard, comma-separated shell patterns (default: all)")
    ap.add_argument("--skip-flights", action="store_true",
                    help="no default-flight-scenario studies (section 7 left out; the measured group still runs)")
    ap.add_argument("--flight-seeds", type=int, default=10, help="seeds of the default flight scenarios (default 10)")
    ap.add_argument("--resolution", type=float, default=0.0,
                    help="the filters run on the records bin-averaged to this many seconds (default 0: the records "
                         "as recorded, 10 Hz, as `socbench estimate` and the leaderboard run them; 1: the noise "
                         "recipe's resolution)")
    ap.add_argument("--slow-resolution", type=float, default=1.0,
                    help="the same for the iterated EKF and the particle filters (sections 4e-4f; default 1: at 10 Hz "
                         "their numpy loops take about ten minutes per record)")
    ap.add_argument("--shortlist", type=int, default=4,
                    help="models (best open-loop voltage on validation) whose filters are tried on the validation "
                         "records to choose the best (default 4)")
    args = ap.parse_args(argv)
    if not os.environ.get("SOCBENCH_DATA_DIR"):
        print("set SOCBENCH_DATA_DIR (the Panasonic, CALCE and DJI folders)", file=sys.stderr)
        return 2
    wall0 = time.perf_counter()
    load0 = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    cache = Cache(Path(args.cache))
    # the filter runs stored in the cache are at one resolution: a cache of another one would be read as this one's
    asked = {"resolution": args.resolution, "slow_resolution": args.slow_resolution}
    stored = cache.json("resolution.json", lambda: asked)
    if stored != asked:
        print(f"{args.cache}: its filter runs are at {stored}, not {asked}; use another --cache", file=sys.stderr)
        return 2
    pool = _pool(args.jobs)
    candidates = args.models.split(",") if args.models else list(model_names())

    # ---- 1-2: five-temperature fits of every candidate, validation on Cycle_1
    todo = [(m, TAGS, str(cache.path("fits", f"{m}_5T.json"))) for m in candidates
            if not cache.path("fits", f"{m}_5T.summary.json").exists()]
    for k, out in _each(pool, fit_job, todo):
        if "error" in out:
            print(f"fit {todo[k][0]} failed: {out['error']}", flush=True)
            continue
        cache.path("fits", f"{out['model']}_5T.summary.json").write_text(json.dumps(out))
        print(f"fit {out['model']}: validation " + ", ".join(f"{1000 * v:.0f}" for v in
                                                             out["validation_rmse_v"].values()) + " mV", flush=True)
    candidates = [m for m in candidates if cache.path("fits", f"{m}_5T.summary.json").exists()]
    fits = {m: json.loads(cache.path("fits", f"{m}_5T.summary.json").read_text()) for m in candidates}
    ranked = sorted(candidates, key=lambda m: np.mean(list(fits[m]["validation_rmse_v"].values())))
    # models that fit to the same numbers are one model here (PNGV = Thevenin and GNL = DP without the C0 integrator,
    # Liu = Tremblay2: ECM_SPEC §5.3, §0): the table compares three different ones
    top = []
    for m in ranked:
        val = np.array(list(fits[m]["validation_rmse_v"].values()))
        if not any(np.all(np.abs(val - np.array(list(fits[k]["validation_rmse_v"].values()))) < 1e-4) for k in top):
            top.append(m)  # equal to 0.1 mV at every temperature: one model

    # ---- 3: the noise recipe on the validation records
    def stats_for(model, fit):
        def compute():
            _, params = load_params(cache.path("fits", f"{model}_{fit}.json"))
            tags = TAGS if fit == "5T" else (fit[len("own_"):],) if fit.startswith("own_") else ("25degC",)
            m, cycles = make_model(model, params), [_record(t, "Cycle") for t in tags]
            # calibrated on the same records with the filters' sensor noise, as `socbench fit --validation` does
            return nis_calibration.calibrate_forms(m, SENSOR, recipe.estimate(m, cycles, measured_on="validation"),
                                                   cycles).to_dict()
        return cache.json(f"stats/{model}_{fit}.json", compute)

    # the filters themselves on the validation records (EKF and UKF, the recipe measured on those records, the
    # scoring protocol): the model whose filters both track the SOC best there is the best model; never a US06
    shortlist = top[: args.shortlist]
    vruns = cached_runs(cache, "validation", pool, {
        f"{m}_5T_{est}_{tag}": lambda m=m, est=est, tag=tag: (
            m, str(cache.path("fits", f"{m}_5T.json")), stats_for(m, "5T"), tag, est, "model", "", args.resolution,
            "Cycle")
        for m in shortlist for est in VALIDATION_FILTERS for tag in TAGS})

    def val_score(m):
        rs = [[vruns.get(f"{m}_5T_{est}_{t}") for est in VALIDATION_FILTERS] for t in TAGS]
        if any(r is None or "error" in r for pair in rs for r in pair):
            return np.inf
        # per temperature the worse of the two filters (the targets hold for both); the median over the
        # temperatures: one catastrophic temperature must not decide alone
        return float(np.median([max(r["soc_rmse"] for r in pair) for pair in rs]))

    top = sorted(shortlist, key=val_score) + top[args.shortlist:]
    best, top = top[0], top[:3]
    print(f"best on validation: {best}; top 3: {top}", flush=True)
    if not cache.path("fits", f"{best}_25.summary.json").exists():
        out = fit_job((best, ("25degC",), str(cache.path("fits", f"{best}_25.json"))))
        cache.path("fits", f"{best}_25.summary.json").write_text(json.dumps(out))
    fit25 = json.loads(cache.path("fits", f"{best}_25.summary.json").read_text())

    configs = [(best, "5T"), (best, "25")] + [(m, "5T") for m in top[1:]]
    stats = {cfg: stats_for(*cfg) for cfg in configs}

    # ---- 4: US06 runs
    jobs, keys = [], []
    for model, fit in configs:
        ests = ("ekf", "ukf", "coulomb") if (model, fit) == (best, "5T") else ("ekf", "ukf")
        for est in ests:
            for tag in TAGS:
                key = f"{model}_{fit}_{est}_{tag}"
                if not cache.path("runs", f"{key}.json").exists():
                    jobs.append((model, str(cache.path("fits", f"{model}_{fit}.json")), stats[(model, fit)], tag, est,
                                 "model", str(cache.path("traces", f"{key}.npz")), args.resolution))
                    keys.append(key)
    for k, out in _each(pool, run_job, jobs):
        cache.path("runs", f"{keys[k]}.json").write_text(json.dumps(out, default=_jsonable))
        if "error" in out:
            print(f"run {keys[k]} failed: {out['error']}", flush=True)
            continue
        print(f"run {keys[k]}: SOC RMSE {100 * out['soc_rmse']:.2f} %, within 3σ {out['frac_within_3sigma']:.3f}, "
              f"NIS {out['nis_mean']:.2f} ({out['seconds']:.0f} s)", flush=True)
    # the ablation: the best model's filters with the recipe but the full Jacobian (no parameter scheduling)
    fit5 = str(cache.path("fits", f"{best}_5T.json"))
    unsched = cached_runs(cache, "unscheduled", pool, {
        f"{best}_5T_{est}_{tag}": lambda est=est, tag=tag: (
            best, fit5, stats[(best, "5T")], tag, est, "model-unscheduled", "", args.resolution)
        for est in ("ekf", "ukf") for tag in TAGS})
    # the same filters without the recipe's mid-period state (what it changes on the measured records)
    nomid = cached_runs(cache, "nomid", pool, {
        f"{best}_5T_{est}_{tag}": lambda est=est, tag=tag: (
            best, fit5, stats[(best, "5T")], tag, est, "model-no-mid", "", args.resolution)
        for est in ("ekf", "ukf") for tag in TAGS})
    # the second ablation: the same filters started at the true SOC (what the 20-point initial error costs each), and
    # the iterated EKF from the 20-point start too ("_guess")
    truestart = cached_runs(cache, "truestart", pool, {
        f"{best}_5T_{est}_{tag}{suffix}": lambda est=est, tag=tag, err=err: (
            best, fit5, stats[(best, "5T")], tag, est, "model", "",
            args.slow_resolution if est == "iekf" else args.resolution, "US06", err)
        for est in ("ekf", "ukf", "iekf") for tag in TAGS
        for suffix, err in (("", 0.0), ("_guess", SOC0_ERROR)) if est == "iekf" or not suffix})
    # the same pair at the other resolution (1 s bins when the records run as recorded, else as recorded): what the
    # bin-averaging the recipe measures at would change in the must-show
    other = 1.0 if args.resolution == 0 else 0.0
    compare = cached_runs(cache, "resolution-compare", pool, {
        f"{best}_5T_{est}_{tag}": lambda est=est, tag=tag: (
            best, fit5, stats[(best, "5T")], tag, est, "model", "", other)
        for est in ("ekf", "ukf") for tag in TAGS})
    # the particle filters from the same 20-point start, each over PF_SEEDS seeds (their random numbers are part of the
    # result): the bootstrap PF (the recipe in its inflated form) and the Rao–Blackwellised PF (the recipe's states)
    particle = cached_runs(cache, "particle", pool, {
        f"{best}_{fit}_{est}_{tag}": lambda fit=fit, est=est, tag=tag: (
            best, str(cache.path("fits", f"{best}_{fit}.json")), stats[(best, fit)], tag, est, "model", "",
            args.slow_resolution, "US06", SOC0_ERROR, PF_SEEDS)
        for fit in ("5T", "25") for est in ("pf", "rbpf") for tag in TAGS})
    # what the two commands give a user who has only the HPPCs (section 4g): `socbench fit` with its defaults (the
    # paper's mode, the noise recipe on the identification records), and with --validation but not --mode auto
    default_fits = {variant: cache.json(f"defaults/{best}_{variant}.fit.json",
                                        lambda variant=variant: cli_fit(cache, best, variant))
                    for variant in DEFAULT_VARIANTS}
    defaults = cached_runs(cache, "defaults", pool, {
        f"{best}_{variant}_{est}_{tag}": lambda variant=variant, est=est, tag=tag: (
            best, default_fits[variant]["params"], default_fits[variant]["model_error"], tag, est, "model", "",
            args.resolution)
        for variant in DEFAULT_VARIANTS for est in ("ekf", "ukf") for tag in TAGS})
    # what a user with one temperature's tests runs (section 4h): each US06 beside a fit of its own temperature's HPPC
    # alone, its setting chosen on that temperature's Cycle_1, the recipe measured there (25 °C: the 25 °C fit)
    own_fit = {tag: "25" if tag == "25degC" else f"own_{tag}" for tag in TAGS}
    for tag, name in own_fit.items():
        if not cache.path("fits", f"{best}_{name}.summary.json").exists():
            out = fit_job((best, (tag,), str(cache.path("fits", f"{best}_{name}.json"))))
            cache.path("fits", f"{best}_{name}.summary.json").write_text(json.dumps(out))
    own_setting = {tag: json.loads(cache.path("fits", f"{best}_{name}.summary.json").read_text())["setting"]
                   for tag, name in own_fit.items()}
    own = cached_runs(cache, "own", pool, {
        f"{best}_{own_fit[tag]}_{est}_{tag}": lambda tag=tag, est=est: (
            best, str(cache.path("fits", f"{best}_{own_fit[tag]}.json")), stats_for(best, own_fit[tag]), tag, est,
            "model", "", args.resolution)
        for est in ("ekf", "ukf") for tag in TAGS})
    runs = {p.stem: json.loads(p.read_text()) for p in cache.path("runs").glob("*.json")}
    rjobs, rkeys = [], []
    for fit in ("5T", "25"):
        for tag in TAGS:
            key = f"{best}_{fit}_{tag}"
            if not cache.path("residuals", f"{key}.json").exists():
                rjobs.append((str(cache.path("fits", f"{best}_{fit}.json")), tag,
                              str(cache.path("residuals", f"{key}.npz"))))
                rkeys.append(key)
    for tag in TAGS:
        key = f"{best}_5T_{tag}_Cycle"  # the validation record, for the comparison with the scored one
        if not cache.path("residuals", f"{key}.json").exists():
            rjobs.append((str(cache.path("fits", f"{best}_5T.json")), tag, "", "Cycle"))
            rkeys.append(key)
    for k, out in _each(pool, residual_job, rjobs):
        cache.path("residuals", f"{rkeys[k]}.json").write_text(json.dumps(out))
    resid = {p.stem: json.loads(p.read_text()) for p in cache.path("residuals").glob("*.json")}
    if pool is not None:
        pool.shutdown()

    # ---- 5: studies
    lb = flights = flights_sensor = None
    if not args.skip_studies:
        from fnmatch import fnmatch

        from socbench.scenarios.catalog import group_names

        t0 = time.perf_counter()
        pats = args.lb_scenarios.split(",")
        lb_scen = [s for s in group_names("measured") if any(fnmatch(s, p) for p in pats)]
        lb = study(cache, "measured", top[: args.lb_models], ("coulomb", "ekf", "ukf"), lb_scen, args.seeds, args.jobs)
        lb_wall = kept_wall(cache, "measured", time.perf_counter() - t0)
    if not args.skip_studies and not args.skip_flights:
        from socbench.study import DEFAULT_ESTIMATORS, DEFAULT_SCENARIOS

        t0 = time.perf_counter()
        flights = study(cache, "flights", list(model_names()), DEFAULT_ESTIMATORS + ("rbpf",), DEFAULT_SCENARIOS,
                        args.flight_seeds, args.jobs)
        fl_wall = kept_wall(cache, "flights", time.perf_counter() - t0)
        flights_sensor = study(cache, "flights-sensor", ("thevenin", "dp"), ("ekf", "ukf"), DEFAULT_SCENARIOS, 3,
                               args.jobs, noise="sensor")

    pulses = cache.json("pulse_resistance.json", pulse_resistance)
    warming = cache.json("warming.json", lambda: {tag: load_warming(tag) for tag in TAGS})

    # ---- figures
    figdir = ROOT / "docs" / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    fig_soc(figdir / "real_data_soc_error.png", cache, best, ["5T", "25"])
    fig_voltage(figdir / "real_data_voltage.png", cache, best, ["5T", "25"])
    dji_best = None
    if lb is not None:
        dji_cells = [r for r in lb.cells if r["row"]["scenario"].startswith("dji") and r["row"]["estimator"] == "ekf"
                     and r["row"]["soc_rmse"] is not None]
        dji_best = min(lb.config.models, key=lambda m: np.mean([r["row"]["soc_rmse"] for r in dji_cells
                                                   if r["row"]["model"] == m] or [np.inf]))
    dji_rows = cache.json(f"dji_{dji_best or best}.json",
                          lambda: fig_dji(figdir / "real_data_dji.png", cache, dji_best or best))

    knee = cache.json(f"knee_{top[0]}.json", lambda: knee_start(top[0])) if lb is not None else None
    write_doc(Path(args.doc), locals())
    print(f"wrote {args.doc} in {time.perf_counter() - wall0:.0f} s", flush=True)
    return 0


def own_beside_5t(v: dict, tag: str) -> tuple[list, list]:
    """The EKF and UKF runs on the US06 of ``tag`` with the fit at its own temperature (section 4h), and with the
    five-temperature fit (section 4); an entry is None where a run is missing."""
    best, own, own_fit = v["best"], v.get("own") or {}, v.get("own_fit") or {}
    return ([own.get(f"{best}_{own_fit.get(tag)}_{est}_{tag}") for est in ("ekf", "ukf")],
            [v["runs"].get(f"{best}_5T_{est}_{tag}") for est in ("ekf", "ukf")])


def drifting_rows(lb) -> list[str]:
    """One line per rising-temperature scenario of the measured leaderboard (the chamber let drift; no choice of
    socbench was made on these records): each model's EKF and UKF SOC RMSE and within 3σ."""
    out = []
    if lb is None:
        return out
    for scen in [s for s in lb.config.scenarios if "trise" in s]:
        rows = {(r["row"]["model"], r["row"]["estimator"]): r["row"] for r in lb.cells if r["row"]["scenario"] == scen}
        parts = []
        for model in lb.config.models:
            e, u = rows.get((model, "ekf")), rows.get((model, "ukf"))
            if e and u and e["soc_rmse"] is not None and u["soc_rmse"] is not None:
                parts.append(f"{model} {pc(e['soc_rmse'])}/{pc(u['soc_rmse'])} % "
                             f"({e['frac_within_3sigma']:.2f}/{u['frac_within_3sigma']:.2f})")
        if parts:
            out.append(f"{scen}: " + ", ".join(parts))
    return out


def drifting_verdict(lb, best: str) -> str:
    """How the best model's EKF and UKF do on the rising-temperature scenarios against the must-show's targets."""
    rows = [r["row"] for r in lb.cells if "trise" in r["row"]["scenario"] and r["row"]["model"] == best
            and r["row"]["estimator"] in ("ekf", "ukf") and r["row"]["soc_rmse"] is not None]
    if not rows:
        return ""
    held = sum(r["frac_within_3sigma"] >= TARGET["coverage"] for r in rows)
    close = sum(r["soc_rmse"] <= TARGET["soc_rmse"] for r in rows)
    return (f"The best model ({best}): within 3σ ≥ {TARGET['coverage']:g} in {held} of {len(rows)} runs, SOC RMSE ≤ "
            f"{100 * TARGET['soc_rmse']:g} % in {close} of {len(rows)} (SOC RMSE "
            f"{pc(min(r['soc_rmse'] for r in rows))}–{pc(max(r['soc_rmse'] for r in rows))} %).")


def verdict(v: dict) -> str:
    """The must-show targets, counted from the tables above, and why they are (not) met."""
    best, runs, fits = v["best"], v["runs"], v["fits"]
    lines = []
    for fit, label in (("5T", "five-temperature fit"), ("25", "25 °C fit")):
        met, missed = [], []
        for tag in TAGS:
            e, u = runs.get(f"{best}_{fit}_ekf_{tag}"), runs.get(f"{best}_{fit}_ukf_{tag}")
            if not (e and u) or "error" in e or "error" in u:
                missed.append(f"{LABEL[tag]} (a run failed)")
                continue
            why = []
            if max(e["soc_rmse"], u["soc_rmse"]) > TARGET["soc_rmse"]:
                why.append(f"SOC RMSE {pc(e['soc_rmse'])}/{pc(u['soc_rmse'])} %")
            if min(e["frac_within_3sigma"], u["frac_within_3sigma"]) < TARGET["coverage"]:
                why.append(f"within 3σ {e['frac_within_3sigma']:.2f}/{u['frac_within_3sigma']:.2f}")
            if abs(e["soc_rmse"] - u["soc_rmse"]) > TARGET["ekf_ukf"]:
                why.append(f"EKF−UKF {100 * abs(e['soc_rmse'] - u['soc_rmse']):.1f} points")
            (missed if why else met).append(LABEL[tag] + (f" ({', '.join(why)})" if why else ""))
        missed_txt = f"missed at {', '.join(missed)} (EKF/UKF)" if missed else "missed at none"
        lines.append(f"- **{best}, {label}, US06 from a 20-point error**: all three targets met at "
                     f"{', '.join(met) if met else 'no temperature'}; {missed_txt}.")
    val = fits[best]["validation_rmse_v"]
    resid = v["resid"]
    lines.append(f"- **Why, first: the model.** The best model's open-loop error on the validation drive cycles is "
                 f"{mv(val['25degC'], 0)} mV at 25 °C but {mv(val['0degC'], 0)}, {mv(val['n10degC'], 0)} and "
                 f"{mv(val['n20degC'], 0)} mV at 0, −10 and −20 °C (section 2), an order of magnitude above its HPPC "
                 "fit at those temperatures (section 1). Fitted on HPPC pulses only (and the Panasonic HPPC files "
                 "leave out the discharges between the pulse sets, so a fit never sees polarisation build up under "
                 "a sustained load), no ECM here predicts the long polarisation of a cold cell on a drive cycle: the "
                 "slow error follows the recent load (section 4c: on the US06 its line on the 5-minute mean current "
                 f"has a slope of {mv(resid.get(f'{best}_5T_25degC', {}).get('load_slope_v_per_a'), 0)} mV/A at "
                 f"25 °C and {mv(resid.get(f'{best}_5T_n20degC', {}).get('load_slope_v_per_a'), 0)} mV/A at −20 °C). "
                 "An honest filter cannot tell a SOC error from a model error of the same voltage (about "
                 "10 mV per SOC point in the middle of the curve).")
    vr = [v["vruns"].get(f"{best}_5T_ekf_{t}") for t in TAGS]
    if all(r and "error" not in r for r in vr):
        lines.append("- **Not only the scored cycle:** on the validation Cycle_1 runs themselves, whose error the "
                     "recipe measured, the best model's EKF reaches " + ", ".join(
                         f"{pc(r['soc_rmse'], 1)} % ({r['frac_within_3sigma']:.2f} within 3σ) at {LABEL[t]}"
                         for r, t in zip(vr, TAGS)) + " (section 2): where the model misses the voltage by a tenth "
                     "of a volt and more for long stretches, an ECM filter does not hold the SOC to a point.")
    hard = [t for t in TAGS if resid.get(f"{best}_5T_{t}") and resid.get(f"{best}_5T_{t}_Cycle")
            and resid[f"{best}_5T_{t}"]["slow_rms_v"] > 1.3 * resid[f"{best}_5T_{t}_Cycle"]["slow_rms_v"]]
    narrow = [t for t in hard if any(runs.get(f"{best}_5T_{e}_{t}", {}).get("frac_within_3sigma", 1.0)
                                     < TARGET["coverage"] for e in ("ekf", "ukf"))]
    if hard:
        lines.append("- **Why, second: the scored cycle is harder than the validation cycle.** The noise recipe can "
                     "only know the error it measured on the validation records; at "
                     + ", ".join(LABEL[t] for t in hard) + " the US06 draws a higher mean current than Cycle_1 and "
                     "the model's slow error on it is more than 1.3 times the validation one (section 4c). "
                     + ("The ±3σ band, honest on the validation cycle's error, is too narrow on the US06 at "
                        + ", ".join(LABEL[t] for t in narrow) + "." if narrow else
                        "The band still holds the truth there (within 3σ ≥ 0.9 for both filters): the recipe's "
                        "mid-period state allows for an error that moves faster than the validation records showed "
                        "(section 4b′); what is left is an error the filters know they cannot resolve."))
    pairs = _ablation_pairs(runs, v["nomid"], best)
    if pairs:
        lines.append("- **The recipe's mid-period state** (section 4b′ → 4: SOC RMSE (within 3σ) without → with it): "
                     + "; ".join(pairs) + ".")
    ts = v.get("truestart") or {}
    far = [t for t in TAGS if all(k in ts for k in (f"{best}_5T_ekf_{t}", f"{best}_5T_iekf_{t}_guess"))
           and runs.get(f"{best}_5T_ekf_{t}") and runs.get(f"{best}_5T_ukf_{t}")
           and runs[f"{best}_5T_ekf_{t}"]["soc_rmse"] - runs[f"{best}_5T_ukf_{t}"]["soc_rmse"] > TARGET["ekf_ukf"]]
    if far:
        lines.append("- **Why the EKF parts from the UKF:** at " + ", ".join(
            f"{LABEL[t]} (EKF {pc(runs[f'{best}_5T_ekf_{t}']['soc_rmse'])} %, UKF "
            f"{pc(runs[f'{best}_5T_ukf_{t}']['soc_rmse'])} %)" for t in far)
            + " the gap is made by the EKF's first linearised correction of the 20-point error: from the true SOC "
            "the EKF reaches " + ", ".join(f"{pc(ts[f'{best}_5T_ekf_{t}']['soc_rmse'])} %" for t in far)
            + ", and the iterated EKF from the same 20-point start " + ", ".join(
                f"{pc(ts[f'{best}_5T_iekf_{t}_guess']['soc_rmse'])} %" for t in far) + " (section 4e).")
    if v["flights"] is None:
        lines.append("- **The default flight scenarios' NIS after the recipe** (must be within a factor 3 of 1): "
                     "**not measured in this run** (`--skip-flights`, to meet its deadline); `python "
                     "benchmarks/real_data.py` without it adds section 7.")
    pr = v.get("particle") or {}
    if pr:
        met = [LABEL[t] for t in TAGS
               if (r := pr.get(f"{best}_5T_rbpf_{t}")) and "error" not in r
               and max(r["runs_soc_rmse"]) <= TARGET["soc_rmse"] and min(r["runs_within_3sigma"]) >= TARGET["coverage"]]
        lines.append("- **The Rao–Blackwellised particle filter** (section 4f; beside the must-show's EKF/UKF pair, "
                     "not in its place): with the five-temperature fit, SOC RMSE ≤ 1.5 % and within 3σ ≥ 0.9 in "
                     f"every one of {PF_SEEDS} seeds at {', '.join(met) if met else 'no temperature'} of the five. "
                     "Section 4f says why, and where it is weaker than the EKF.")
    if v["flights"] is not None:
        fl = v["flights"]
        per = []
        for est in fl.config.estimators:
            rows = [r["row"] for r in fl.cells if r["row"]["estimator"] == est and r["row"]["nis_mean"] is not None]
            if est == "coulomb" or not rows:
                continue
            nis = np.array([r["nis_mean"] for r in rows])
            cov = [r["frac_within_3sigma"] for r in rows if r["frac_within_3sigma"] is not None]
            per.append(f"{est.upper()} {int(np.sum((nis >= 1 / 3) & (nis <= 3)))}/{len(rows)} cells "
                       f"(within 3σ, median over the cells, {np.median(cov):.2f})")
        lines.append("- **The default flight scenarios' NIS after the recipe** (within a factor 3 of 1, section 7): "
                     + "; ".join(per) + ". A NIS near 1 is the innovations' consistency, the share within 3σ the "
                     "SOC band's: the two are measured apart.")
    dr = v.get("defaults") or {}
    only = [r for r in (dr.get(f"{best}_hppc-only_{est}_{t}") for est in ("ekf", "ukf") for t in TAGS)
            if r and "error" not in r]
    if only:
        lines.append(f"- **Without drive cycles (`socbench fit` on the HPPCs with its defaults, section 4g)** the "
                     f"targets are not met: SOC RMSE ≤ 1.5 % in "
                     f"{sum(r['soc_rmse'] <= TARGET['soc_rmse'] for r in only)} of {len(only)} runs, within 3σ ≥ 0.9 "
                     f"in {sum(r['frac_within_3sigma'] >= TARGET['coverage'] for r in only)} of {len(only)}, NIS "
                     f"{min(r['nis_mean'] for r in only):.1f}–{max(r['nis_mean'] for r in only):.1f}: the recipe "
                     "measured on an HPPC is too small for a drive cycle. The must-show's numbers need the validated "
                     "fit and recipe (`--mode auto --validation`); both commands now say so to a user who has only "
                     "HPPCs.")
    lines.append("- **What the recipe now gets right (measured):** on synthetic records with a planted error, "
                 "including one more persistent than the record, its band holds the truth 90–100 % of the time "
                 "(`tests/test_model_error.py`, where the first version held a persistent error 47 % of the time).")
    pairs = _ablation_pairs(runs, v["unsched"], best)
    if pairs:
        lines.append("- **Parameter scheduling on the real records is not a uniform gain** (section 4b → 4: SOC RMSE "
                     "(within 3σ) without → with it): " + "; ".join(pairs) + ". It removes information the fitted "
                     "tables do not hold (on synthetic data and where the tables are worst), and with it some the "
                     "tables do hold.")
    pairs = []
    for tag in TAGS:
        o, f5 = own_beside_5t(v, tag)
        if all(r and "error" not in r for r in o + f5):
            pairs.append((LABEL[tag], max(r["soc_rmse"] for r in o), max(r["soc_rmse"] for r in f5),
                          min(r["frac_within_3sigma"] for r in o), min(r["frac_within_3sigma"] for r in f5)))
    if pairs:
        better = sum(b < a for _, a, b, _, _ in pairs)
        lines.append("- **Against a fit at the record's own temperature** (section 4h; worse filter's SOC RMSE, own "
                     "temperature's fit → five-temperature fit, lowest within 3σ in brackets): "
                     + "; ".join(f"{t} {pc(a)} → {pc(b)} % ({ca:.2f} → {cb:.2f})" for t, a, b, ca, cb in pairs)
                     + f". The five-temperature set is the better of the two at {better} of {len(pairs)} "
                     "temperatures.")
    drift = drifting_rows(v.get("lb"))
    if drift:
        lines.append("- **Records no choice was made on** (the two Panasonic runs whose chamber was let drift, the "
                     "cell warming by 17–33 K within the record; section 6; SOC RMSE EKF/UKF, within 3σ in brackets): "
                     + "; ".join(drift) + ". " + drifting_verdict(v["lb"], v["best"]))
    lines.append("- **What carries:** the five-temperature set runs every record at its measured cell temperature "
                 "(one mechanism for every model); the SOC-axis conversion makes counting on the model's axis "
                 "reproduce each temperature's own reference; the measured group runs in the leaderboard and is "
                 "skipped cleanly without data.")
    return "\n".join(lines) + "\n"


def _slow_note(args, what: str = "the iterated EKF") -> str:
    """Where the slow filters run at another resolution than section 4: say so."""
    if args.slow_resolution == args.resolution:
        return ""
    at = f"on {args.slow_resolution:g} s bins" if args.slow_resolution > 0 else "as recorded"
    return f"; {what} {at}: their numpy loops take about ten minutes per record at 10 Hz"


def _ablation_pairs(runs: dict, ablated: dict, best: str) -> list[str]:
    """"T EST a → b % (coverage a → b)" per temperature and filter: an ablation's run beside the recipe's own."""
    pairs = []
    for tag in TAGS:
        for est in ("ekf", "ukf"):
            a, b = runs.get(f"{best}_5T_{est}_{tag}"), ablated.get(f"{best}_5T_{est}_{tag}")
            if a and b and "error" not in a and "error" not in b:
                pairs.append(f"{LABEL[tag]} {est.upper()} {pc(b['soc_rmse'], 1)} → {pc(a['soc_rmse'], 1)} % "
                             f"({b['frac_within_3sigma']:.2f} → {a['frac_within_3sigma']:.2f})")
    return pairs


def _filter_pair_table(w, runs: dict, best: str) -> None:
    """An ablation's US06 rows: the five-temperature fit's EKF and UKF per temperature."""
    w("| US06 | EKF SOC RMSE % | EKF within 3σ | EKF NIS | UKF SOC RMSE % | UKF within 3σ | UKF NIS |")
    w("|---|---|---|---|---|---|---|")
    for tag in TAGS:
        cells = []
        for r in (runs.get(f"{best}_5T_ekf_{tag}"), runs.get(f"{best}_5T_ukf_{tag}")):
            cells += (["failed", "", ""] if r is None or "error" in r else
                      [pc(r["soc_rmse"]), f"{r['frac_within_3sigma']:.3f}", nis_txt(r)])
        w(f"| {LABEL[tag]} | " + " | ".join(cells) + " |")


def write_doc(path: Path, v: dict):
    best, top, fits, fit25, runs, stats, resid = (v[k] for k in ("best", "top", "fits", "fit25", "runs", "stats",
                                                                  "resid"))
    ranked, lb, flights, flights_sensor = v["ranked"], v["lb"], v["flights"], v["flights_sensor"]
    L = []
    w = L.append
    w("# Real cells at every temperature: temperature-aware models, honest filters, measured-data scenarios\n")
    w(f"*Generated by `benchmarks/real_data.py` (`SOCBENCH_DATA_DIR=/work/shared/data python benchmarks/real_data.py "
      f"--jobs {v['args'].jobs}`); every number below comes from that run. Python {platform.python_version()}, "
      f"{os.cpu_count()} CPU cores shared with other jobs (1-minute load average {v['load0']:.1f} at the start; fits, "
      "runs and study cells an earlier invocation on the same `--cache` computed are reused, and the studies' wall "
      "times are those of the runs that computed them).*\n")
    w("**Data.** " + CITE["panasonic"] + ": HPPC, Cycle_1 and US06 at 25, 10, 0, −10, −20 °C (plus HWFET, LA92, NN "
      "at 25 °C in the leaderboard). " + CITE["calce"] + ". " + CITE["dji"] + ".\n")
    w("## 1. One SOC axis, five temperatures\n")
    f5 = fits[best]["fit"]
    w(f"Each HPPC is placed on the charge axis of the 25 °C capacity, Q_ref = {f5['capacity_ref_ah']:.4g} Ah (the "
      "charge a cold cell fails to deliver before the cut-off is lost to resistance, not missing charge), fitted on "
      "its own (`socbench.identify.temperature.fit_temperatures`), and the parameters become tables over "
      "SOC × temperature (log-linear in T for positive quantities, exact at each fitted temperature, held outside); "
      "the OCV is each HPPC's own rest points (a cold HPPC covers only the top of the axis: below it the lowest-"
      "reaching curve is shifted to meet it). The same command, the choice below included: `socbench fit --data "
      f"HPPC25 HPPC10 HPPC0 HPPCn10 HPPCn20 --model {best} --mode auto --validation CYCLE25 CYCLE10 CYCLE0 CYCLEn10 "
      "CYCLEn20 --out P.json` (it prints the scores of the table below and the setting it keeps).\n")
    w("**How each model is fitted is chosen by validation** (`socbench.identify.select_temperature_fit`, "
      "the same choice the measured scenarios of the leaderboard make on their validation records, section 6): "
      "the paper's SOC polynomials or a piecewise-linear SOC lookup, each with the three sample weightings "
      "of `socbench.identify.FIT_CANDIDATES` (`edges`: the samples right after each current edge; `dense`; "
      "`time-weighted`: each kept sample weighted by the time it stands for, so the long relaxations count as much "
      "as they last). Each setting is fitted at every temperature and scored open loop on the Cycle_1 runs of those "
      "temperatures (the 25 °C fit: the 25 °C run alone); the lowest mean RMSE wins. The US06 runs are never used. "
      f"Over five temperatures one more candidate, **{PER_TEMPERATURE}**: each HPPC fitted with the setting whose "
      "fit predicts the Cycle_1 run of its own temperature best (the setting that suits the warm cell need not suit "
      "the cold one; the tables interpolate between nodes of different forms), kept if the assembled set's mean "
      "is lower. The winner of a five-temperature fit is then fitted again with the **charge-transfer term** "
      "(section 4d: a "
      "Butler–Volmer over-potential whose exchange current follows an Arrhenius law I₀(T), fitted with the model on "
      "each HPPC, `fit_temperatures(..., charge_transfer=True)`, `socbench fit --charge-transfer`) and kept if its "
      "mean Cycle_1 RMSE is lower.\n")
    w(f"| setting | {best}: mean Cycle_1 RMSE, five-temperature fit [mV] | "
      f"{best}: 25 °C Cycle_1 RMSE, 25 °C fit [mV] |")
    w("|---|---|---|")
    extra_labels = [k for k in fits[best].get("settings", {}) if k not in FIT_SETTINGS]
    per_t = fits[best].get("settings", {}).get(PER_TEMPERATURE, {}).get("per_temperature")
    for label in list(FIT_SETTINGS) + extra_labels:
        cells = []
        for f in (fits[best], fit25):
            t = f.get("settings", {}).get(label, {})
            cells.append("failed" if "error" in t else (mv(t["mean_rmse_v"]) if t else "—") +
                         (" **(chosen)**" if f.get("setting") == label else ""))
        shown = label if not (label.startswith(PER_TEMPERATURE) and per_t) else label + " (" + ", ".join(
            f"{LABEL[t]} {per_t[t]}" for t in TAGS) + ")"
        w(f"| {shown} | " + " | ".join(cells) + " |")
    w("")
    w("| HPPC | temperature (median of the cell thermocouple) | capacity delivered [Ah] | SOC range on Q_ref | "
      f"fit RMSE ({best}) [mV] |")
    w("|---|---|---|---|---|")
    for rec in sorted(f5["by_temperature"], key=lambda r: -r["temperature_c"]):
        q = rec["capacity_ah"]
        w(f"| {rec['record']} | {rec['temperature_c']:.1f} °C | {q:.4g} | [{1 - q / f5['capacity_ref_ah']:.3f}, 1] | "
          f"{mv(rec['rmse_v'])} |")
    w("\n" + "; ".join(n for n in fits[best]["notes"][1:]) + ".\n")
    w("The US06 runs heat the cell (the model looks its parameters up at the measured cell temperature, sample by "
      "sample):\n")
    w("| US06 | cell temperature at the start of the record | … when the load starts | maximum under load | "
      "reference SOC capacity Q_data [Ah] |")
    w("|---|---|---|---|---|")
    for tag in TAGS:
        r = runs.get(f"{best}_5T_coulomb_{tag}")
        if r and "error" not in r:
            t0, t1, t2 = v["warming"][tag]
            w(f"| {LABEL[tag]} | {t0:.1f} °C | {t1:.1f} °C | {t2:.1f} °C | {r['axis']['data_capacity_ah']:.5g} |")
    w("\nReported SOC follows the data: z_data = 1 − (1 − z_model)·Q_ref/Q_data, σ_data = σ_model·Q_ref/Q_data "
      "(`socbench.socaxis`; the initial guess the other way).\n")
    w("## 2. Best model, chosen on validation records\n")
    w("Open-loop voltage RMSE [mV] of the five-temperature fits on the Cycle_1 runs (validation; the US06 runs are "
      "never used to choose):\n")
    w("| model | fit setting | " + " | ".join(LABEL[t] for t in TAGS) + " | mean |")
    w("|---|---|" + "---|" * (len(TAGS) + 1))
    for m in ranked:
        vals = [fits[m]["validation_rmse_v"][t] for t in TAGS]
        w(f"| {m} | {fits[m].get('setting', 'paper/edges')} | " + " | ".join(mv(x) for x in vals) +
          f" | **{mv(np.mean(vals))}** |")
    w(f"\nThe {len(v['shortlist'])} best distinct models there ({', '.join(v['shortlist'])}) then run their EKF and "
      "UKF (the noise recipe measured on the same Cycle_1 runs, the scoring protocol below) on each Cycle_1 run: the "
      "model whose two filters track the SOC best on validation is the best model (open-loop voltage alone is not "
      "the criterion: a filter corrects a slow voltage error it can tell apart from the SOC). SOC RMSE % of EKF / "
      "UKF, within 3σ in brackets:\n")
    w("| model | " + " | ".join(LABEL[t] for t in TAGS) + " | median of the worse filter % |")
    w("|---|" + "---|" * (len(TAGS) + 1))
    for m in v["shortlist"]:
        cells = []
        for t in TAGS:
            rs = [v["vruns"].get(f"{m}_5T_{est}_{t}") for est in VALIDATION_FILTERS]
            cells.append(" / ".join(
                ("failed" if "error" in r else f"{pc(r['soc_rmse'])} ({r['frac_within_3sigma']:.2f})") if r else "—"
                for r in rs))
        w(f"| {m} | " + " | ".join(cells) + f" | **{pc(v['val_score'](m))}** |")
    w("\n(Per temperature the worse of the two filters, since the targets hold for both; then the median over the "
      "five temperatures, so that one catastrophic temperature does not decide alone.)\n")
    w(f"\nBest: **{best}** (then {', '.join(top[1:])}).\n")
    w("## 3. The noise recipe\n")
    w("`socbench.estimators.model_error` (the equations are in its docstring). The fitted model runs open loop on "
      "records where the SOC is known — the validation records, never the one scored — and its voltage error is split "
      "into a resistive part (local regression on the current), a slow part (10 s mean), a fast part and a white part; "
      "each gets a scale per temperature × SOC and an integral correlation time. The filter's model is augmented with "
      "four unit-variance Gauss–Markov states (`ModelError` effect: "
      "y += κ·σ_s(z,T)·(ε_s + ε_m) + σ_f(z,T)·ε_f − σ_r(z,T)·ε_r·I, ε⁺ = e^{−dt/τ}ε + w; ε_m carries the slow "
      "scale again at τ_m = √(10 s·τ_slow), so that an error of that size may also come and go within minutes, "
      "section 4b′; κ = √½ where the recipe was measured on validation records at the record's temperatures, so "
      "that ε_s + ε_m has the measured slow variance, else κ = 1: `model_error.slow_share`) whose walk variances "
      "1 − e^{−2dt₀/τ} enter Q, and R = σ_V² + the white variance averaged "
      "over the record's temperatures: inside the form the compiled filters take (R_k = σ_V² + σ_I²D_k², "
      "Q_k = σ_I²B_kB_kᵀ + diag(walk)·dt_k/dt₀). The sensor-only covariance stays available (`--noise sensor`).\n")
    w("Four rules keep the band honest where the first version of the recipe was not (sections 4 and 8 measure "
      "it):\n")
    w("- **Parameter scheduling** (`Model.schedule_soc`, set by the recipe; `socbench.estimators.base."
      "scheduled_jacobian`, `scheduled_step`, `scheduled_output`, `scheduled_points_output`): every parameter "
      "(R0(z), R1(z), C1(z), the error scales σ(z)…) is looked up at the estimated SOC but not differentiated in it, "
      "in the EKF family and the sigma-point filters alike. In the dynamics ∂x_j⁺/∂z = 0 for j ≠ z (every sigma "
      "point steps its other states with the mean SOC's parameters and keeps its own SOC deviation); in the output "
      "the SOC enters the linearisation only through the equilibrium curve E(z, T) = h([z, 0, …], I = 0, T), the "
      "OCV of an RC model (H_z = ∂E/∂z; each sigma point's output is taken at the mean SOC plus E(z_s) − E(z̄)). "
      "Differentiated, tables fitted point by point on HPPC pulses let a filter read the SOC off the polarisation's "
      "shape or the resistance's SOC profile (R0'(z)·I) to a precision the model does not have, and a UKF, whose "
      "sigma points sample those slopes far from the mean, parts from the EKF (section 4b: the same runs with the "
      "full Jacobian).\n")
    w("- **Persistence**: a correlation time is the larger of the integral time and −L/ln ρ(L) at the longest lag "
      "measured, so an error that has not decorrelated within the records is not averaged away over two of them.\n")
    w("- **Robust scales**: each SOC cell's mean square is shrunk toward its temperature row's median cell by the "
      "independent looks it holds (cell seconds / 2τ): a persistent error seen a few times per cell is a handful of "
      "numbers, and the smallest would narrow the band there.\n")
    w("- **NIS calibration** (`socbench.estimators.nis_calibration`, as `socbench fit --validation` does): the EKF "
      "and the particle filter run on the validation records themselves (bin-averaged to the recipe's 1 s, from their "
      "reference SOC) with the recipe, and every model-error variance of each form (the coloured states; the "
      "inflated white R) is scaled by the factor that brings the filter's NIS mean to 1 there (two rounds, the "
      "factor within [¼, 4]). The recipe measures the error's shape; the records it was measured on check its "
      "size.\n")
    w("On synthetic records with a planted error (`tests/test_model_error.py`, now including an error more persistent "
      "than the record) the band holds the truth 90–100 % of the time in every configuration; the first version "
      "held a persistent error 47 % of the time there.\n")
    for cfg in ((best, "5T"), (best, "25")):
        s = recipe.ModelErrorStats.from_dict(stats[cfg])
        sm = s.summary()
        which = ("five-temperature fit, on the five Cycle_1 runs" if cfg[1] == "5T"
                 else "25 °C fit, on the 25 °C Cycle_1 only")
        cal = ", ".join(f"{a:.2f} ({nis_calibration.CALIBRATED_WITH[f]}, {f} form)" for f, a in s.nis_scale)
        w(f"**{cfg[0]}, {which}** (RMS over SOC; τ_slow {s.tau_slow_s:.0f} s, τ_fast {s.tau_fast_s:.1f} s, τ_r "
          f"{s.tau_r_s:.0f} s; NIS calibration on the same runs: variances × {cal or '1 (not calibrated)'}):\n")
        w("| temperature node | slow [mV] | fast [mV] | resistive [mΩ] | white [mV] |")
        w("|---|---|---|---|---|")
        for j, t in enumerate(s.temps):
            w(f"| {t:.1f} °C | {mv(sm['slow'][j])} | {mv(sm['fast'][j])} | {mv(sm['r'][j])} | {mv(sm['white'][j])} |")
        w("")
    w("## 4. The US06 at each temperature (the must-show)\n")
    res = v["args"].resolution
    w(f"{best}, a guess {-100 * SOC0_ERROR:.0f} SOC points below the reference (SD {SOC0_SD:g}), "
      + (f"the record bin-averaged to {res:g} s (the noise recipe's resolution; the default `--resolution 0` runs "
         "the records as recorded)" if res > 0 else
         "the record as recorded (10 Hz, as `socbench estimate` and the leaderboard run it; the recipe's white part "
         "is scaled so that a faster record gives the filter the same information per second, section 3)")
      + ", the recipe's noise. Targets: SOC RMSE ≤ 1.5 %, within 3σ ≥ 0.9, EKF and UKF within 0.5 points.\n")
    w("| US06 | fit | EKF SOC RMSE % | EKF within 3σ | EKF NIS [95 % band] | UKF SOC RMSE % | UKF within 3σ | "
      "UKF NIS | \\|EKF − UKF\\| points | targets met |")
    w("|---|---|---|---|---|---|---|---|---|---|")
    for tag in TAGS:
        for fit in ("5T", "25"):
            e, u = runs.get(f"{best}_{fit}_ekf_{tag}"), runs.get(f"{best}_{fit}_ukf_{tag}")
            if not (e and u):
                continue
            if "error" in e or "error" in u:
                why = "; ".join(f"{n} failed ({r['error']})" for n, r in (("EKF", e), ("UKF", u)) if "error" in r)
                w(f"| {LABEL[tag]} | {'5 temperatures' if fit == '5T' else '25 °C only'} | {why} |||||||| **no** |")
                continue
            met = (max(e["soc_rmse"], u["soc_rmse"]) <= TARGET["soc_rmse"]
                   and min(e["frac_within_3sigma"], u["frac_within_3sigma"]) >= TARGET["coverage"]
                   and abs(e["soc_rmse"] - u["soc_rmse"]) <= TARGET["ekf_ukf"])
            w(f"| {LABEL[tag]} | {'5 temperatures' if fit == '5T' else '25 °C only'} | {pc(e['soc_rmse'])} | "
              f"{e['frac_within_3sigma']:.3f} | {nis_txt(e)} | {pc(u['soc_rmse'])} | {u['frac_within_3sigma']:.3f} | "
              f"{nis_txt(u)} | {100 * abs(e['soc_rmse'] - u['soc_rmse']):.2f} | {ok(met)} |")
    w("\n**4b. The same with the full Jacobian** (the recipe without parameter scheduling; five-temperature fit):\n")
    _filter_pair_table(w, v["unsched"], best)
    other = 1.0 if res == 0 else 0.0
    w("\n**4b″. The same at " + (f"{other:g} s bins** (the records bin-averaged to the noise recipe's resolution "
                                   "before filtering" if other > 0 else "the records' own 10 Hz** (as recorded")
      + f"; five-temperature fit; section 4 runs them {'as recorded' if res == 0 else f'at {res:g} s bins'}):\n")
    _filter_pair_table(w, v["compare"], best)
    w("\n**4b′. The same without the recipe's mid-period state** (ε_mid held at 0: one slow error state at the "
      "integral time τ_slow, as the recipe was before it; five-temperature fit, parameter scheduling on):\n")
    _filter_pair_table(w, v["nomid"], best)
    w(f"\n**4c. The model's error on the validation cycle and on the scored one** ({best}, five-temperature fit, open "
      "loop from the true initial state at the records' own 10 Hz; slow = the 10 s mean; load slope = the "
      "least-squares line of the slow error on the 5-minute mean current):\n")
    w("| temperature | Cycle_1 mean \\|I\\| A | Cycle_1 slow RMS mV | Cycle_1 load slope mV/A | US06 mean \\|I\\| A | "
      "US06 slow RMS mV | US06 load slope mV/A |")
    w("|---|---|---|---|---|---|---|")
    for tag in TAGS:
        c, u = v["resid"].get(f"{best}_5T_{tag}_Cycle"), v["resid"].get(f"{best}_5T_{tag}")
        if c and u:
            w(f"| {LABEL[tag]} | {c['mean_abs_current_a']:.2f} | {mv(c['slow_rms_v'], 0)} | "
              f"{mv(c['load_slope_v_per_a'], 0)} | {u['mean_abs_current_a']:.2f} | {mv(u['slow_rms_v'], 0)} | "
              f"{mv(u['load_slope_v_per_a'], 0)} |")
    w("\n**4d. Why the cold runs miss: the cell's resistance depends on the current.** The 10 s resistance "
      "(ΔV/I at the end of a 10 s discharge pulse, median over the SOC levels where the pulse ran its full length; in "
      "brackets the ohmic jump at the pulse edge) of each HPPC's five pulse currents "
      "(`socbench.identify.hppc.analyze_hppc`):\n")
    currents = sorted({k for t in TAGS for k in v["pulses"][t]}, key=float)
    w("| HPPC | " + " | ".join(f"{float(c):.1f} A" for c in currents) + " |")
    w("|---|" + "---|" * len(currents))
    for tag in TAGS:
        row = v["pulses"][tag]
        w(f"| {LABEL[tag]} | " + " | ".join(
            (f"{1000 * row[c]['r10_ohm']:.0f} mΩ ({1000 * row[c]['r0_ohm']:.0f})" if c in row else "—")
            for c in currents) + " |")
    def pol_ratio(tag):
        row = v["pulses"][tag]
        lo, hi = currents[0], min(currents, key=lambda c: abs(float(c) - 5.8))  # 0.5C and 2C of the 2.9 Ah cell
        if lo not in row or hi not in row:
            return float("nan")
        return ((row[lo]["r10_ohm"] - row[lo]["r0_ohm"]) / (row[hi]["r10_ohm"] - row[hi]["r0_ohm"]))

    w("\nThe polarisation part (10 s minus ohmic) at the smallest pulse over that at 2C: "
      f"{pol_ratio('25degC'):.2f}× at 25 °C, {pol_ratio('0degC'):.2f}× at 0 °C, "
      f"{pol_ratio('n20degC'):.2f}× at −20 °C. In the cold "
      "the charge-transfer over-potential grows like asinh(I/2I₀), "
      "not like I (Butler–Volmer, ECM_SPEC §9.6), and a linear model fitted on all five pulse currents is too stiff "
      "at the drive cycles' everyday currents and too soft at their peaks. None of the 14 models has this term; "
      "the `butler_volmer` effect of `socbench.models.effects` does, and its exchange current now follows an "
      "Arrhenius law I₀(T) = I₀·exp[−(E_a/R)(1/T − 1/T_ref)] fitted with the base model on the HPPCs "
      "(`fit_temperatures(..., charge_transfer=True)`: I₀ per temperature with the model's parameters, the law "
      "through them, every temperature refitted with the law held; section 1 says whether validation kept it).\n")
    ct = fits[best].get("fit", {}).get("charge_transfer")
    if ct:
        w(f"{best}'s charge-transfer fit: I₀ per HPPC " + ", ".join(
            f"{t:.1f} °C {i:.3g} A" + ("" if u else " (at a bound: left out of the law)")
            for t, i, u in zip(ct["temps"], ct["i0_fitted_a"], ct["used"]))
          + f"; the law I₀ = {ct['i0_ref_a']:.3g} A at {ct['t_ref_c']:g} °C, E_a = {ct['ea_j_per_mol'] / 1e3:.1f} "
            "kJ/mol.\n")
    w("\n**4e. What the initial error costs** (five-temperature fit, the recipe, the filters started at the true SOC "
      "instead of 20 points below it; SOC RMSE % (within 3σ), with the 20-point start of section 4 beside it"
      + _slow_note(v["args"]) + "):\n")
    w("| US06 | EKF from the truth | EKF from −20 points | UKF from the truth | UKF from −20 points | iterated EKF "
      "from the truth | iterated EKF from −20 points |")
    w("|---|---|---|---|---|---|---|")
    for tag in TAGS:
        cells = []
        for est in ("ekf", "ukf", "iekf"):
            ts = v["truestart"]
            for r in (ts.get(f"{best}_5T_{est}_{tag}"), runs.get(f"{best}_5T_{est}_{tag}") if est != "iekf"
                      else ts.get(f"{best}_5T_{est}_{tag}_guess")):
                cells.append("failed" if r is None or "error" in r else
                             f"{pc(r['soc_rmse'])} ({r['frac_within_3sigma']:.2f})")
        w(f"| {LABEL[tag]} | " + " | ".join(cells) + " |")
    gaps = [(LABEL[t], e, u, et) for t in TAGS
            for e, u, et in [(runs.get(f"{best}_5T_ekf_{t}"), runs.get(f"{best}_5T_ukf_{t}"),
                              v["truestart"].get(f"{best}_5T_ekf_{t}"))]
            if e and u and et and "error" not in e and "error" not in u and "error" not in et
            and e["soc_rmse"] - u["soc_rmse"] > TARGET["ekf_ukf"]
            and et["soc_rmse"] < e["soc_rmse"] - TARGET["ekf_ukf"]]
    if gaps:
        w("\nWhere the EKF ends far from the UKF (" + ", ".join(
            f"{g[0]}: {pc(g[1]['soc_rmse'])} against {pc(g[2]['soc_rmse'])} %, {pc(g[3]['soc_rmse'])} % from the "
            "truth" for g in gaps) + "), the gap is made in the first minute: the EKF corrects the 20-point error "
          "in one linearised step, at the guess's OCV slope, lands points away from the truth with a band already "
          "narrow, and the slow model-error state takes up the rest; the sigma-point filter spans the curvature. The "
          "iterated EKF (`iekf`: the update re-linearised at the corrected state until it stops moving, "
          "`socbench.estimators.iekf`) is the EKF-side remedy; its columns above measure it.\n")
    pr = v.get("particle") or {}
    if pr:
        w("\n**4f. The particle filters** (the same 20-point start" + _slow_note(v["args"], "these filters")
          + ", each run over "
          f"{PF_SEEDS} seeds of its random numbers; SOC RMSE % median (worst) over the seeds, within 3σ median "
          "(lowest)). The bootstrap PF (`pf`) takes the recipe's error as white noise (its inflated form: "
          "near-deterministic coloured states collapse a bootstrap cloud) and weighs its particles with the "
          "coloured part counted once per correlation time (`SensorNoise.weight_extra_var`): its band is honest, "
          "but from a far start it reaches the SOC slowly, as its weights cannot tell the OCV's shape along the "
          "drive from the error's slow level; the Rao–Blackwellised PF (`rbpf`, "
          "`socbench.estimators.rbpf`) puts particles on the SOC alone and carries every other state — the RC "
          "voltages and the recipe's coloured error states — in one Kalman filter per run, the parameters looked up "
          "at the particles' mean SOC. Targets for one filter: SOC RMSE ≤ 1.5 % and within 3σ ≥ 0.9 in every "
          "seed.\n")
        w("| US06 | fit | PF SOC RMSE % | PF within 3σ | RBPF SOC RMSE % | RBPF within 3σ | RBPF NIS | RBPF targets "
          "met in every seed |")
        w("|---|---|---|---|---|---|---|---|")
        for tag in TAGS:
            for fit, label in (("5T", "5 temperatures"), ("25", "25 °C only")):
                cells = []
                for est in ("pf", "rbpf"):
                    r = pr.get(f"{best}_{fit}_{est}_{tag}")
                    if r is None or "error" in r:
                        cells += ["failed", "failed"]
                        continue
                    e, c = np.asarray(r["runs_soc_rmse"], float), np.asarray(r["runs_within_3sigma"], float)
                    cells += [f"{pc(np.median(e))} ({pc(np.max(e))})", f"{np.median(c):.2f} ({np.min(c):.2f})"]
                r = pr.get(f"{best}_{fit}_rbpf_{tag}")
                ok_all = bool(r and "error" not in r and max(r["runs_soc_rmse"]) <= TARGET["soc_rmse"]
                              and min(r["runs_within_3sigma"]) >= TARGET["coverage"])
                nis = nis_txt(r) if r and "error" not in r else "—"
                w(f"| {LABEL[tag]} | {label} | " + " | ".join(cells) + f" | {nis} | {ok(ok_all)} |")
        w("\nWhy the RBPF differs from the EKF here: its particles place the SOC from the first rested voltage "
          "without a linearisation (the EKF's first correction of the 20-point error lands where the guess's OCV "
          "slope points, section 4e), and its SOC moves by reweighting, which a slow voltage error the coloured "
          "states explain moves little. The same property is its weakness: a particle cloud's spread depends on "
          "the data, and under an error its noise does not describe (a constant current-sensor offset declared as "
          "white noise) reweighting narrows the cloud and the SOC follows the voltage more slowly than the EKF's, "
          "whose covariance never looks at the data (docs/estimators.md, section 4: the current-bias scenario). On "
          "the recipe's calibration records (a known coloured error planted, `tests/test_rbpf.py`) its band holds "
          "the truth 90–100 % of the time, as the EKF's does, and so does the bootstrap PF's "
          "(`tests/test_model_error.py`), at a larger SOC error from a far start (the table above).\n")
    dr, dfits = v.get("defaults") or {}, v.get("default_fits") or {}
    if dr:
        w("\n**4g. What the defaults give: HPPCs without drive cycles** (`socbench fit` without `--mode auto`, "
          "then the same filters, 20-point start and scoring as section 4; the commands as run, "
          "abbreviated; `$HPPCS` the five HPPC files, `$CYCLES` the five Cycle_1 files of section 1):\n")
        for variant, (_, what) in DEFAULT_VARIANTS.items():
            w(f"- *{variant}*: `{dfits[variant]['command']}` ({what})")
        w(f"- *validated*: `socbench fit --data $HPPCS --model {best} --mode auto --validation $CYCLES --out "
          f"{best}.json` (section 4's fit and recipe)\n")
        w("| US06 | fit | EKF SOC RMSE % | EKF within 3σ | EKF NIS | UKF SOC RMSE % | UKF within 3σ | UKF NIS |")
        w("|---|---|---|---|---|---|---|---|")
        for tag in TAGS:
            for variant in (*DEFAULT_VARIANTS, "validated"):
                pair = [runs.get(f"{best}_5T_{est}_{tag}") if variant == "validated"
                        else dr.get(f"{best}_{variant}_{est}_{tag}") for est in ("ekf", "ukf")]
                cells = []
                for r in pair:
                    cells += (["failed"] * 3 if r is None or "error" in r else
                              [pc(r["soc_rmse"]), f"{r['frac_within_3sigma']:.3f}", f"{r['nis_mean']:.2f}"])
                w(f"| {LABEL[tag]} | {variant} | " + " | ".join(cells) + " |")
        only = [dr.get(f"{best}_hppc-only_{est}_{t}") for est in ("ekf", "ukf") for t in TAGS]
        only = [r for r in only if r and "error" not in r]
        if only:
            cover = [r["frac_within_3sigma"] for r in only]
            w(f"\nWith the HPPCs alone the filters' ±3σ holds the truth {min(cover):.3f}–{max(cover):.3f} of the "
              f"time ({sum(c >= TARGET['coverage'] for c in cover)} of {len(cover)} runs reach {TARGET['coverage']}) "
              f"and their NIS is {min(r['nis_mean'] for r in only):.1f}–{max(r['nis_mean'] for r in only):.1f}: an "
              "HPPC (and these files leave out the discharges between the pulse sets) never shows the model's error "
              "under a sustained load, so the recipe measured on it is too small for a drive cycle; and the paper's "
              "mode fits the cold cell worst (section 1). Nothing in the HPPC tells how much larger the drive-cycle "
              "error is, so `socbench fit` says so when it measures the recipe on the identification records, and "
              "`socbench estimate` repeats it for such a parameter file; given drive cycles of the same cell "
              "(`--validation`), `--mode auto` makes section 4's choice.\n")
    if v.get("own"):
        w("\n**4h. Beside a fit at the record's own temperature** (what a user with one temperature's tests runs: "
          "that temperature's HPPC alone, its setting chosen on that temperature's Cycle_1 "
          "(`socbench.identify.select_temperature_fit` on the one record, as section 1's 25 °C fit), the recipe "
          "measured there; the same "
          "filters, 20-point start and scoring as section 4, five-temperature fit beside it). SOC RMSE %, within 3σ "
          "in brackets:\n")
        w("| US06 | own temperature's fit (setting) | EKF | UKF | five-temperature fit: EKF | UKF |")
        w("|---|---|---|---|---|---|")
        for tag in TAGS:
            cells = []
            for r in sum(own_beside_5t(v, tag), []):
                cells.append("failed" if r is None or "error" in r else
                             f"{pc(r['soc_rmse'])} ({r['frac_within_3sigma']:.2f})")
            w(f"| {LABEL[tag]} | {v['own_setting'][tag]} | " + " | ".join(cells) + " |")
        warm = [(LABEL[t], *v["warming"][t][1:]) for t in TAGS]
        w("\nA set fitted at one temperature looks every parameter up at that temperature, whatever the cell's: the "
          "US06 runs warm the cell under load (" + ", ".join(f"{t}: {a:.1f} → {b:.1f} °C" for t, a, b in warm)
          + "), and "
          "a cold cell's resistances fall by a factor of several over that range (section 4d). The filter then "
          "reads the model's surplus over-potential as SOC; the five-temperature set follows the measured "
          "temperature sample by sample.\n")
    w("\n![SOC error with ±3σ](figures/real_data_soc_error.png)\n")
    w("*SOC error (data axis) of the EKF and UKF with their ±3σ bands, per temperature; left the five-temperature "
      "fit, right the 25 °C fit.*\n")
    w("## 5. SOC, voltage and consistency over temperature × model × estimator\n")
    w("US06, five-temperature fits (the three best models on validation), the same protocol; V RMSE is the filter's "
      "innovation (measured − predicted before the update); open loop = the model alone from the true initial state.\n")
    w("| US06 | model | estimator | SOC RMSE % | SOC max % | within 3σ | NIS [95 % band] | V RMSE mV | open-loop V "
      "RMSE mV |")
    w("|---|---|---|---|---|---|---|---|---|")
    for tag in TAGS:
        for m in top:
            for est in ("ekf", "ukf", "coulomb"):
                r = runs.get(f"{m}_5T_{est}_{tag}")
                if not r:
                    continue
                if "error" in r:
                    w(f"| {LABEL[tag]} | {m} | {est} | failed: {r['error']} ||||||")
                    continue
                ol = resid.get(f"{m}_5T_{tag}")
                w(f"| {LABEL[tag]} | {m} | {est} | {pc(r['soc_rmse'])} | {pc(r['soc_max_abs'])} | "
                  f"{r['frac_within_3sigma']:.3f} | {nis_txt(r)} | {mv(r['rmse_v'])} | "
                  f"{mv(ol['rmse_v']) if ol else '—'} |")
    w("\n![voltage residuals](figures/real_data_voltage.png)\n")
    w(f"*Open-loop voltage error of {best} on each US06 (10 s mean), five-temperature vs 25 °C fit.*\n")
    if lb is not None:
        from socbench.report import nis_text
        from socbench.report import ranked as ranked_cells

        w("## 6. Leaderboard of the measured group\n")
        from socbench.scenarios.catalog import group_names

        every = group_names("measured")
        subset = list(lb.config.scenarios) != list(every)
        w(f"`socbench leaderboard --scenarios {'measured' if not subset else ','.join(lb.config.scenarios)} --models "
          f"{','.join(lb.config.models)} --estimators coulomb,ekf,ukf --seeds "
          f"{v['args'].seeds}` ({len(lb.cells)} cells; {v['lb_wall']:.0f} s wall in the run that computed them, "
          "cells reused from the cache's store cost nothing). Every scenario replays a measured "
          "record with its own voltage; seeds perturb the initial SOC guess (20 points low ± 2); the models are fitted "
          "on characterisation tests only (Panasonic: the five HPPCs; CALCE: the C/22 OCV test + one other dynamic "
          "record; DJI: 8 other flights), each model with the fit setting its scenario's validation records choose "
          "(the choice of section 1: `socbench.identify.select_temperature_fit`, `select_fit` for one record), and "
          "the noise recipe uses the same validation records (catalog TOML files say which).\n")
        if subset:
            w(f"**Shrunk to meet the deadline of this run** (`--lb-scenarios {v['args'].lb_scenarios}`, "
              f"`--lb-models {v['args'].lb_models}`): {len(lb.config.scenarios)} of the {len(every)} scenarios of "
              f"the group; left out: {', '.join(s for s in every if s not in lb.config.scenarios)} (the Panasonic "
              "records at 10 Hz take 60–190 s per filter run on the numpy engine here). The full group runs with the "
              "defaults.\n")
        w("| scenario | rank | model | estimator | SOC RMSE % | within 3σ | NIS [95 % band] | V RMSE mV | failed |")
        w("|---|---|---|---|---|---|---|---|---|")
        for scen in lb.config.scenarios:
            for k, rec in enumerate(ranked_cells(lb, scen), 1):
                r = rec["row"]
                cov = "—" if r["frac_within_3sigma"] is None else f"{r['frac_within_3sigma']:.3f}"
                w(f"| {scen if k == 1 else ''} | {k} | {r['model']} | {r['estimator']} | {pc(r['soc_rmse'])} | "
                  f"{cov} | {nis_text(r['nis_mean'], rec.get('nis_band'))} | {mv(r['v_rmse'])} | "
                  f"{r['failed_runs']}/{r['n_runs']} |")
        drift = drifting_rows(lb)
        if drift:
            w("\n**Two records no choice was made on.** `pan-us06-n20-trise` and `pan-cycle1-10-trise` replay the "
              "Panasonic runs whose chamber was let drift (`panasonic_18650pf/PROVENANCE.md`): the cell warms from "
              "−20 to 13 °C and from 10 to 27 °C within the record, a path none of the fixed-temperature HPPCs or "
              "validation cycles has; they were added after every setting here was chosen. SOC RMSE EKF/UKF (within "
              "3σ): " + "; ".join(drift) + ".")
        kn = v.get("knee")
        if kn and (kn["filters"]["ekf"]["within_3sigma"] >= 0.5
                   or abs(kn["filters"]["ekf"]["err_1min"]) <= 3 * kn["filters"]["ekf"]["sd_1min"]):
            kn = None  # the EKF's band held here: nothing to explain
        if kn:
            f = kn["filters"]
            w(f"\n**Why the EKF's band collapses on {kn['scenario']}** ({kn['model']}, the scenario's fit and recipe, "
              f"seeds {', '.join(map(str, kn['seeds']))}; median over the seeds one minute in): the record starts "
              f"full and just charged, at {kn['v0']:.3f} V, above the model's OCV at full ({kn['ocv_full']:.3f} V): "
              f"the relaxation after the charge is a model error no SOC explains. The guess ({pc(kn['guess'])} %) "
              f"sits on the LFP plateau, where the OCV rises {1000 * kn['slope_guess'] / 100:.1f} mV per SOC point; "
              f"at full it rises {1000 * kn['slope_full'] / 100:.0f} mV per point. The EKF's first correction, "
              "linearised on the plateau, overshoots to the top of the knee; the next one, linearised there, reads "
              "the SOC to the steep slope's precision and the band collapses. With no random walk on the SOC (the "
              "recipe gives it none: the coloured states carry the model error) it never widens again, and the "
              "flat plateau that follows cannot correct it.\n")
            w("| filter | SOC error after 1 min % | SOC SD after 1 min % | SOC RMSE % | within 3σ |")
            w("|---|---|---|---|---|")
            for name, label in (("ekf", "EKF"), ("iekf", "iterated EKF"), ("ukf", "UKF")):
                r = f[name]
                w(f"| {label} | {pc(r['err_1min'])} | {pc(r['sd_1min'], 3)} | {pc(r['soc_rmse'])} | "
                  f"{r['within_3sigma']:.3f} |")
            w("\nThe iterated EKF re-linearises each correction where it lands and the UKF's sigma points span the "
              "knee: neither collapses. On an LFP cell that starts near a knee, use one of the two rather than the "
              "EKF.\n")
        w("\n**The DJI flights: the pack's own SOC beside the counted reference** (EKF on the model with the best DJI "
          "SOC RMSE above):\n")
        w("| flight | minutes | EKF SOC RMSE % | EKF within 3σ | pack BMS SOC − reference: RMS % | max % |")
        w("|---|---|---|---|---|---|")
        for r in v["dji_rows"]:
            w(f"| {r['scenario']} | {r['minutes']:.0f} | {pc(r['ekf_rmse'])} | {r['ekf_cov']:.3f} | "
              f"{pc(r['bms_rmse'])} | {pc(r['bms_max'])} |")
        w("\n![DJI flights](figures/real_data_dji.png)\n")
    if flights is not None:
        w("## 7. The default flight scenarios after the noise recipe\n")
        w(f"`socbench leaderboard` (every model, {', '.join(flights.config.estimators)}, "
          f"{len(flights.config.seeds)} seeds; "
          f"{v['fl_wall']:.0f} s wall in the run that computed them): NIS mean per cell with the recipe (target: "
          "within a factor 3 of 1).\n")
        w("| scenario | estimator | cells | NIS median | NIS min | NIS max | cells with 1/3 ≤ NIS ≤ 3 | within 3σ "
          "median |")
        w("|---|---|---|---|---|---|---|---|")
        for scen in flights.config.scenarios:
            for est in flights.config.estimators:
                rows = [r["row"] for r in flights.cells if r["row"]["scenario"] == scen and r["row"]["estimator"] == est
                        and r["row"]["nis_mean"] is not None]
                if not rows:
                    continue
                nis = np.array([r["nis_mean"] for r in rows])
                cov = np.array([r["frac_within_3sigma"] for r in rows if r["frac_within_3sigma"] is not None])
                w(f"| {scen} | {est} | {len(rows)} | {np.median(nis):.2f} | {nis.min():.2f} | {nis.max():.2f} | "
                  f"{int(np.sum((nis >= 1 / 3) & (nis <= 3)))}/{len(rows)} | "
                  f"{np.median(cov) if cov.size else float('nan'):.3f} |")
        bad = [r["row"] for r in flights.cells if r["row"]["nis_mean"] is not None
               and not (1 / 3 <= r["row"]["nis_mean"] <= 3) and r["row"]["estimator"] != "coulomb"]
        if bad:
            w("\nFiltering cells outside the factor 3: " + "; ".join(
                f"{r['scenario']}/{r['model']}+{r['estimator']} {r['nis_mean']:.2f}" for r in bad) + ".\n")
        if flights_sensor is not None:
            w("\nThe same with the sensor-only covariance (`--noise sensor`, thevenin and dp, 3 seeds):\n")
            w("| scenario | model | estimator | NIS | within 3σ | SOC RMSE % |")
            w("|---|---|---|---|---|---|")
            for rec in flights_sensor.cells:
                r = rec["row"]
                w(f"| {r['scenario']} | {r['model']} | {r['estimator']} | {r['nis_mean']:.1f} | "
                  f"{r['frac_within_3sigma']:.3f} | {pc(r['soc_rmse'])} |")
    w("\n## What is met and what is not\n")
    w(verdict(v))
    path.write_text("\n".join(L) + "\n")


if __name__ == "__main__":
    sys.exit(main())
