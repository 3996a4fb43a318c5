"""Scoring an :class:`~.estimate.Estimate` against its profile: accuracy, voltage prediction, filter consistency.

Per run r (samples from ``skip_s`` on; SOC error ``ε = ẑ − z_ref``)::

    soc_rmse   √mean ε²           soc_max_abs  max |ε|           rmse_v  √mean (v_meas − v_pred)²
    nis_mean   mean e²/S          nees_mean    mean ε²/σ²          frac_within_3sigma  mean [|ε| ≤ 3σ]
    convergence_time_s  first time after which |ε| stays within ``band`` (from the start of the record)
    lost_s     the longest stretch [s] over which every innovation lies beyond :data:`LOST_SIGMA` of its predicted SD
               (``lost_from_s`` its start): a filter that has lost the measurement (its model far from the record —
               temperature, capacity, a fault — or its SOC held where the OCV curve is flat), whatever it reports after

Aggregates run over the runs that did not fail (``failed_runs`` counts the others): RMSEs pool the squared errors,
max takes the max, the NIS/NEES means average all samples. Consistency bands (two-sided, ``confidence``):

* NIS: innovations of a consistent filter are white, so ``N·mean ~ χ²(N)`` with ``N`` = runs × samples
  (``metrics.chi2_band(1, N)``);
* NEES: SOC errors are correlated in time, so the grand mean is tested against the band of the mean over the
  *runs* only, ``chi2_band(1, runs)``: the time average of correlated χ²(1) values has variance ≤ 2, which makes this
  band conservative. ``nees_frac_in_band`` adds the classical test (Bar-Shalom): the fraction of samples whose
  across-run average NEES lies in that band (≈ confidence for a consistent filter).

With no reference SOC the SOC keys are None; with every run failed the aggregates are None (never NaN).
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from ..metrics import chi2_band, convergence_time, fraction_within, longest_stretch, normalized_error_squared
from ..models.effects import ModelError
from ..profile import Profile
from .estimate import Estimate

#: an innovation this many predicted SDs out (NIS 25: a consistent filter's odds are 6e-7 per sample) ...
LOST_SIGMA = 5.0
#: ... on every sample for this long is a filter that has lost the measurement [s] (socbench estimate warns)
LOST_MIN_S = 60.0


def error_state_excess(estimate: Estimate) -> dict:
    """``{state: (seconds, start)}`` for each coloured model-error state of the noise recipe the estimate carries
    (:class:`~socbench.models.effects.ModelError`, unit variance by construction): the longest stretch over which
    its posterior mean lies beyond :data:`LOST_SIGMA` in any run. The innovations of a filter whose model misses a
    record by far more than the recipe measured can look fine — the error states take the miss up — but a unit state
    held at many σ says the record's model error is beyond the one its identification records showed, and the SOC
    band is narrower than the truth's spread there. Empty without stored states or recipe states."""
    if estimate.x is None:
        return {}
    out = {}
    for name in ModelError.state_names:
        if name not in estimate.state_names:
            continue
        j = estimate.state_names.index(name)
        runs = [longest_stretch(estimate.time_s, np.abs(estimate.x[r, :, j]) > LOST_SIGMA)
                for r in range(estimate.x.shape[0])]
        out[name] = max(runs, key=lambda d: d[0])
    return out


def _f(v):
    v = float(v)
    return v if np.isfinite(v) else None


def score(estimate: Estimate, profile: Profile, skip_s: float = 0.0, band: float = 0.02,
          confidence: float = 0.95) -> dict:
    """Per-run arrays under ``"runs"`` and aggregates (see the module docstring)."""
    R, T = estimate.soc.shape
    if profile.n != T:
        raise ValueError(f"estimate has {T} samples, profile {profile.n}")
    t = estimate.time_s
    keep = t >= t[0] + skip_s
    if not keep.any():
        raise ConfigError(f"skip_s={skip_s:g} s leaves no samples (record is {t[-1] - t[0]:g} s long)")
    ok = ~estimate.failed
    n_ok = int(ok.sum())
    v_meas = np.broadcast_to(profile.voltage_v, (R, T))
    ev = (v_meas - estimate.v_pred)[:, keep]
    nis = normalized_error_squared(estimate.innovation, estimate.innovation_var)[:, keep]
    lost = np.array([longest_stretch(t[keep], nis[r] > LOST_SIGMA**2) for r in range(R)]).reshape(R, 2)
    runs = {
        "rmse_v": np.sqrt(np.mean(ev * ev, axis=1)),
        "nis_mean": np.mean(nis, axis=1),
        "lost_s": lost[:, 0],
        "lost_from_s": lost[:, 1],
        "failed": estimate.failed.copy(),
        "clamped": estimate.clamped.sum(axis=1),
        "gated": estimate.gated.sum(axis=1),
    }
    out = {
        "n_runs": R,
        "failed_runs": R - n_ok,
        "n": int(keep.sum()),
        "skip_s": float(skip_s),
        "rmse_v": None,
        "nis_mean": None,
        "nis_band": None,
        "soc_rmse": None,
        "soc_max_abs": None,
        "nees_mean": None,
        "nees_band": None,
        "nees_frac_in_band": None,
        "frac_within_3sigma": None,
        "convergence_time_s": None,
        "converged_fraction": None,
        "clamped_steps": int(estimate.clamped[ok].sum()),
        "gated_steps": int(estimate.gated[ok].sum()),
        "lost_s": float(np.max(lost[:, 0])),
        "lost_from_s": _f(lost[int(np.argmax(lost[:, 0])), 1]),
        "runs": runs,
    }
    if n_ok:
        out["rmse_v"] = _f(np.sqrt(np.mean(ev[ok] ** 2)))
        out["nis_mean"] = _f(np.mean(nis[ok]))
        out["nis_band"] = chi2_band(1, n_ok * int(keep.sum()), confidence)
    soc_ref = profile.get("soc_ref")  # a reference given but refused (far outside [0, 1]) fails here, where used
    if soc_ref is None:
        return out
    z_ref = np.broadcast_to(soc_ref, (R, T))
    err = estimate.soc - z_ref
    e_k, sd_k = err[:, keep], estimate.soc_std[:, keep]
    nees = normalized_error_squared(e_k, sd_k**2)
    conv = np.array([convergence_time(t, err[r], band) for r in range(R)])
    runs.update({
        "soc_rmse": np.sqrt(np.mean(e_k * e_k, axis=1)),
        "soc_max_abs": np.max(np.abs(e_k), axis=1),
        "nees_mean": np.mean(nees, axis=1),
        "frac_within_3sigma": fraction_within(e_k, sd_k, 3.0, axis=1),
        "convergence_time_s": conv,
    })
    if n_ok:
        lo, hi = chi2_band(1, n_ok, confidence)
        ens = np.mean(nees[ok], axis=0)
        conv_ok = conv[ok]
        finite = np.isfinite(conv_ok)
        out.update({
            "soc_rmse": _f(np.sqrt(np.mean(e_k[ok] ** 2))),
            "soc_max_abs": _f(np.max(np.abs(e_k[ok]))),
            "nees_mean": _f(np.mean(nees[ok])),
            "nees_band": (lo, hi),
            "nees_frac_in_band": _f(np.mean((ens >= lo) & (ens <= hi))),
            "frac_within_3sigma": _f(np.mean(runs["frac_within_3sigma"][ok])),
            "convergence_time_s": _f(np.median(conv_ok)),
            "converged_fraction": _f(np.mean(finite)),
        })
    return out
