"""The glue between an :class:`~socbench.estimators.base.Estimator` and its compiled kernel.

:func:`plan` decides whether an estimator can run compiled (numba importable, the model lowers, the noise is of the
compiled form) and says why not otherwise; :class:`Job` lays a run batch out as the plain arrays every filter kernel
takes (:mod:`socbench.kernels.filters` docstring) and turns the kernel's outputs into an
:class:`~socbench.estimators.estimate.Estimate`. An estimator's ``_run_compiled(job)`` (one short method in its own
module) calls its kernel with ``job``'s arguments and returns ``job.finish(info)``.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor, wait
from functools import cache

import numpy as np

from . import jit
from .lowering import Lowered, try_lower


@cache
def cores() -> int:
    """The machine's cores (asked once: a fit asks for every batch it simulates)."""
    return max(1, os.cpu_count() or 1)


def n_threads() -> int:
    """Threads for a batch: ``$SOCBENCH_THREADS``, else one per core."""
    env = os.environ.get("SOCBENCH_THREADS")
    return max(1, int(env)) if env else cores()


def share_cores(workers: int) -> None:
    """``workers`` processes share the machine's cores: each runs its batches on ``cores // workers`` threads (set in
    ``$SOCBENCH_THREADS`` unless the user set it; a forked or spawned worker inherits it)."""
    os.environ.setdefault("SOCBENCH_THREADS", str(max(1, cores() // max(1, workers))))


#: slices of a batch per thread (parallel_runs)
SLICES_PER_THREAD = 4

#: the thread pools of this process, by size, with the process id they were started in
_POOLS: dict = {}


def thread_pool(threads: int) -> ThreadPoolExecutor:
    """A pool of ``threads`` threads kept for the life of the process. A fit simulates small batches thousands of
    times: starting the threads on every call took ~6 % of a diagnosis (a profile of seed 7's cases 1-4). Keyed on the
    process id too: a forked child inherits the parent's pool object, but not its threads."""
    key = (os.getpid(), threads)
    pool = _POOLS.get(key)
    if pool is None:
        pool = _POOLS[key] = ThreadPoolExecutor(threads, thread_name_prefix="socbench-kernel")
    return pool


def parallel_runs(kernel, n_runs: int, *args, min_runs: int = 4) -> None:
    """``kernel(r0, r1, *args)`` over slices of ``0 … n_runs − 1`` on threads (the kernels release the GIL); one
    call when the batch is small or one thread is asked for.

    A batch is cut into a few slices per thread (:data:`SLICES_PER_THREAD`, each of at least ``min_runs`` runs),
    handed out as the threads free up: on a machine shared with other jobs, a thread that is preempted no longer holds
    the whole batch up while the other one idles (with one slice per thread, the batch took as long as its slowest
    thread)."""
    threads = min(n_threads(), max(1, n_runs // min_runs))
    if threads <= 1:
        kernel(0, n_runs, *args)
        return
    slices = min(threads * SLICES_PER_THREAD, max(threads, n_runs // min_runs))
    bounds = np.linspace(0, n_runs, slices + 1).round().astype(int)
    pool = thread_pool(threads)
    futures = [pool.submit(kernel, int(a), int(b), *args) for a, b in zip(bounds[:-1], bounds[1:])]
    wait(futures)  # every slice done before an error is raised: none writes into the outputs afterwards
    for f in futures:
        f.result()


def noise_arrays(noise, n: int):
    """``(nz, walk, Qo)`` of a :class:`~socbench.estimators.noise.NoiseModel`, or a reason string when it has callable
    overrides (the compiled form is ``R = σ_V² + σ_in² D²`` or a scalar, ``Q = σ_in² B Bᵀ + diag(walk) dt/dt0`` or a
    matrix). ``walk`` holds the sensor's random walks per ``dt0`` plus the model's own (``NoiseModel.walk``, per
    second, times ``dt0``)."""
    if callable(noise.Q_override) or callable(noise.R_override):
        return "a callable Q or R override (only the sensor-noise form and constant overrides are compiled)"
    s = noise.sensor
    walk = sensor_walk(s, n)
    if noise.walk is not None:
        walk = walk + np.asarray(noise.walk, dtype=float) * s.dt
    if noise.Q_override is not None:
        walk = np.zeros(n)
    has_walk = (s.has_walk or noise.walk is not None) and noise.Q_override is None  # NoiseModel.Q: the override alone
    nz = np.array([s.voltage_sd**2, s.input_var, np.nan if noise.R_override is None else float(noise.R_override),
                   s.dt, 1.0 if has_walk else 0.0, 0.0 if noise.Q_override is None else 1.0, s.current_sd**2,
                   s.current_bias_sd**2, s.weight_extra_var])
    Qo = np.zeros((n, n)) if noise.Q_override is None else np.ascontiguousarray(noise.Q_override, dtype=float)
    return nz, np.ascontiguousarray(walk, dtype=float), Qo


def sensor_walk(sensor, n: int) -> np.ndarray:
    """The sensor noise's random-walk variances per ``sensor.dt`` ``(n,)`` (zeros without one)."""
    return np.asarray(sensor.walk_var(n, sensor.dt), dtype=float) if sensor.has_walk else np.zeros(n)


def plan(estimator) -> tuple[Lowered | None, str]:
    """``(lowered model, "")`` when ``estimator`` can run compiled, else ``(None, the reason)``."""
    if not jit.available():
        return None, "numba is not installed"
    from ..estimators.base import Estimator

    cls = type(estimator)
    if cls._run_compiled is Estimator._run_compiled:
        return None, f"estimator '{estimator.name}' has no compiled form"
    owner = next(c for c in cls.__mro__ if "_run_compiled" in c.__dict__)
    for hook in ("_run",) + tuple(getattr(owner, "kernel_hooks", ())):
        if getattr(cls, hook) is not getattr(owner, hook):
            return None, (f"estimator '{estimator.name}' overrides {hook}() of {owner.__name__}, whose compiled "
                          "kernel does not follow it")
    lowered, why = try_lower(estimator.model)
    if lowered is None:
        return None, why
    if lowered.n_variants != 1:
        return None, "a parameter batch (one model per run is not compiled for the filters)"
    noise = noise_arrays(estimator.noise, estimator.n)
    if isinstance(noise, str):
        return None, noise
    return lowered, ""


class Job:
    """One batch laid out for a filter kernel: inputs, noise and option arrays, and preallocated outputs."""

    def __init__(self, estimator, lowered: Lowered, inputs, x0, P0):
        from ..estimators.safety import gate_threshold

        opt = estimator.options
        R, T, n = inputs.n_runs, inputs.n, estimator.n
        self.estimator, self.inputs, self.R, self.T, self.n = estimator, inputs, R, T, n
        self.im, self.fm = lowered.im, np.ascontiguousarray(lowered.fm[0])
        self.x0 = np.ascontiguousarray(x0, dtype=float)
        self.P0 = np.ascontiguousarray(P0, dtype=float)
        self.cur = np.ascontiguousarray(inputs.current, dtype=float)
        self.volt = np.ascontiguousarray(inputs.voltage, dtype=float)
        self.has_temp = inputs.temp is not None
        self.temp = np.ascontiguousarray(inputs.temp, dtype=float) if self.has_temp else np.zeros((R, T))
        self.dts = np.ascontiguousarray(inputs.dt, dtype=float)
        self.hv = np.ascontiguousarray(inputs.hold_var, dtype=float)
        self.nz, self.walk, self.Qo = noise_arrays(estimator.noise, n)
        self.threshold = gate_threshold(opt["gate_alpha"])
        self.opt = np.array([self.threshold, float(opt["gate_release"]), float(opt["var_max"]), float(opt["nis_max"]),
                             float(opt["psd_floor"]), float(opt["psd_rel_floor"]),
                             1.0 if getattr(estimator.model, "schedule_soc", False) else 0.0,
                             1.0 if opt.get("gate_widen") else 0.0])
        self.store = bool(opt["store_states"])
        self.outf = np.empty((5, R, T))
        self.outb = np.zeros((2, R, T), dtype=np.bool_)
        self.xs = np.empty((R, T, n) if self.store else (1, 1, n))
        self.pd = np.empty((R, T, n) if self.store else (1, 1, n))
        self.failed = np.zeros(R, dtype=np.int8)  # the reason code of a failed run (safety.DIVERGENCE_REASONS)
        self.failed_at = np.full(R, -1, dtype=np.int64)
        self.status = np.zeros(R, dtype=np.int64)
        self.repairs = np.zeros(R, dtype=np.int64)

    def keep_states(self) -> None:
        """Store the states and variances of every sample whatever ``store_states`` says (an estimator that reads
        them after the run, e.g. the joint filter's parameter paths)."""
        if not self.store:
            self.store = True
            self.xs = np.empty((self.R, self.T, self.n))
            self.pd = np.empty((self.R, self.T, self.n))

    def add_walk(self, var_per_dt0) -> None:
        """Add an estimator's own random-walk variances per sensor period ``(n,)`` to Q (also under an override)."""
        self.walk = np.ascontiguousarray(self.walk + np.asarray(var_per_dt0, dtype=float))
        self.nz = self.nz.copy()
        self.nz[4] = 1.0  # filters.HAS_WALK

    @property
    def model_args(self) -> tuple:
        return (self.im, self.fm, self.x0, self.P0, self.cur, self.volt, self.temp, self.has_temp, self.dts, self.hv)

    @property
    def noise_args(self) -> tuple:
        return (self.nz, self.walk, self.Qo)

    @property
    def out_args(self) -> tuple:
        # the flags as bytes: a compiled function stores into them through a pointer (kernels.filters.record)
        return (self.outf, self.outb.view(np.uint8), self.xs, self.pd, self.store, self.failed, self.failed_at,
                self.status, self.repairs)

    def kalman(self, variant: int, vopt=(0.0,)):
        """Run the EKF-family kernel (:func:`socbench.kernels.filters.ekf`) with update ``variant`` over the batch;
        returns its per-run outputs ``(R, 2)`` (the variant's ``vout``)."""
        from .filters import ekf

        vout = np.zeros((self.R, 2))
        parallel_runs(ekf, self.R, *self.model_args, *self.noise_args, self.opt, int(variant),
                      np.asarray(vopt, dtype=float), vout, *self.out_args)
        return vout

    def finish(self, info: dict):
        """The :class:`Estimate`, or None when a run met a condition only the numpy engine reports (its status)."""
        from ..estimators.estimate import Estimate

        if self.status.any():
            return None
        m = self.estimator.model
        return Estimate(
            time_s=self.inputs.time_s, soc=self.outf[0], soc_std=self.outf[1], v_pred=self.outf[2],
            innovation=self.outf[3], innovation_var=self.outf[4], failed=self.failed != 0, failed_at=self.failed_at,
            clamped=self.outb[0], gated=self.outb[1], x=self.xs if self.store else None,
            P_diag=self.pd if self.store else None, estimator=self.estimator.name,
            model=getattr(m, "name", type(m).__name__), state_names=tuple(m.state_names),
            info={"psd_repairs": self.repairs.astype(int), **info}, failed_reason=self.failed.copy(),
        )
