"""Error statistics: voltage error (the paper's Table 4 columns), SOC error, and filter consistency.

Voltage error ``e_k = y_meas,k − y_model,k`` (ECM_SPEC §2): mean, RMS = √mean(e²), SD with N−1, max = max|e|.
"""

from __future__ import annotations

import numpy as np
from scipy import special


def voltage_error_stats(measured, model, axis=-1) -> dict:
    """``{"n", "mean_v", "rmse_v", "sd_v", "max_v"}`` of ``measured − model`` along ``axis`` (floats or arrays)."""
    e = np.asarray(measured, dtype=float) - np.asarray(model, dtype=float)
    n = e.shape[axis]
    out = {
        "n": int(n),
        "mean_v": np.mean(e, axis=axis),
        "rmse_v": np.sqrt(np.mean(e * e, axis=axis)),
        "sd_v": np.std(e, axis=axis, ddof=1) if n > 1 else np.zeros_like(np.mean(e, axis=axis)),
        "max_v": np.max(np.abs(e), axis=axis),
    }
    return {k: (v if k == "n" else float(v) if np.ndim(v) == 0 else v) for k, v in out.items()}


def soc_error_stats(estimate, truth, axis=-1) -> dict:
    """``{"soc_rmse", "soc_max_abs", "soc_mean"}`` of ``estimate − truth`` (fractions, not %)."""
    e = np.asarray(estimate, dtype=float) - np.asarray(truth, dtype=float)
    out = {
        "soc_rmse": np.sqrt(np.mean(e * e, axis=axis)),
        "soc_max_abs": np.max(np.abs(e), axis=axis),
        "soc_mean": np.mean(e, axis=axis),
    }
    return {k: (float(v) if np.ndim(v) == 0 else v) for k, v in out.items()}


def lag1_autocorrelation(e, max_rho: float = 0.999999) -> float:
    """The lag-1 autocorrelation ρ of the series ``e`` (its mean removed), clipped to ``[0, max_rho]``: a smooth error
    counts as ``N(1 − ρ)/(1 + ρ)`` independent samples, and the standard error of an average over it grows by
    ``√((1 + ρ)/(1 − ρ))``."""
    e = np.asarray(e, dtype=float)
    ec = e - e.mean()
    den = float(ec @ ec)
    rho = float(ec[1:] @ ec[:-1]) / den if den > 0 else 0.0
    return min(max(rho, 0.0), max_rho)


def chi2_band(dof: int, n_samples: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band for the *average* of ``n_samples`` independent χ²(dof) statistics.

    ``n_samples · mean ~ χ²(n_samples · dof)``, so the band of the mean is ``χ²_{α/2, ±}(N·dof) / N``.
    """
    a = (1.0 - confidence) / 2.0
    nd = dof * n_samples
    # χ² quantiles by the inverse survival function of scipy.special (scipy.stats would cost a command 0.3 s of
    # import): ppf(q, ν) = chdtri(ν, 1 − q)
    return float(special.chdtri(nd, 1 - a) / n_samples), float(special.chdtri(nd, a) / n_samples)


def convergence_time(time_s, soc_error, band: float = 0.02) -> float:
    """First time after which ``|soc_error|`` stays within ``band`` (inf if it never settles)."""
    err = np.abs(np.asarray(soc_error, dtype=float))
    outside = np.nonzero(err > band)[0]
    if outside.size == 0:
        return float(time_s[0] - time_s[0])
    k = outside[-1] + 1
    if k >= err.size:
        return float("inf")
    return float(time_s[k] - time_s[0])


def longest_stretch(time_s, flag) -> tuple[float, float]:
    """``(duration, start)`` [s] of the longest run of consecutive samples where ``flag`` holds, from its first sample
    to the sample after its last (the record's end if it runs to it); ``(0, nan)`` when it never holds."""
    t = np.asarray(time_s, dtype=float)
    f = np.asarray(flag, dtype=bool)
    if not f.any():
        return 0.0, float("nan")
    edges = np.diff(np.concatenate([[0], f.astype(np.int8), [0]]))
    starts, stops = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    ends = t[np.minimum(stops, t.size - 1)]
    j = int(np.argmax(ends - t[starts]))
    return float(ends[j] - t[starts[j]]), float(t[starts[j]])


def normalized_error_squared(error, variance, floor: float = 1e-18):
    """``e² / max(var, floor)``: NEES of a scalar state or NIS of a scalar innovation (finite whenever e is)."""
    e = np.asarray(error, dtype=float)
    return e * e / np.maximum(np.asarray(variance, dtype=float), floor)


def fraction_within(error, sd, k: float = 3.0, axis=-1):
    """Fraction of samples with ``|error| ≤ k·sd`` along ``axis``."""
    inside = np.abs(np.asarray(error, dtype=float)) <= k * np.asarray(sd, dtype=float)
    return np.mean(inside, axis=axis)
