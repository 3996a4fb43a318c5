"""``socbench bench``: socbench's engines against a bare filterpy loop and against its own references, side by side.

What is measured (DESIGN.md, "Performance")::

    sweep      a Monte Carlo sweep on the paper pack (22 Ah, 6S): the dp model (2 RC, 3 states) as its own truth on one
               dynamic pulse current (dt = 1 s), R runs with their own sensor noise (σ_V = 10 mV, σ_I = 0.2 A) and
               their own initial-SOC guess (truth 0.95, guess error N(0, 0.05²))
    scaling    EKF, UKF and PF (100 particles) at R = 1, 10, 100, 1000, 10 000 runs (PF: 1 … 1000), three engines:
               bare filterpy   the hand-written dp model in a plain filterpy loop (socbench.barefilterpy): its cost is
                               linear in the runs, so it is timed on a few runs and its µs per step is the µs per
                               run-step at every R (R runs cost R times one run)
               socbench numpy     make_estimator(name, engine="numpy").run(sweep)
               socbench compiled  make_estimator(name, engine="compiled").run(sweep)   (kernels compiled before)
               → µs per run-step = t / (R·T); speed-up = bare / engine at each R. T shrinks with R so that every
               measurement stays within a budget of run-steps (µs per run-step does not depend on T: no state grows)
    compile    the first call of every kernel in this process (compile, or load from the cache), and in full mode a
               cold compile in a subprocess with an empty cache
    reference  every estimator with a reference backend: the default engine against filterpy's per-run classes (or
               a textbook per-run form) on the first R_f runs and T_f steps; max |difference| over soc, soc_std, v_pred,
               innovation, innovation_var ≤ 1e-9 with equal gate/clamp/failure flags (``{name}_identical``); and
               compiled against numpy on the same runs (``{name}_compiled_vs_numpy``)

Each timing is repeated (the engines alternate within a repeat, so load on a shared machine hits them alike) and
the medians are reported, with every repeat kept; wall and process-CPU time are both recorded. ``fit_all_models_s``
fits every registered model (paper mode) to the Panasonic 25 °C HPPC when ``SOCBENCH_DATA_DIR`` is set, else to the
built-in HPPC (at most 2 least-squares evaluations per model in quick mode, ``fit_effort`` says which); in full mode
``default_leaderboard_s`` runs ``socbench leaderboard`` with its defaults into a temporary folder and, with the data,
``estimate_us06_s`` times ``socbench estimate`` (EKF, UKF) on the 25 °C US06 with parameters fitted on the HPPC.
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
    """How big each measurement is. ``ref_runs × ref_steps`` is the reference subset (a prefix of the sweep)."""

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
    #: the scaling against the bare filterpy loop (module docstring)
    scale_runs: tuple = (1, 10, 100, 1000, 10000)
    scale_steps: int = 2000
    pf_runs: tuple = (1, 10, 100, 1000)
    pf_steps: int = 1000
    pf_particles: int = 100
    bare_runs: int = 2
    bare_steps: int = 1000
    #: run-steps (PF: particle-steps) per timed run of each engine: T = min(steps, budget / runs)
    compiled_budget: float = 4e6
    numpy_budget: float = 4e5
    pf_compiled_budget: float = 2e7
    pf_numpy_budget: float = 2e6
    #: full mode: a cold compile in a subprocess, and `socbench estimate` on the Panasonic US06
    cold_compile: bool = True
    estimate_us06: bool = True


FULL = BenchSizes()
QUICK = BenchSizes(runs=40, steps=400, ref_runs=1, ref_steps=200, particles=32, fit="capped", leaderboard=False,
                   scale_runs=(1, 100, 1000), scale_steps=500, pf_runs=(1, 100), pf_steps=200, bare_runs=1,
                   bare_steps=300, compiled_budget=1e6, numpy_budget=1e5, pf_compiled_budget=4e6,
                   pf_numpy_budget=4e5, cold_compile=False, estimate_us06=False)
#: hidden ``--tiny`` option: a smoke test of the whole pipeline in seconds (tests only; the figures mean nothing)
TINY = BenchSizes(runs=3, steps=20, ref_runs=2, ref_steps=20, particles=16, fit="tiny", leaderboard=False,
                  scale_runs=(1, 3), scale_steps=20, pf_runs=(1, 3), pf_steps=10, pf_particles=16, bare_runs=1,
                  bare_steps=10, compiled_budget=100, numpy_budget=60, pf_compiled_budget=500, pf_numpy_budget=500,
                  cold_compile=False, estimate_us06=False)
TINY_FIT_MODELS = ("rint", "thevenin")
#: the filters that have a bare filterpy loop (socbench.barefilterpy), and the run count of their headline ratio
SCALED = {"ekf": 1000, "ukf": 1000, "pf": 100}

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


# --------------------------------------------------------------------------------------------------- references
def bench_reference(name: str, model, sizes: BenchSizes, sweep, log=print) -> dict:
    """The default engine on the sweep against ``name``'s reference backend on a prefix of it: timings and the
    identical-results checks (reference, and compiled against numpy)."""
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
        log(f"  {name} repeat {rep + 1}/{sizes.repeats}: socbench ({est_b.info['engine']}) {tb:.2f} s "
            f"({sizes.runs}×{sizes.steps}), reference {tr:.2f} s ({Rf}×{Tf})")
    check = compare(est_b, est_r)  # every engine draws a run's numbers from its index: the prefix rows compare
    numpy_est = make_estimator(name, model, noise, engine="numpy", **opts).run(shared, soc0=soc0[:Rf], P0=P0,
                                                                              seed=sizes.seed)
    same = compare(est_b, numpy_est)
    us_b = statistics.median(t_b) / (sizes.runs * sizes.steps) * 1e6
    us_r = statistics.median(t_r) / (Rf * Tf) * 1e6
    return {
        f"{name}_engine": est_b.info["engine"],
        f"{name}_sweep_us_per_run_step": us_b,
        f"{name}_reference_us_per_step": us_r,
        f"{name}_reference_speedup": us_r / us_b,
        f"{name}_max_abs_diff": check["max_abs_diff"],
        f"{name}_identical": check["identical"],
        f"{name}_compiled_vs_numpy_max_abs_diff": same["max_abs_diff"],
        f"{name}_compiled_vs_numpy_identical": same["identical"],
        f"{name}_failed_runs": int(np.count_nonzero(est_b.failed)),
        f"{name}_sweep_cpu_us_per_run_step": statistics.median(c_b) / (sizes.runs * sizes.steps) * 1e6,
        f"{name}_reference_cpu_us_per_step": statistics.median(c_r) / (Rf * Tf) * 1e6,
        f"{name}_reference_repeats_s": {"socbench": t_b, "reference": t_r, "socbench_cpu": c_b, "reference_cpu": c_r},
    }


# --------------------------------------------------------------------------------------------------- scaling
def _steps_for(runs: int, steps: int, budget: float, per_run: int = 1) -> int:
    """Steps of a timed run: ``min(steps, budget / (runs·per_run))``, at least 10 (and at most ``steps``)."""
    return int(min(steps, max(10, budget // (runs * per_run))))


def time_bare(name: str, params, sweep, runs: int, steps: int, particles: int, seed: int):
    """``(wall s, CPU s)`` per run-step of the bare filterpy loop on the first ``runs`` runs, ``steps`` steps."""
    from .barefilterpy import BareDP, bare_ekf, bare_pf, bare_ukf

    profile, soc0, P0 = sweep
    model = BareDP.from_params(params)
    dt = np.diff(profile.time_s[:steps])
    P0m = np.diag(P0)

    def go():
        for r in range(runs):
            args = (model, profile.current_a[r, :steps], profile.voltage_v[r, :steps], dt, soc0[r], P0m,
                    SENSOR["voltage_sd"], SENSOR["current_sd"])
            if name == "ekf":
                bare_ekf(*args)
            elif name == "ukf":
                bare_ukf(*args)
            else:
                bare_pf(*args, n_particles=particles, seed=seed + r)

    wall, cpu, _ = _timed(go)
    return wall / (runs * steps), cpu / (runs * steps)


def bench_scaling(name: str, model, params, sizes: BenchSizes, log=print) -> dict:
    """µs per run-step of the three engines at every run count of ``sizes`` (module docstring), and the speed-ups."""
    from .estimators import SensorNoise, make_estimator

    pf = name == "pf"
    N = sizes.pf_particles
    runs_list = sizes.pf_runs if pf else sizes.scale_runs
    T_max = sizes.pf_steps if pf else sizes.scale_steps
    per_run = N if pf else 1
    budgets = {"compiled": sizes.pf_compiled_budget if pf else sizes.compiled_budget,
               "numpy": sizes.pf_numpy_budget if pf else sizes.numpy_budget}
    noise = SensorNoise(**SENSOR)
    opts = {"n_particles": N} if pf else {}
    engines = {e: make_estimator(name, model, noise, engine=e, **opts) for e in ("numpy", "compiled")}
    steps = {(e, R): _steps_for(R, T_max, budgets[e], per_run) for e in engines for R in runs_list}
    sweeps = {R: monte_carlo_sweep(model, R, max(steps[(e, R)] for e in engines), sizes.seed) for R in runs_list}
    bare_sweep = monte_carlo_sweep(model, sizes.bare_runs, sizes.bare_steps, sizes.seed)
    wall = {(e, R): [] for e in engines for R in runs_list}
    cpu = {k: [] for k in wall}
    bare_wall, bare_cpu = [], []
    for rep in range(sizes.repeats):
        bw, bc = time_bare(name, params, bare_sweep, sizes.bare_runs, sizes.bare_steps, N, sizes.seed)
        bare_wall.append(bw)
        bare_cpu.append(bc)
        for R in runs_list:
            for e, est in engines.items():
                T = steps[(e, R)]
                prof, soc0, P0 = sweeps[R]
                prof = _prefix(prof, R, T)
                w, c, _ = _timed(lambda est=est, prof=prof, soc0=soc0, P0=P0: est.run(prof, soc0=soc0, P0=P0,
                                                                                      seed=sizes.seed))
                wall[(e, R)].append(w / (R * T))
                cpu[(e, R)].append(c / (R * T))
        log(f"  {name} scaling repeat {rep + 1}/{sizes.repeats}: bare filterpy {bw * 1e6:.1f} µs/step; compiled "
            + ", ".join(f"R={R}: {wall[('compiled', R)][-1] * 1e6:.3g}" for R in runs_list) + " µs/run-step")
    bare_us = statistics.median(bare_wall) * 1e6
    rows = [{"estimator": name, "engine": "bare filterpy", "runs": R, "steps": sizes.bare_steps,
             "timed_runs": sizes.bare_runs, "particles": N if pf else None, "us_per_run_step": bare_us,
             "cpu_us_per_run_step": statistics.median(bare_cpu) * 1e6, "repeats_s": bare_wall,
             "extrapolated": R != sizes.bare_runs} for R in runs_list]
    out = {f"{name}_bare_us_per_step": bare_us, f"{name}_bare_cpu_us_per_step": statistics.median(bare_cpu) * 1e6}
    for e in engines:
        label = f"socbench {e}"
        us = {R: statistics.median(wall[(e, R)]) * 1e6 for R in runs_list}
        rows += [{"estimator": name, "engine": label, "runs": R, "steps": steps[(e, R)], "timed_runs": R,
                  "particles": N if pf else None, "us_per_run_step": us[R],
                  "cpu_us_per_run_step": statistics.median(cpu[(e, R)]) * 1e6, "repeats_s": wall[(e, R)],
                  "extrapolated": False} for R in runs_list]
        out[f"{name}_{e}_us_per_run_step"] = {str(R): us[R] for R in runs_list}
        out[f"{name}_{e}_speedup_vs_bare"] = {str(R): bare_us / us[R] for R in runs_list}
    head = SCALED[name] if SCALED[name] in runs_list else runs_list[-1]
    out.update({f"{name}_headline_runs": head, f"{name}_filterpy_us_per_step": bare_us,
                f"{name}_batched_us_per_run_step": out[f"{name}_compiled_us_per_run_step"][str(head)],
                f"{name}_speedup": bare_us / out[f"{name}_compiled_us_per_run_step"][str(head)],
                f"{name}_scaling_rows": rows})
    return out


# --------------------------------------------------------------------------------------------------- compilation
def cold_compile(log=print) -> dict:
    """Every kernel compiled in a fresh subprocess with an empty cache: ``{"wall_s", "cpu_s", "kernels"}``."""
    import json
    import resource

    code = ("import json, time; t = time.perf_counter(); from socbench.kernels import warm; "
            "r = warm(); r['process_s'] = time.perf_counter() - t; print(json.dumps(r))")
    with tempfile.TemporaryDirectory(prefix="socbench-cold-compile-") as tmp:
        env = {**os.environ, "SOCBENCH_NUMBA_CACHE": tmp}
        root = str(Path(__file__).resolve().parents[1])
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
        ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"cold compile failed: {proc.stderr.strip()[-500:]}")
    kernels = json.loads(proc.stdout.strip().splitlines()[-1])
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    log(f"  cold compile of every kernel: {wall:.1f} s wall, {cpu:.1f} CPU-s (empty cache, fresh process)")
    return {"wall_s": wall, "cpu_s": cpu, "kernels": kernels}


# --------------------------------------------------------------------------------------------------- US06
def estimate_us06(log=print) -> dict | None:
    """``socbench estimate`` (EKF, UKF) on the Panasonic 25 °C US06 with parameters from ``socbench fit`` on the 25 °C
    HPPC: wall seconds of each command in a subprocess (Python start-up, imports, reading, the filter; kernels loaded
    from the cache), or None without the data."""
    root = os.environ.get("SOCBENCH_DATA_DIR")
    if not root:
        return None
    folder = Path(root) / "panasonic_18650pf" / "25degC"
    us06 = sorted(folder.glob("*US06*.mat"))
    hppc = sorted(folder.glob("*HPPC*.mat"))
    if not us06 or not hppc:
        return None
    out = {"data": us06[0].name}
    with tempfile.TemporaryDirectory(prefix="socbench-us06-") as tmp:
        params = Path(tmp) / "params.json"
        base = [sys.executable, "-m", "socbench.cli"]
        env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]) + os.pathsep
               + os.environ.get("PYTHONPATH", "")}
        fit = subprocess.run(base + ["fit", "--data", str(hppc[0]), "--model", "dp", "--out", str(params)],
                             capture_output=True, text=True, env=env)
        if fit.returncode != 0:
            raise RuntimeError(f"socbench fit failed: {fit.stderr.strip()[-300:]}")
        for name in ("ekf", "ukf"):
            cmd = base + ["estimate", "--data", str(us06[0]), "--params", str(params), "--estimator", name,
                          "--out", str(Path(tmp) / name)]
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
            out[name] = time.perf_counter() - t0
            if proc.returncode != 0:
                raise RuntimeError(f"socbench estimate failed: {proc.stderr.strip()[-300:]}")
            log(f"  socbench estimate --estimator {name} on {us06[0].name}: {out[name]:.2f} s")
    return out


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
    """Run every measurement of ``sizes``; returns the JSON-ready result (keys in the module docstring and
    docs/performance.md).

    ``checkpoint(result)``, if given, is called after each stage with what is measured so far (``complete`` False), so
    a run stopped during the long leaderboard stage still leaves its estimator and fitting figures behind.
    """
    checkpoint = checkpoint or (lambda partial: None)
    from .kernels import jit, warm
    from .models import make_model, paper_params

    t_start = time.perf_counter()
    result = {"mode": mode, "machine": machine(), "repeats": sizes.repeats, "sizes": asdict(sizes),
              "tolerance": TOLERANCE, "numba": jit.available()}
    params = paper_params(sizes.model)
    model = make_model(sizes.model, params)
    result["complete"] = False
    log(f"bench ({mode}): {sizes.model} on the paper pack; load average {result['machine']['loadavg'][0]:.1f}")
    result["first_call_s"] = warm(log)  # compile or load every kernel before anything is timed
    if sizes.cold_compile and jit.available():
        result["cold_compile"] = cold_compile(log)
    checkpoint(result)
    for name in (n for n in SCALED if n in estimators):
        result.update(bench_scaling(name, model, params, sizes, log))
        checkpoint(result)
    sweep = monte_carlo_sweep(model, sizes.runs, sizes.steps, sizes.seed)
    log(f"references: {sizes.runs} runs × {sizes.steps} steps against {min(sizes.ref_runs, sizes.runs)} × "
        f"{min(sizes.ref_steps, sizes.steps)}, {sizes.particles} particles")
    for name in estimators:
        result.update(bench_reference(name, model, sizes, sweep, log))
        checkpoint(result)
    result["identical_results"] = all(result[f"{n}_identical"] and result[f"{n}_compiled_vs_numpy_identical"]
                                      for n in estimators)
    profile, label = hppc_profile()
    fit = fit_all_models(profile, sizes.fit, log=log)
    result.update({"fit_all_models_s": fit["seconds"], "fit_effort": sizes.fit, "fit_data": label,
                   "fit_models": fit["models"]})
    checkpoint(result)
    result["estimate_us06_s"] = estimate_us06(log) if sizes.estimate_us06 else None
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
