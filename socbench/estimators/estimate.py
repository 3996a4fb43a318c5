"""Estimate: what every estimator returns, batched over Monte Carlo runs (R runs × T samples).

At sample ``k`` the filter first predicts the voltage from its prior ``x_{k|k−1}`` (``v_pred``), compares it with the
measurement (``innovation = v_meas − v_pred``, predicted variance ``innovation_var = S_k``), updates, and reports the
posterior SOC ``soc = ẑ_{k|k}`` with ``soc_std = √P_{k|k}[0, 0]``. ``NIS_k = innovation² / S_k``.

A run that diverged (non-finite numbers, runaway covariance or NIS) is marked in ``failed`` with the sample where it
happened in ``failed_at``; from there on its outputs repeat the last finite values, so no output ever holds a NaN.
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

    def run(self, r: int) -> Estimate:
        """Run ``r`` as a one-run Estimate."""
        sl = slice(r, r + 1)

        def cut(a):
            return None if a is None else a[sl]

        return Estimate(
            self.time_s, self.soc[sl], self.soc_std[sl], self.v_pred[sl], self.innovation[sl],
            self.innovation_var[sl], self.failed[sl], self.failed_at[sl], self.clamped[sl], self.gated[sl],
            cut(self.x), cut(self.P_diag), self.estimator, self.model, self.state_names, dict(self.info),
        )

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
