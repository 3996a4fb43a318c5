"""Compiled kernels (numba): every model, effect and filter loop compiled once, from one pattern.

**The pattern.** Nothing here is written per model. A model *lowers* itself to plain arrays and one compiled
interpreter evaluates any lowered model; each filter's time loop is one compiled kernel calling that interpreter::

    model ──lower()──▶ Lowered(im: int64 structure, fm: float64 numbers)          lowering.py (pure numpy)
                          │
    evaluate.py   model_step(im, fm, x, I, dt, T…) / model_output(…)              one interpreter, every model
                   ├─ model_step_points / model_output_points: a particle cloud at once (the parameters of every
                   │  point evaluated together, points innermost), the same step/output per point
                   ├─ SOC functions (Constant, Polynomial, Lookup, TemperatureTable) and OCV curves
                   ├─ the blocks B1–B6 of models/blocks.py, once each
                   ├─ one step/output pair per model *family* (rc_network, improved_rc, static_terms, tremblay, esc)
                   └─ the AugmentedModel composition with its effects
    filters.py    ekf / ukf / coulomb   pf.py  pf   openloop.py  open_loop_rows     one kernel per filter loop
    engine.py     Job: a run batch as arrays in, an Estimate out; parallel_runs: slices of runs on threads

*A new model family*: give the class a :meth:`~socbench.models.base.Model.kernel_spec` (family name, parameter list
in the order the compiled code reads them, the index ranges its step and output read, two small integers for
options), add the family to ``lowering.FAMILIES`` and its ``_x_step``/``_x_output`` pair to ``evaluate.py`` (written
with the shared blocks, dispatched in ``base_step``/``base_output``). *A new parameter form or OCV curve*: a record kind
in ``lowering.py`` and its branch in ``plain_fn``/``soc_fn``/``ocv_eval``. *A new effect*: ``kernel_values(base)`` on
the :class:`~socbench.models.effects.Effect` (the numbers its hooks read), a code in ``lowering.EFFECT_CODES`` and its
branches in ``model_step``/``model_output``. Anything without a compiled form raises ``NotLowerable`` with the reason,
and the estimator runs numpy (``Estimate.info["engine_note"]``).

*A new estimator*: keep its numpy ``_run`` (the reference), write its loop as a kernel over a run slice ``r0 … r1``
with the arguments of :class:`~socbench.kernels.engine.Job` (the model via ``model_step``/``model_output``, noise via
``measurement_var``/``process_cov``, safety via ``linalg``, outputs via ``record``/``freeze``), and add a
``_run_compiled(self, job, seed=None)`` method that calls ``parallel_runs(kernel, job.R, *job.model_args, …,
*job.out_args)`` and returns ``job.finish(info)``. List in ``kernel_hooks`` the methods its kernel implements, so that
a subclass overriding one of them runs numpy. tests/test_kernels.py picks it up from the registry and holds it to its
numpy engine at 1e-9 (outputs, states, flags, counters) on models with every parameter form, effects, temperature
tables, gating, clamping and divergences.

**Rules of the compiled code** (each one measured; docs/performance.md): compiled functions pass *pointers*, not arrays
(:func:`~socbench.kernels.evaluate.ptr`: numba passes an array as a reference-counted struct, ~30 ns per call); no
literal constant is passed to a compiled function (numba compiles a copy of it, and of everything it calls, per
literal); small helpers with few call sites are inlined (``kernel(inline=True)``), the rest stay calls (inlining
everything triples the compile time); kernels loop over a slice of runs and Python threads share the runs out (numba's
``prange`` costs more to compile than it saves); compiled code never allocates inside the time loop; a kernel ends with
:func:`~socbench.kernels.evaluate.keep_alive` over the arrays it allocated and reaches only through pointers (numba
frees an array after its variable's last use, which for those is the ``ptr`` call: the kernel would write into freed
memory, and a large block is unmapped on free: a segfault).

**Compilation** is lazy and cached (:mod:`socbench.kernels.jit`): nothing compiles at import; the first call of each
kernel compiles it (tens of seconds for all of them, once per machine and version) and stores it under a fingerprint
of the compiled sources; later processes load it in about a second. :func:`warm` compiles (or loads) every kernel up
front and says how long each took.
"""

from __future__ import annotations

import time


def warm(log=None) -> dict:
    """Compile or load every kernel the estimators and fits use, on a tiny batch; ``{kernel: seconds}``.

    On a machine whose cache holds them this is the load time (about a second in all); on a fresh one, the compile.
    """
    import numpy as np

    from ..estimators import SensorNoise, make_estimator
    from ..models import make_model, paper_params
    from ..profile import Profile
    from . import jit

    if not jit.available():
        return {}
    model = make_model("dp", paper_params("dp"))
    t = np.arange(8.0)
    cur = np.full((2, 8), 5.0)
    prof = Profile(t, cur, voltage_v=model.simulate(Profile(t, cur[0]), soc0=0.8).voltage_v + np.zeros((2, 8)))
    out = {}
    t_start = time.perf_counter()
    for name in ("coulomb", "ekf", "ukf", "pf"):
        t0 = time.perf_counter()
        opts = {"n_particles": 8} if name == "pf" else {}
        make_estimator(name, model, SensorNoise(0.01, 0.1), engine="compiled", **opts).run(prof, soc0=0.8, seed=0)
        out[name] = time.perf_counter() - t0
        if log:
            log(f"  compiled {name}: {out[name]:.1f} s")
    from .openloop import open_loop

    t0 = time.perf_counter()
    open_loop(model, model.x0(0.8, (2,)), t, cur)
    out["open_loop"] = time.perf_counter() - t0
    out["total"] = time.perf_counter() - t_start
    return out
