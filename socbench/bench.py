"""``socbench bench``: the batched engines against a loop of filterpy reference runs, side by side in one process.

What is measured (DESIGN.md, "Performance")::

    sweep      a Monte Carlo sweep on the paper pack (22 Ah, 6S): the model itself as the truth on one dynamic pulse
               current (dt = 1 s), R runs with their own sensor noise (σ_V = 10 mV, σ_I = 0.2 A) and their own
               initial-SOC guess (truth 0.95, guess error N(0, 0.05²))
    batched    make_estimator(name).run(sweep)                       → µs per run-step = t / (R·T)
    filterpy   make_reference(name).run(first R_f runs, first T_f steps) → µs per step  = t / (R_f·T_f)
    speedup    filterpy µs per step / batched µs per run-step
    identical  max |batched − filterpy| over soc, soc_std, v_pred, innovation, innovation_var on the shared runs
               (≤ 1e-9), gate/clamp flags and failures equal. The EKF/UKF compare the sweep's own rows; the PF draws
               its random numbers per batch shape, so its check reruns the batched PF on the shared runs alone.

Each timing is repeated (the batched and the filterpy run alternate, so load on a shared machine hits both alike) and
the medians are reported, with every repeat kept. ``fit_all_models_s`` fits every registered model (paper mode) to the
Panasonic 25 °C HPPC when ``SOCBENCH_DATA_DIR`` is set, else to the built-in HPPC (full effort in full mode; at most 2
least-squares evaluations per model in quick mode, ``fit_effort`` says which); ``default_leaderboard_s`` runs
``socbench leaderboard`` with its defaults into a temporary folder (full mode only).
"""

from __future__ import annotations

import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

#: batched and filterpy results must agree to this (DESIGN.md)
TOLERANCE = 1e-9
#: the estimate fields compared between the batched engine and its reference
FIELDS = ("soc", "soc_std", "v_pred", "innovation", "innovation_var")
#: every registered estimator with a reference backend (all but coulomb counting), in registry order
def _benched() -> tuple:
    from .estimators import estimator_names
    from .estimators.reference import REFERENCES

    return tuple(n for n in estimator_names() if n in REFERENCES)


ESTIMATORS = _benched()


@dataclass(frozen=True)
class BenchSizes:
    """How big each measurement is. ``ref_runs × ref_steps`` is the filterpy subset (a prefix of the sweep)."""

    model: str = "dp"
    runs: int = 200
    steps: int = 3600
    ref_runs: int = 2
    ref_steps: int = 1200
    particles: int = 50
    repeats: int = 3
    #: "full": every model at full effort; "capped": every model, at most 2 least-squares evaluations each (the
    #: pipeline's fixed cost: analysis, compression, set-up); "tiny": two models capped (smoke tests only)
    fit: str = "full"
    leaderboard: bool = True
    seed: int = 7


FULL = BenchSizes()
QUICK = BenchSizes(runs=40, steps=400, ref_runs=1, ref_steps=200, particles=32, fit="capped", leaderboard=False)
#: hidden ``--tiny`` option: a smoke test of the whole pipeline in seconds (tests only; the figures mean nothing)
TINY = BenchSizes(runs=3, steps=20, ref_runs=2, ref_steps=20, particles=16, fit="tiny", leaderboard=False)
TINY_FIT_MODELS = ("rint", "thevenin")

SENSOR = {"voltage_sd": 0.01, "current_sd": 0.2}
SOC_TRUE = 0.95
SOC_GUESS_SD = 0.05


# --------------------------------------------------------------------------------------------------- the sweep
def pulse_current(steps: int, seed: int) -> np.ndarray:
    """A dynamic discharge: random 5–90 s pulses between −10 A (charge) and 40 A on the 22 Ah pack (≈ 15 A mean)."""
    rng = np.random.default_rng(seed)
    seg = rng.integers(5, 90, size=steps)
    amps = rng.uniform(-10.0, 40.0, size=steps)
    return np.repeat(amps, seg)[:steps]


def monte_carlo_sweep(model, runs: int, steps: int, seed: int = 7):
    """``(profile (runs, steps), soc0 (runs,), P0 (n,))``: the model as its own truth, noisy readings per run."""
    from .profile import Profile, ProfileMeta

    rng = np.random.default_rng(seed)
    t = np.arange(steps, dtype=float)
    current = pulse_current(steps, seed)
    truth = model.simulate(Profile(t, current), soc0=SOC_TRUE)
    volts = truth.voltage_v + SENSOR["voltage_sd"] * rng.standard_normal((runs, steps))
    amps = current + SENSOR["current_sd"] * rng.standard_normal((runs, steps))
    soc0 = np.clip(SOC_TRUE + SOC_GUESS_SD * rng.standard_normal(runs), 0.0, 1.0)
    profile = Profile(t, amps, voltage_v=volts, soc_ref=np.tile(truth.soc, (runs, 1)),
                      meta=ProfileMeta(name="bench-sweep", source="socbench bench", capacity_ah=model.capacity_ah))
    sd = np.full(model.n_states, 1e-3)
    sd[0] = 0.1
    return profile, soc0, sd**2


def _prefix(profile, runs: int, steps: int):
    from .profile import Profile

    return Profile(profile.time_s[:steps], profile.current_a[:runs, :steps], voltage_v=profile.voltage_v[:runs, :steps],
                   soc_ref=profile.soc_ref[:runs, :steps], meta=profile.meta)


def compare(a, b) -> dict:
    """Max abs difference of the compared fields and whether the flags agree; ``a`` may have more rows/steps."""
    R, T = b.soc.shape
    diff = max(float(np.max(np.abs(getattr(a, f)[:R, :T] - getattr(b, f)))) for f in FIELDS)
    flags = (np.array_equal(a.gated[:R, :T], b.gated) and np.array_equal(a.clamped[:R, :T], b.clamped)
             and np.array_equal(a.failed[:R], b.failed))
    return {"max_abs_diff": diff, "flags_equal": bool(flags), "identical": bool(diff <= TOLERANCE and flags)}


def _timed(fn):
    """``(wall s, process CPU s, result)``: CPU time is the steadier figure on a shared machine."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - t0, time.process_time() - c0, out


# --------------------------------------------------------------------------------------------------- estimators
def bench_estimator(name: str, model, sizes: BenchSizes, sweep, log=print) -> dict:
    """Median timings of the batched engine and the filterpy loop for ``name`` plus the identical-results check."""
    from .estimators import SensorNoise, make_estimator, make_reference

    profile, soc0, P0 = sweep
    noise = SensorNoise(**SENSOR)
    opts = {"n_particles": sizes.particles} if name == "pf" else {}
    Rf, Tf = min(sizes.ref_runs, sizes.runs), min(sizes.ref_steps, sizes.steps)
    shared = _prefix(profile, Rf, Tf)
    batched = make_estimator(name, model, noise, **opts)
    reference = make_reference(name, model, noise, **opts)
    t_b, t_r, c_b, c_r = [], [], [], []
    est_b = est_r = None
    for rep in range(sizes.repeats):
        tb, cb, est_b = _timed(lambda: batched.run(profile, soc0=soc0, P0=P0, seed=sizes.seed))
        tr, cr, est_r = _timed(lambda: reference.run(shared, soc0=soc0[:Rf], P0=P0, seed=sizes.seed))
        t_b.append(tb)
        t_r.append(tr)
        c_b.append(cb)
        c_r.append(cr)
        log(f"  {name} repeat {rep + 1}/{sizes.repeats}: batched {tb:.2f} s ({sizes.runs}×{sizes.steps}), "
            f"filterpy {tr:.2f} s ({Rf}×{Tf})")
    if name == "pf":  # the PF's draws depend on the batch shape: rerun the batched PF on the shared runs alone
        est_b = batched.run(shared, soc0=soc0[:Rf], P0=P0, seed=sizes.seed)
    check = compare(est_b, est_r)
    us_b = statistics.median(t_b) / (sizes.runs * sizes.steps) * 1e6
    us_r = statistics.median(t_r) / (Rf * Tf) * 1e6
    cpu_b = statistics.median(c_b) / (sizes.runs * sizes.steps) * 1e6
    cpu_r = statistics.median(c_r) / (Rf * Tf) * 1e6
    return {
        f"{name}_batched_us_per_run_step": us_b,
        f"{name}_filterpy_us_per_step": us_r,
        f"{name}_speedup": us_r / us_b,
        f"{name}_max_abs_diff": check["max_abs_diff"],
        f"{name}_identical": check["identical"],
        f"{name}_failed_runs": int(np.count_nonzero(est_b.failed)),
        f"{name}_batched_cpu_us_per_run_step": cpu_b,
        f"{name}_filterpy_cpu_us_per_step": cpu_r,
        f"{name}_cpu_speedup": cpu_r / cpu_b if cpu_b > 0 else None,
        f"{name}_repeats_s": {"batched": t_b, "filterpy": t_r, "batched_cpu": c_b, "filterpy_cpu": c_r},
    }


# --------------------------------------------------------------------------------------------------- fitting
def hppc_profile():
    """``(profile, label)``: the Panasonic 25 °C HPPC when SOCBENCH_DATA_DIR is set, else the built-in HPPC."""
    from .datasets import load

    root = os.environ.get("SOCBENCH_DATA_DIR")
    if root:
        found = sorted((Path(root) / "panasonic_18650pf" / "25degC").glob("*HPPC*.mat"))
        if found:
            return load(found[0]), f"panasonic 25degC HPPC ({found[0].name})"
    return load("builtin:hppc"), "builtin:hppc"


def fit_all_models(profile, effort: str = "full", log=print) -> dict:
    """Fit every registered model (paper mode) to ``profile``, one after the other; wall time and per-model figures.

    The recipe of benchmarks/fit_all_models.py: one OCV curve from the HPPC shared by every model (built once, not
    timed), then ``fit_model(name, hppc, mode="paper", ocv=ocv)`` per model.
    """
    from .identify import fit_model, ocv_from_hppc
    from .models import model_names

    ocv = ocv_from_hppc(profile)
    per_model = {}
    t0 = time.perf_counter()
    for name in TINY_FIT_MODELS if effort == "tiny" else model_names():
        res = fit_model(name, profile, mode="paper", ocv=ocv, max_nfev=None if effort == "full" else 2)
        per_model[name] = {"seconds": res.seconds, "rmse_v": float(res.rmse_v)}
    total = time.perf_counter() - t0
    log(f"  fitted {len(per_model)} models in {total:.1f} s ({effort} effort)")
    return {"seconds": total, "models": per_model}


# --------------------------------------------------------------------------------------------------- leaderboard
def default_leaderboard(log=print) -> dict:
    """``socbench leaderboard`` with its defaults into a temporary folder, in a subprocess (what a user types)."""
    with tempfile.TemporaryDirectory(prefix="socbench-bench-leaderboard-") as tmp:
        cmd = [sys.executable, "-m", "socbench.cli", "leaderboard", "--out", str(Path(tmp) / "out")]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True)
        seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"default leaderboard exited {proc.returncode}: {proc.stderr.strip()[-500:]}")
    summary = [line for line in proc.stdout.splitlines() if " cells (" in line]
    log(f"  default leaderboard: {seconds:.1f} s ({summary[0].strip() if summary else 'no summary'})")
    return {"seconds": seconds, "summary": summary[0].strip() if summary else ""}


# --------------------------------------------------------------------------------------------------- the whole run
def machine() -> dict:
    return {"cpu_count": os.cpu_count(), "numpy_version": np.__version__, "python_version": platform.python_version(),
            "platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "loadavg": list(os.getloadavg()) if hasattr(os, "getloadavg") else None}


def run_bench(sizes: BenchSizes = FULL, mode: str = "full", estimators=ESTIMATORS, log=print, checkpoint=None) -> dict:
    """Run every measurement of ``sizes``; returns the JSON-ready result (keys in the module docstring).

    ``checkpoint(result)``, if given, is called after each stage with what is measured so far (``complete`` False), so
    a run stopped during the long leaderboard stage still leaves its estimator and fitting figures behind.
    """
    checkpoint = checkpoint or (lambda partial: None)
    from .models import make_model, paper_params

    t_start = time.perf_counter()
    result = {"mode": mode, "machine": machine(), "repeats": sizes.repeats, "sizes": asdict(sizes),
              "tolerance": TOLERANCE}
    model = make_model(sizes.model, paper_params(sizes.model))
    sweep = monte_carlo_sweep(model, sizes.runs, sizes.steps, sizes.seed)
    log(f"bench ({mode}): {sizes.model} on the paper pack, {sizes.runs} runs × {sizes.steps} steps batched, "
        f"filterpy on {min(sizes.ref_runs, sizes.runs)} × {min(sizes.ref_steps, sizes.steps)}, "
        f"{sizes.particles} particles, {sizes.repeats} repeats")
    result["complete"] = False
    for name in estimators:
        result.update(bench_estimator(name, model, sizes, sweep, log))
        checkpoint(result)
    result["identical_results"] = all(result[f"{n}_identical"] for n in estimators)
    profile, label = hppc_profile()
    fit = fit_all_models(profile, sizes.fit, log=log)
    result.update({"fit_all_models_s": fit["seconds"], "fit_effort": sizes.fit, "fit_data": label,
                   "fit_models": fit["models"]})
    checkpoint(result)
    if sizes.leaderboard:
        board = default_leaderboard(log)
        result.update({"default_leaderboard_s": board["seconds"], "default_leaderboard_summary": board["summary"]})
    else:
        result["default_leaderboard_s"] = None  # skipped in quick mode
    result["machine"]["loadavg_after"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    result["total_s"] = time.perf_counter() - t_start
    result["complete"] = True
    return result


def sizes_for(quick: bool = False, tiny: bool = False, **overrides) -> tuple[BenchSizes, str]:
    base, mode = (TINY, "tiny") if tiny else (QUICK, "quick") if quick else (FULL, "full")
    return replace(base, **{k: v for k, v in overrides.items() if v is not None}), mode
