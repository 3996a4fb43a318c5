"""Estimate: what every estimator returns, batched over Monte Carlo runs (R runs × T samples).

At sample ``k`` the filter first predicts the voltage from its prior ``x_{k|k−1}`` (``v_pred``), compares it with the
measurement (``innovation = v_meas − v_pred``, predicted variance ``innovation_var = S_k``), updates, and reports the
posterior SOC ``soc = ẑ_{k|k}`` with ``soc_std = √P_{k|k}[0, 0]``. ``NIS_k = innovation² / S_k``.

A run that diverged (non-finite numbers, runaway covariance or NIS) is marked in ``failed`` with the sample where it
happened in ``failed_at`` and why in ``failed_reason`` (a code of :data:`~.safety.DIVERGENCE_REASONS`); from there on
its outputs repeat the last finite values, so no output ever holds a NaN.

``domain`` is the estimate's domain report (:func:`socbench.domain.estimate_domain`: SOC clamped or outside [0, 1],
OCV extrapolated, model guards along the estimated path); ``segments`` the segments the record was filtered in
(:mod:`socbench.segments`; None for one piece).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class Estimate:
    """Outputs of :meth:`Estimator.run` (shapes with R runs, T samples, n states)."""

    time_s: np.ndarray  # (T,)
    soc: np.ndarray  # (R, T) posterior SOC
    soc_std: np.ndarray  # (R, T) posterior SOC standard deviation
    v_pred: np.ndarray  # (R, T) voltage predicted before the update
    innovation: np.ndarray  # (R, T) v_meas − v_pred
    innovation_var: np.ndarray  # (R, T) its predicted variance S
    failed: np.ndarray  # (R,) bool
    failed_at: np.ndarray  # (R,) first failed sample, −1 if none
    clamped: np.ndarray  # (R, T) bool: the SOC clamp to [0, 1] acted at this sample
    gated: np.ndarray  # (R, T) bool: the update was skipped by the innovation gate
    x: np.ndarray | None = None  # (R, T, n) posterior state (store_states=True)
    P_diag: np.ndarray | None = None  # (R, T, n) posterior variances (store_states=True)
    estimator: str = ""
    model: str = ""
    state_names: tuple = ()
    info: dict = field(default_factory=dict)
    failed_reason: np.ndarray | None = None  # (R,) int8 code, 0 = did not fail (safety.DIVERGENCE_REASONS)
    domain: dict = field(default_factory=dict)
    segments: object = None

    @property
    def n_runs(self) -> int:
        return int(self.soc.shape[0])

    @property
    def n(self) -> int:
        return int(self.time_s.size)

    @property
    def nis(self) -> np.ndarray:
        """Normalised innovation squared ``(R, T)``."""
        return self.innovation**2 / self.innovation_var

    @property
    def clamped_count(self) -> np.ndarray:
        return self.clamped.sum(axis=-1)

    @property
    def gated_count(self) -> np.ndarray:
        return self.gated.sum(axis=-1)

    @property
    def failed_runs(self) -> int:
        return int(self.failed.sum())

    def failure_reasons(self) -> list[str]:
        """Per run: why it failed ("" if it did not; "diverged" when the estimator gave no reason)."""
        from .safety import DIVERGENCE_REASONS

        codes = self.failed_reason if self.failed_reason is not None else np.zeros(self.n_runs, dtype=np.int8)
        return [DIVERGENCE_REASONS.get(int(c), "diverged") or ("diverged" if f else "")
                for c, f in zip(codes, self.failed)]

    def run(self, r: int) -> Estimate:
        """Run ``r`` as a one-run Estimate."""
        sl = slice(r, r + 1)

        def cut(a):
            return None if a is None else a[sl]

        return Estimate(
            self.time_s, self.soc[sl], self.soc_std[sl], self.v_pred[sl], self.innovation[sl],
            self.innovation_var[sl], self.failed[sl], self.failed_at[sl], self.clamped[sl], self.gated[sl],
            cut(self.x), cut(self.P_diag), self.estimator, self.model, self.state_names, dict(self.info),
            cut(self.failed_reason), {}, self.segments,
        )

    @classmethod
    def join(cls, parts: list, time_s: np.ndarray, segments=None) -> Estimate:
        """One estimate from the estimates of consecutive segments of a record (time axis concatenated).

        A run fails where it first failed in any segment (``failed_at`` on the whole record's samples); a later
        segment restarts it, so its outputs there are that segment's own. ``info``: per-run paths over time are
        joined, per-run integer counters (PSD repairs, resamplings) summed, other entries are the last segment's."""
        def cat(name):
            vals = [getattr(p, name) for p in parts]
            return None if any(v is None for v in vals) else np.concatenate(vals, axis=1)

        R = parts[0].n_runs
        failed = np.zeros(R, dtype=bool)
        failed_at = np.full(R, -1)
        reason = np.zeros(R, dtype=np.int8)
        offset = 0
        for p in parts:
            new = p.failed & ~failed
            failed_at[new] = p.failed_at[new] + offset
            if p.failed_reason is not None:
                reason[new] = p.failed_reason[new]
            failed |= new
            offset += p.n
        p0 = parts[0]
        info = dict(parts[-1].info)
        for k, v in p0.info.items():
            vals = [p.info.get(k) for p in parts]
            if not all(isinstance(a, np.ndarray) for a in vals):
                continue
            if v.ndim == 2 and v.shape[0] == R:  # a path over time (the joint estimator's parameters): joined
                info[k] = np.concatenate(vals, axis=1)
            elif v.ndim == 1 and v.shape[0] == R and np.issubdtype(v.dtype, np.integer):  # per-run counters
                info[k] = np.sum(vals, axis=0)
            # anything else (a final value per run) is the last segment's
        return cls(time_s, cat("soc"), cat("soc_std"), cat("v_pred"), cat("innovation"), cat("innovation_var"),
                   failed, failed_at, cat("clamped"), cat("gated"), cat("x"), cat("P_diag"), p0.estimator, p0.model,
                   p0.state_names, info, reason, {}, segments)

    def to_frame(self, r: int = 0):
        """A pandas DataFrame of run ``r``: ``time_s, soc, soc_std, v_pred, innovation, innovation_var, …``."""
        import pandas as pd

        return pd.DataFrame({
            "time_s": self.time_s,
            "soc": self.soc[r],
            "soc_std": self.soc_std[r],
            "v_pred": self.v_pred[r],
            "innovation": self.innovation[r],
            "innovation_var": self.innovation_var[r],
            "clamped": self.clamped[r].astype(int),
            "gated": self.gated[r].astype(int),
        })
