"""Numerical safety shared by the filters: symmetric PSD covariances, SOC clamp, innovation gate, divergence.

* symmetrise      ``P ← (P + Pᵀ)/2`` after every update and prediction (round-off makes P drift asymmetric);
* PSD repair      where ``λ_min(P) < (1 − s)·floor`` rebuild ``P = V max(Λ, floor) Vᵀ`` with
                  ``floor = max(abs_floor, rel_floor·λ_max)``; matrices that are fine are left bit-for-bit alone. The
                  slack ``s`` = :data:`REPAIR_SLACK` keeps a matrix that sits at the floor (repaired before, to
                  rounding: the eigenvalues of two implementations differ by ~ε·λ_max, i.e. ~1e-4 of a 1e-12·λ_max
                  floor) from being "repaired" again, which would change nothing but the repair count;
* SOC bound       a Kalman update that leaves [0, 1] is projected onto the bound with the whole state
                  (:func:`project_soc`); the counter and the particles clip ``z ← clip(z, 0, 1)``; flagged per sample;
* innovation gate skip the update when ``NIS = e²/S > χ²_{1−α}(1)``, counted; after ``release`` consecutive skips the
                  next update is taken anyway, so a filter that started far off is never locked out for good;
* divergence      a run whose state, covariance or NIS is not finite, whose SOC variance exceeds ``var_max`` or whose
                  NIS exceeds ``nis_max`` is marked failed; its internal state is reset to the last good (finite)
                  values so the batch keeps computing, and its outputs are frozen by the recorder. :func:`diverged`
                  returns *why* (a code of :data:`DIVERGENCE_REASONS`, 0 = fine), which the recorder keeps per run.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import special


def symmetrise(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def psd_certified(P: np.ndarray, abs_floor: float = 1e-15, rel_floor: float = 1e-12) -> np.ndarray:
    """(…,) bool: where ``λ_min(P) ≥ floor`` is certain without an eigen-decomposition (the usual case, cheaply).

    With ``t = tr P`` and ``c = 2·max(abs_floor, rel_floor·|t|, 64ε|t|)``: if every pivot of an LDLᵀ elimination of
    ``P − c I`` is positive, ``P − c I`` is positive definite, hence so is ``P``, ``λ_max ≤ t``, and the repair floor
    ``max(abs_floor, rel_floor·λ_max) ≤ c/2 < λ_min``: the eigenvalue test below would pass the matrix untouched. The
    margin (a factor 2, and at least 128ε·t) dwarfs the elimination's rounding (~n ε t). NaN/inf never certify.
    Batched over runs; the only loop is over the n states.
    """
    n = P.shape[-1]
    ok = np.ones(P.shape[:-2], dtype=bool)
    with np.errstate(all="ignore"):
        t = np.abs(np.trace(P, axis1=-2, axis2=-1))
        c = 2.0 * np.maximum(np.maximum(abs_floor, rel_floor * t), 64.0 * np.finfo(float).eps * t)
        A = P - c[..., None, None] * np.eye(n)
        for _ in range(n):
            d = A[..., 0, 0]
            ok &= d > 0.0
            A = A[..., 1:, 1:] - A[..., 1:, :1] * (A[..., :1, 1:] / d[..., None, None])
    return ok


#: relative slack below the floor before a matrix counts as needing the repair (module docstring)
REPAIR_SLACK = 1e-2


def repair_psd(P: np.ndarray, abs_floor: float = 1e-15, rel_floor: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """``(P', repaired (…,) bool)``: eigenvalues below the floor raised to it (only where needed).

    ``floor = max(abs_floor, rel_floor·λ_max)``; matrices that :func:`psd_certified` passes skip the eigenvalue test
    (which would leave them alone: the result is the same, without the batched ``eigvalsh`` on every step).
    """
    ok = psd_certified(P, abs_floor, rel_floor)
    need = np.zeros(ok.shape, dtype=bool)
    if ok.all():
        return P, need
    rows = ~ok
    Q = P[rows]
    finite = np.all(np.isfinite(Q), axis=(-1, -2))
    Qf = np.where(finite[..., None, None], Q, 0.0)
    w = np.linalg.eigvalsh(Qf)
    floor = np.maximum(abs_floor, rel_floor * np.abs(w[..., -1]))
    sub = finite & (w[..., 0] < (1.0 - REPAIR_SLACK) * floor)
    if not sub.any():
        return P, need
    need[rows] = sub
    P = P.copy()
    w_bad, V = np.linalg.eigh(Qf[sub])
    w_bad = np.maximum(w_bad, floor[sub][..., None])
    P[need] = symmetrise((V * w_bad[..., None, :]) @ np.swapaxes(V, -1, -2))
    return P, need


def project_soc(x: np.ndarray, P: np.ndarray, factor: bool = False) -> np.ndarray:
    """Put ``x[..., 0]`` back into [0, 1] by projecting the whole state onto the bound (in place); returns the
    (…,) flag of where it acted. ``P`` (…, n, n) the covariance, or its lower-triangular root with ``factor=True``.

    Estimate projection (Simon & Chia, "Kalman filtering with state equality constraints", IEEE TAES 38(1), 2002,
    with the weight ``W = P⁻¹``): for a run whose SOC left the range, with ``b`` the nearer bound and
    ``d = z − b``::

        x ← x − P[:, 0] · d / P[0, 0]        (so z = b exactly; the other states move as P correlates them)

    ``P`` is kept. Clipping the SOC alone throws away the part of the update that the SOC could not take while the
    states correlated with it keep theirs; at a bound the filter meets again and again (a full-charge rest) that
    difference accumulates in the unobservable combinations (an RC voltage against a model-error state) until the
    filter diverges. Where ``P[0, 0]`` is not positive and finite the SOC alone is clipped.
    """
    z = x[..., 0]
    out = (z < 0.0) | (z > 1.0)
    if not out.any():
        return out
    col = np.einsum("...ij,...j->...i", P, P[..., 0, :]) if factor else P[..., :, 0]
    pzz = col[..., 0]
    ok = out & np.isfinite(pzz) & (pzz > 0.0) & np.all(np.isfinite(col), axis=-1)
    bound = np.clip(z, 0.0, 1.0)
    if ok.any():  # only the runs that crossed: another run's infinite covariance must not touch its state
        x[ok] -= col[ok] * ((z[ok] - bound[ok]) / pzz[ok])[..., None]
    x[..., 0] = np.where(out, bound, x[..., 0])
    return out


def clamp_soc(x: np.ndarray) -> np.ndarray:
    """Clip ``x[..., 0]`` into [0, 1] in place; returns the (…,) flag of where it acted."""
    z = x[..., 0]
    out = (z < 0.0) | (z > 1.0)
    if out.any():
        np.clip(z, 0.0, 1.0, out=z)
    return out


@functools.lru_cache(maxsize=64)
def gate_threshold(alpha: float | None) -> float:
    """NIS threshold of a χ²(1) gate with tail probability ``alpha`` (None: no gate)."""
    if alpha is None:
        return np.inf
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"gate_alpha must be in (0, 1) or None, got {alpha!r}")
    return float(special.chdtri(1, alpha))  # χ²(1).isf(α), without importing scipy.stats (0.3 s)


class Gate:
    """Innovation gate over R runs with a release after ``release`` consecutive skips."""

    def __init__(self, n_runs: int, alpha: float | None, release: int):
        self.threshold = gate_threshold(alpha)
        self.release = int(release)
        self.consecutive = np.zeros(n_runs, dtype=int)

    def __call__(self, nis: np.ndarray) -> np.ndarray:
        """``gated (R,) bool``: True where this update must be skipped."""
        gated = (nis > self.threshold) & (self.consecutive < self.release)
        self.consecutive = np.where(gated, self.consecutive + 1, 0)
        return gated


def widen_on_release(P, H, S, e, nis, gated, threshold: float):
    """``(P, S)`` with the SOC variance widened on the runs whose gate released: where an innovation beyond the gate
    is taken after ``gate_release`` rejections in a row (``nis > threshold`` and not gated), ``P_zz`` grows by
    ``d = max(0, e²/threshold − S)/H_z²`` so that the innovation lies on the gate (``S + H_z² d = e²/threshold``);
    ``S`` (R,) comes back widened too. Batched: ``P (R, n, n)``, ``H (R, n)``, ``S, e, nis, gated (R,)``.

    Why: a first update from a wide prior where the output is steep (the paper pack's OCV climbs 61 V per unit SOC
    over its first tenth) leaves a linearised filter sure of a wrong SOC (SD 0.5 → 0.0002); every later innovation is
    gated and each release, with that S, moves it nowhere: an EKF stayed 39 points off for an hour. A release means
    the filter has rejected the measurement ten samples running: its band no longer holds the cell, and it re-acquires
    by admitting as much. A run the gate never holds back is not touched.
    """
    released = ~gated & (nis > threshold) & (H[:, 0] != 0.0)
    if not released.any():
        return P, S
    h2 = np.where(released, H[:, 0] * H[:, 0], 1.0)
    d = np.where(released, np.maximum(e * e / threshold - S, 0.0) / h2, 0.0)
    P = P.copy()
    P[:, 0, 0] += d
    return P, S + H[:, 0] * H[:, 0] * d


#: why a run diverged: code -> text (codes in ``Estimate.failed_reason``; 0 = did not fail)
DIVERGENCE_REASONS = {
    0: "",
    1: "non-finite state",
    2: "non-finite covariance",
    3: "SOC variance above var_max",
    4: "non-finite NIS",
    5: "NIS above nis_max",
}


def diverged(x, P_or_var, nis, var_max: float, nis_max: float) -> np.ndarray:
    """(R,) int8 reason code, nonzero where the run diverged (use it as a mask): non-finite state (1) or covariance
    (2), SOC variance above ``var_max`` (3), non-finite NIS (4) or NIS above ``nis_max`` (5); the first that applies,
    in that order (:data:`DIVERGENCE_REASONS`)."""
    code = np.zeros(x.shape[:-1], dtype=np.int8)

    def mark(bad, c):
        np.copyto(code, np.int8(c), where=bad & (code == 0))

    mark(~np.all(np.isfinite(x), axis=-1), 1)
    if P_or_var.ndim == x.ndim + 1:  # full covariance (R, n, n)
        mark(~np.all(np.isfinite(P_or_var), axis=(-1, -2)), 2)
        var = P_or_var[..., 0, 0]
    else:
        mark(~np.isfinite(P_or_var), 2)
        var = P_or_var
    mark(~(var <= var_max), 3)
    if nis is not None:
        mark(~np.isfinite(nis), 4)
        mark(~(nis <= nis_max), 5)
    return code
