"""Compiled open-loop simulation: ``y_k = h(x_k, I_k)``, ``x_{k+1} = f(x_k, I_k, dt_k)`` for a batch of rows, each
with its own parameter variant — what fitting evaluates hundreds of times (``P + 1`` parameter variants per
least-squares iteration, :mod:`socbench.identify.lsq`).

The same step loop as :meth:`~socbench.models.base.Model.open_loop_stepwise` (output, then step, then the record's
SOC jump), compiled: the numbers equal the step loop's to rounding and the whole-record prefix scan's
(:meth:`Model.open_loop`) to ~1e-15 relative. :func:`open_loop` is the Python entry: it returns None when the model
(or the batch layout) has no compiled form, and the caller runs the numpy open loop instead.
"""

from __future__ import annotations

import numpy as np

from .evaluate import WORK_SIZE, keep_alive, model_output, model_step, ptr, ptr_at
from .jit import kernel
from .lowering import try_lower


@kernel
def open_loop_rows(r0, r1, im, fm2, x0, cur, temp, has_temp, dts, jumps, volts, states, store, status):
    """Rows ``r0 … r1 − 1``: row ``b`` uses variant ``b`` of ``fm2`` (or its only row), current row ``b`` of
    ``cur`` (or its only row), likewise ``temp``."""
    T = volts.shape[1]
    n = x0.shape[1]
    V, L = fm2.shape
    jac = n < 0  # run-time False (a literal would make numba compile copies of every callee)
    x = np.empty(n)
    xn = np.empty(n)
    H = np.empty(n)
    B = np.empty(n)
    F = np.empty((n, n))
    scratch = np.empty(WORK_SIZE)
    imp, xp, xnp, Hp, Bp, Fp, sp = ptr(im), ptr(x), ptr(xn), ptr(H), ptr(B), ptr(F), ptr(scratch)
    for b in range(r0, r1):
        fmp = ptr_at(fm2, (b if V > 1 else 0) * L)
        rc = b if cur.shape[0] > 1 else 0
        rt = b if temp.shape[0] > 1 else 0
        for a in range(n):
            x[a] = x0[b, a]
        for k in range(T):
            if store:
                for a in range(n):
                    states[b, k, a] = x[a]
            y, _, st = model_output(imp, fmp, xp, cur[rc, k], temp[rt, k], has_temp, jac, Hp, sp)
            if st != 0:
                status[b] = st
                break
            volts[b, k] = y
            if k + 1 < T:
                st = model_step(imp, fmp, xp, cur[rc, k], dts[k], temp[rt, k], has_temp, jac, xnp, Fp, Bp, sp)
                if st != 0:
                    status[b] = st
                    break
                for a in range(n):
                    x[a] = xn[a]
                x[0] += jumps[k + 1]
    keep_alive((x, xn, H, B, F, scratch))




def open_loop(model, x0, time_s, current_a, temp_c=None, soc_jumps=None, states: bool = False):
    """``(states (B, T, n) or None, voltage (B, T))`` — or ``(…, (T,))`` for a single state — of the compiled step loop,
    or None when it does not apply (model not lowerable, a batch layout other than rows × variants, or
    a model condition only numpy reports: the caller then runs :meth:`Model.open_loop`)."""
    lowered, _ = try_lower(model)
    if lowered is None:
        return None
    x0 = np.asarray(x0, dtype=float)
    single = x0.ndim == 1
    x0 = np.ascontiguousarray(np.atleast_2d(x0))
    if x0.ndim != 2 or x0.shape[1] != lowered.n_states:
        return None
    Bn = x0.shape[0]
    V = lowered.n_variants
    if V not in (1, Bn):
        return None
    t = np.asarray(time_s, dtype=float)
    T = t.size
    cur = np.ascontiguousarray(np.atleast_2d(np.asarray(current_a, dtype=float)))
    if cur.ndim != 2 or cur.shape[1] != T or cur.shape[0] not in (1, Bn):
        return None
    has_temp = temp_c is not None
    temp = np.zeros((1, T)) if not has_temp else np.ascontiguousarray(np.atleast_2d(np.asarray(temp_c, float)))
    if temp.ndim != 2 or temp.shape[1] != T or temp.shape[0] not in (1, Bn):
        return None
    jumps = np.zeros(T) if soc_jumps is None else np.ascontiguousarray(soc_jumps, dtype=float)
    volts = np.empty((Bn, T))
    st = np.empty((Bn, T, x0.shape[1]) if states else (1, 1, x0.shape[1]))
    status = np.zeros(Bn, dtype=np.int64)
    from .engine import parallel_runs

    parallel_runs(open_loop_rows, Bn, lowered.im, np.ascontiguousarray(lowered.fm), x0, cur, temp, has_temp,
                  np.ascontiguousarray(np.diff(t)), jumps, volts, st, bool(states), status)
    if status.any():
        return None
    if single:
        return (st[0] if states else None), volts[0]
    return (st if states else None), volts
