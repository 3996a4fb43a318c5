"""Linear recurrences over a whole record at once: the time loop of a model whose states, once the SOC path is known,
evolve linearly.

Every RC-type model has the form ``x_{k+1} = A_k x_k + c_k`` in its polarisation states, with ``A_k`` and ``c_k``
fixed by the SOC ``z_k`` and the current ``I_k`` of the step (B2, B3, B5), and the SOC path itself is a running sum of
the current (B1) that no parameter other than the capacity touches. Given the whole current record, every ``A_k`` and
``c_k`` can be evaluated in one vectorised call, and the recurrence solved by a *parallel prefix scan* of the affine
maps ``M_k(x) = A_k x + c_k``::

    (A, c)_k ∘ (A, c)_j = (A_k A_j,  A_k c_j + c_k)          (composition of two affine maps)

Hillis–Steele doubling: after the pass with stride ``d`` entry ``k`` holds ``M_k ∘ … ∘ M_{k−2d+1}``, so
``⌈log₂ T⌉`` passes give every prefix ``P_k = M_k ∘ … ∘ M_0`` and ``x_{k+1} = P_k(x_0)``. Each pass is a few numpy
operations over the whole ``(T, batch)`` array instead of ``T`` Python-level steps: fitting, which simulates the same
record hundreds of times for dozens of parameter variants, is where this pays.

The result equals the step-by-step loop to rounding (a different summation order: relative differences ~1e-15 per
pass); the model tests check it against ``step`` on every model that uses it. Products of many ``A_k < 1`` underflow to
0, which is the correct limit (the memory of the initial state is gone).
"""

from __future__ import annotations

import numpy as np


def running_sum(x0, increments, extra=None) -> np.ndarray:
    """``x_0 = x0``, ``x_{k+1} = (x_k + increments_k) + extra_{k+1}`` for ``k = 0 … T−2``, time on the first axis.

    The same additions in the same order as the step loop (``extra`` is what the loop adds after a step, e.g. charge
    missing from a record's current column): bit-for-bit the loop's result. ``increments`` has shape
    ``(T − 1, *batch)``, ``extra`` ``(T, *batch)`` or None (its entry 0 is unused); returns ``(T, *batch)``.
    """
    inc = np.asarray(increments, dtype=float)
    x0 = np.broadcast_to(np.asarray(x0, dtype=float), inc.shape[1:])
    n = inc.shape[0]
    if extra is None:
        seq = np.concatenate([x0[None], inc], axis=0)
        return np.cumsum(seq, axis=0)
    ex = np.broadcast_to(np.asarray(extra, dtype=float), (n + 1,) + inc.shape[1:])
    seq = np.empty((2 * n + 1,) + inc.shape[1:])
    seq[0] = x0
    seq[1::2] = inc
    seq[2::2] = ex[1:]
    return np.cumsum(seq, axis=0)[::2]


def affine_scan(a, c, x0) -> np.ndarray:
    """All states of ``x_{k+1} = a_k x_k + c_k`` (elementwise ``a``), time on the first axis.

    ``a``, ``c``: ``(T − 1, *batch)`` (broadcastable to each other), ``x0``: ``(*batch)``. Returns ``(T, *batch)`` with
    ``x[0] = x0``.
    """
    a, c = np.broadcast_arrays(np.asarray(a, dtype=float), np.asarray(c, dtype=float))
    A, C = a.copy(), c.copy()
    n = A.shape[0]
    d = 1
    while d < n:
        C[d:] += A[d:] * C[:-d]  # the product is a temporary: C[:-d] is read before C[d:] is written
        A[d:] *= A[:-d]  # numpy resolves the overlap as if the input were copied first
        d *= 2
    out = np.empty((n + 1,) + A.shape[1:])
    out[0] = x0
    np.multiply(A, x0, out=out[1:])
    out[1:] += C
    return out


def matrix_affine_scan(A, c, x0) -> np.ndarray:
    """All states of ``x_{k+1} = A_k x_k + c_k`` with ``A_k`` an ``m × m`` matrix, time on the first axis.

    ``A``: ``(T − 1, *batch, m, m)``, ``c``: ``(T − 1, *batch, m)``, ``x0``: ``(*batch, m)``. Returns
    ``(T, *batch, m)``. The small matrix products are written out entry by entry (``m³`` elementwise operations over
    the whole record): numpy's ``matmul`` on millions of 2 × 2 matrices costs ~100 ns per product, the entry-wise form
    a few ns.
    """
    A = np.asarray(A, dtype=float)
    m = A.shape[-1]
    a = [[A[..., r, q].copy() for q in range(m)] for r in range(m)]  # a[r][q]: (T − 1, *batch)
    cc = [np.array(np.broadcast_to(c[..., r], a[0][0].shape), dtype=float) for r in range(m)]
    n = a[0][0].shape[0]
    d = 1
    while d < n:
        # (A, c)_k ← (A_k A_{k−d}, A_k c_{k−d} + c_k) for k ≥ d, from the values before this pass
        new_c = [cc[r][d:] + sum(a[r][q][d:] * cc[q][:-d] for q in range(m)) for r in range(m)]
        new_a = [[sum(a[r][j][d:] * a[j][q][:-d] for j in range(m)) for q in range(m)] for r in range(m)]
        for r in range(m):
            cc[r][d:] = new_c[r]
            for q in range(m):
                a[r][q][d:] = new_a[r][q]
        d *= 2
    x0 = np.asarray(x0, dtype=float)
    out = np.empty((n + 1,) + a[0][0].shape[1:] + (m,))
    out[0] = x0
    for r in range(m):
        out[1:, ..., r] = cc[r] + sum(a[r][q] * x0[..., q] for q in range(m))
    return out


# ------------------------------------------------------------------------------ the blocks' whole-record forms
def lowpass_path(a, i, i0) -> np.ndarray:
    """B4 over a record: ``I*⁺ = a I* + (1 − a) I`` (``a = e^{−dt/t_c}`` per step), time first, from ``I*_0 = i0``."""
    return affine_scan(a, (1.0 - a) * i, i0)


def hysteresis_path(decay, i, moving, h0, s0):
    """Plett's hysteresis over a record, time first: ``(h, s)``.

    ``h⁺ = A h − (1 − A) sgn I`` with the per-step decay ``A``, and the sign memory ``s⁺ = sgn I`` while ``moving``,
    else ``s`` (an affine map with ``a = 0`` or ``1``). Each step of ``h`` is a convex combination of ``h`` and ``±1``,
    so ``|h| ≤ 1``; the scan's summation order can overshoot that by an ulp, which the clip removes (the step loop
    stays inside by construction).
    """
    sg = np.sign(i)
    h = np.clip(affine_scan(decay, -(1.0 - decay) * sg, h0), -1.0, 1.0)
    s = affine_scan(np.where(moving, 0.0, 1.0), np.where(moving, sg, 0.0), s0)
    return h, s
