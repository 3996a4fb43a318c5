"""Numerical safety shared by the filters: symmetric PSD covariances, SOC clamp, innovation gate, divergence.

* symmetrise      ``P ← (P + Pᵀ)/2`` after every update and prediction (round-off makes P drift asymmetric);
* PSD repair      where ``λ_min(P) < floor`` rebuild ``P = V max(Λ, floor) Vᵀ`` with
                  ``floor = max(abs_floor, rel_floor·λ_max)``; matrices that are fine are left bit-for-bit alone;
* SOC clamp       ``z ← clip(z, 0, 1)``, flagged per sample;
* innovation gate skip the update when ``NIS = e²/S > χ²_{1−α}(1)``, counted; after ``release`` consecutive skips the
                  next update is taken anyway, so a filter that started far off is never locked out for good;
* divergence      a run whose state, covariance or NIS is not finite, whose SOC variance exceeds ``var_max`` or whose
                  NIS exceeds ``nis_max`` is marked failed; its internal state is reset to the last good (finite)
                  values so the batch keeps computing, and its outputs are frozen by the recorder.
"""

from __future__ import annotations

import numpy as np
from scipy import stats


def symmetrise(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def repair_psd(P: np.ndarray, abs_floor: float = 1e-15, rel_floor: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """``(P', repaired (…,) bool)``: eigenvalues below the floor raised to it (only where needed)."""
    finite = np.all(np.isfinite(P), axis=(-1, -2))
    Pf = np.where(finite[..., None, None], P, 0.0)
    w = np.linalg.eigvalsh(Pf)
    floor = np.maximum(abs_floor, rel_floor * np.abs(w[..., -1]))
    need = finite & (w[..., 0] < floor)
    if not need.any():
        return P, need
    P = P.copy()
    w_bad, V = np.linalg.eigh(Pf[need])
    w_bad = np.maximum(w_bad, floor[need][..., None])
    P[need] = symmetrise((V * w_bad[..., None, :]) @ np.swapaxes(V, -1, -2))
    return P, need


def clamp_soc(x: np.ndarray) -> np.ndarray:
    """Clip ``x[..., 0]`` into [0, 1] in place; returns the (…,) flag of where it acted."""
    z = x[..., 0]
    out = (z < 0.0) | (z > 1.0)
    if out.any():
        np.clip(z, 0.0, 1.0, out=z)
    return out


def gate_threshold(alpha: float | None) -> float:
    """NIS threshold of a χ²(1) gate with tail probability ``alpha`` (None: no gate)."""
    if alpha is None:
        return np.inf
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"gate_alpha must be in (0, 1) or None, got {alpha!r}")
    return float(stats.chi2.isf(alpha, 1))


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


def diverged(x, P_or_var, nis, var_max: float, nis_max: float) -> np.ndarray:
    """(R,) bool: non-finite state/covariance/NIS, SOC variance above ``var_max`` or NIS above ``nis_max``."""
    bad = ~np.all(np.isfinite(x), axis=-1)
    if P_or_var.ndim == x.ndim + 1:  # full covariance (R, n, n)
        bad |= ~np.all(np.isfinite(P_or_var), axis=(-1, -2))
        var = P_or_var[..., 0, 0]
    else:
        bad |= ~np.isfinite(P_or_var)
        var = P_or_var
    bad |= ~(var <= var_max)
    if nis is not None:
        bad |= ~(nis <= nis_max)  # NaN compares False: caught here too
    return bad
