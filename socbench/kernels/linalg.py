"""Compiled small dense linear algebra and the numerical safety rules of :mod:`socbench.estimators.safety`.

One covariance at a time (``n × n``, n ≤ ~12), no allocation: every function takes pointers (row-major ``n × n``
matrices, :func:`socbench.kernels.evaluate.ptr`) and writes into the memory it is given.

* ``symmetrise``      ``P ← (P + Pᵀ)/2``;
* ``psd_certified``   the LDLᵀ certificate of ``safety.psd_certified`` (same margin, same operations);
* ``eigh_jacobi``     cyclic Jacobi eigen-decomposition of a symmetric matrix (Golub & Van Loan §8.5): accurate to
                      rounding for the small covariances here, and free of LAPACK calls inside parallel loops;
* ``repair_psd``      ``safety.repair_psd``: where not certified and ``λ_min < (1 − slack)·floor``, ``floor = max(abs,
                      rel·λ_max)``, rebuild
                      ``V max(Λ, floor) Vᵀ`` (symmetrised); non-finite matrices are left alone (the divergence check
                      catches them);
* ``cholesky_lower``  ``L Lᵀ = A``; returns False where a pivot is not positive (numpy's LinAlgError);
* ``gate``            the χ² innovation gate with its release (``safety.Gate``), on one run's counter;
* ``diverged_cov``, ``diverged_var``   ``safety.diverged`` for one run (full covariance, or the SOC variance only).

No literal constants are passed between compiled functions (here and in every kernel module): numba compiles a
specialised copy of a function, and of everything it calls, for each literal argument it meets.
"""

from __future__ import annotations

import math

import numpy as np

from ..estimators.safety import REPAIR_SLACK
from .jit import kernel

EPS = float(np.finfo(float).eps)
JACOBI_SWEEPS = 60


@kernel(inline=True)
def symmetrise(P, n):
    for a in range(n):
        for b in range(a + 1, n):
            v = 0.5 * (P[a * n + b] + P[b * n + a])
            P[a * n + b] = v
            P[b * n + a] = v
        P[a * n + a] = 0.5 * (P[a * n + a] + P[a * n + a])


@kernel(inline=True)
def all_finite(P, n):
    for a in range(n):
        for b in range(n):
            if not math.isfinite(P[a * n + b]):
                return False
    return True


@kernel(inline=True)
def psd_certified(P, n, abs_floor, rel_floor, work):
    """``safety.psd_certified`` for one matrix (``work``: n × n scratch)."""
    t = 0.0
    for a in range(n):
        t += P[a * n + a]
    t = abs(t)
    c = 2.0 * max(max(abs_floor, rel_floor * t), 64.0 * EPS * t)
    for a in range(n):
        for b in range(n):
            work[a * n + b] = P[a * n + b]
        work[a * n + a] = P[a * n + a] - c
    for m in range(n):
        d = work[m * n + m]
        if not d > 0.0:
            return False
        for a in range(m + 1, n):
            f = work[a * n + m]
            for b in range(m + 1, n):
                work[a * n + b] = work[a * n + b] - f * (work[m * n + b] / d)
    return True


@kernel
def eigh_jacobi(A, n, w, V, work):
    """Eigenvalues ``w (n,)`` and eigenvectors (columns of ``V``) of the symmetric ``A`` (``work``: n × n scratch)."""
    for a in range(n):
        for b in range(n):
            work[a * n + b] = A[a * n + b]
            V[a * n + b] = 1.0 if a == b else 0.0
    for _ in range(JACOBI_SWEEPS):
        off = 0.0
        scale = 0.0
        for a in range(n):
            scale += work[a * n + a] * work[a * n + a]
            for b in range(a + 1, n):
                off += work[a * n + b] * work[a * n + b]
        if off <= 1e-36 * scale or off == 0.0:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = work[p * n + q]
                if apq == 0.0:
                    continue
                theta = (work[q * n + q] - work[p * n + p]) / (2.0 * apq)
                t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                if theta < 0.0:
                    t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # A ← Jᵀ A J on columns p, q then rows p, q
                    akp = work[k * n + p]
                    akq = work[k * n + q]
                    work[k * n + p] = c * akp - s * akq
                    work[k * n + q] = s * akp + c * akq
                for k in range(n):
                    apk = work[p * n + k]
                    aqk = work[q * n + k]
                    work[p * n + k] = c * apk - s * aqk
                    work[q * n + k] = s * apk + c * aqk
                work[p * n + q] = 0.0
                work[q * n + p] = 0.0
                for k in range(n):
                    vkp = V[k * n + p]
                    vkq = V[k * n + q]
                    V[k * n + p] = c * vkp - s * vkq
                    V[k * n + q] = s * vkp + c * vkq
    for a in range(n):
        w[a] = work[a * n + a]


@kernel
def repair_psd(P, n, abs_floor, rel_floor, w, V, work):
    """``safety.repair_psd`` of one matrix, in place; returns whether it acted."""
    if psd_certified(P, n, abs_floor, rel_floor, work):
        return False
    if not all_finite(P, n):
        return False
    eigh_jacobi(P, n, w, V, work)
    lo = w[0]
    hi = w[0]
    for a in range(1, n):
        lo = min(lo, w[a])
        hi = max(hi, w[a])
    floor = max(abs_floor, rel_floor * abs(hi))
    if not lo < (1.0 - REPAIR_SLACK) * floor:
        return False
    for a in range(n):
        if w[a] < floor:
            w[a] = floor
    for a in range(n):
        for b in range(n):
            s = 0.0
            for k in range(n):
                s += V[a * n + k] * w[k] * V[b * n + k]
            P[a * n + b] = s
    symmetrise(P, n)
    return True


@kernel
def cholesky_lower(A, n, L):
    """Lower Cholesky factor of ``A`` into ``L``; False if ``A`` is not positive definite (or not finite)."""
    for a in range(n):
        for b in range(n):
            L[a * n + b] = 0.0
    for j in range(n):
        d = A[j * n + j]
        for k in range(j):
            d -= L[j * n + k] * L[j * n + k]
        if not d > 0.0:
            return False
        ljj = math.sqrt(d)
        L[j * n + j] = ljj
        for a in range(j + 1, n):
            s = A[a * n + j]
            for k in range(j):
                s -= L[a * n + k] * L[j * n + k]
            L[a * n + j] = s / ljj
    return True


@kernel(inline=True)
def gate(nis, threshold, consecutive, release):
    """``(gated, consecutive')``: skip the update when NIS > threshold, unless ``release`` skips in a row."""
    gated = nis > threshold and consecutive < release
    return gated, (consecutive + 1 if gated else 0)


@kernel(inline=True)
def _diverged_tail(var, nis, var_max, nis_max):
    """Codes 3–5 of ``safety.diverged`` (NaN-safe comparisons), 0 when none applies."""
    if not var <= var_max:
        return 3
    if not math.isfinite(nis):
        return 4
    if not nis <= nis_max:
        return 5
    return 0


@kernel(inline=True)
def diverged_cov(x, n, P, nis, var_max, nis_max):
    """``safety.diverged`` for one run with its covariance ``P``: the reason code (0: fine, else
    ``safety.DIVERGENCE_REASONS``; the first that applies, in its order)."""
    for a in range(n):
        if not math.isfinite(x[a]):
            return 1
    if not all_finite(P, n):
        return 2
    return _diverged_tail(P[0 * n + 0], nis, var_max, nis_max)


@kernel(inline=True)
def diverged_var(x, n, var, nis, var_max, nis_max):
    """``safety.diverged`` for one run with an SOC variance ``var`` only: the reason code (0: fine)."""
    for a in range(n):
        if not math.isfinite(x[a]):
            return 1
    if not math.isfinite(var):
        return 2
    return _diverged_tail(var, nis, var_max, nis_max)
