"""Open-circuit-voltage curves ``U_oc(z)``: monotone PCHIP through rest points (ECM_SPEC §3.3).

The interpolant is built once with :class:`scipy.interpolate.PchipInterpolator` (shape preserving, C¹, analytic
derivative per segment). Evaluation is done here from the cached piecewise-cubic coefficients, because a filter calls it
once per time step on a whole batch and scipy's per-call overhead would dominate.

Outside the rest points ``[z_lo, z_hi]`` the curve is extended linearly with its end slopes for an excursion of up to
``EXCURSION_FLAG`` = 0.05 (ECM_SPEC §3.3/§7.3: extrapolate linearly, flag ``|Δz| > 0.05``), and held at the value it
reached there beyond::

    U_oc(z) = U(z_lo) + U'(z_lo)·max(z − z_lo, −0.05)     z < z_lo      dU_oc/dz = U'(z_lo) within 0.05, else 0
    U_oc(z) = U(z_hi) + U'(z_hi)·min(z − z_hi, +0.05)     z > z_hi      dU_oc/dz = U'(z_hi) within 0.05, else 0

so an SOC driven far outside the curve (a model counting through a battery swap, a filter before its clamp) meets a
bounded voltage instead of an unbounded line (kilovolts after a few units of SOC). The derivative is the exact one of
this piecewise curve (0 on the held parts), so Jacobians stay consistent with finite differences away from the two
kinks. :meth:`OCVCurve.excursion` tells how far a SOC lies outside the rest points; ``socbench.domain`` counts the
samples where that is > 0 (extrapolated) and > 0.05 (held).

Inverse ``z = U_oc⁻¹(v)`` is found by bisection on the monotone curve (to 1e-12 in SOC); outside the curve it inverts
the linear extension and stops at the held ends (``z_lo − 0.05``, ``z_hi + 0.05``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from .errors import DataError

#: |Δz| beyond the rest points at which an extrapolated OCV is flagged (ECM_SPEC §7.3).
EXCURSION_FLAG = 0.05


@dataclass(frozen=True, eq=False)
class OCVCurve:
    """Monotone OCV curve through ``(soc, voltage)`` rest points.

    Parameters
    ----------
    soc, voltage : array-like
        Rest points. Sorted by SOC here; duplicate SOCs are averaged. Voltage must be non-decreasing in SOC
        (a measured curve that wiggles is made monotone by :func:`monotone_points` before this).
    source : str
        Where the points come from (kept in parameter files).
    """

    soc: np.ndarray
    voltage: np.ndarray
    source: str = ""

    def __post_init__(self):
        z = np.asarray(self.soc, dtype=float).ravel()
        v = np.asarray(self.voltage, dtype=float).ravel()
        if z.size != v.size or z.size < 2:
            raise DataError(f"an OCV curve needs at least 2 (soc, voltage) points, got {z.size} and {v.size}")
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(v))):
            raise DataError("OCV points contain NaN or inf")
        order = np.argsort(z, kind="stable")
        z, v = z[order], v[order]
        uz, inv = np.unique(z, return_inverse=True)
        if uz.size != z.size:
            v = np.bincount(inv, weights=v) / np.bincount(inv)
            z = uz
        if uz.size < 2:
            raise DataError("OCV points need at least 2 distinct SOC values")
        if np.any(np.diff(v) < 0):
            k = int(np.argmax(np.diff(v) < 0))
            raise DataError(
                f"OCV must not decrease with SOC (z={z[k]:.4f}: {v[k]:.4f} V, z={z[k + 1]:.4f}: {v[k + 1]:.4f} V)",
                column="voltage",
                row=k + 2,
            )
        object.__setattr__(self, "soc", z)
        object.__setattr__(self, "voltage", v)
        pchip = PchipInterpolator(z, v, extrapolate=False)
        # c[m, j]: coefficient of (z - x_j)^(3-m) on segment j
        object.__setattr__(self, "_coef", np.ascontiguousarray(pchip.c.T))  # (segments, 4)
        object.__setattr__(self, "_inner", np.ascontiguousarray(z[1:-1]))
        d = pchip.derivative()
        object.__setattr__(self, "_slope_lo", float(d(z[0])))
        object.__setattr__(self, "_slope_hi", float(d(z[-1])))

    # ------------------------------------------------------------ evaluation
    def _segment(self, z: np.ndarray):
        # segment j of z: the interior breakpoints at or below z (= clip(searchsorted(soc) − 1, 0, segments − 1))
        j = np.searchsorted(self._inner, z, side="right")
        return j, z - np.take(self.soc, j)

    def value_and_slope(self, z) -> tuple[np.ndarray, np.ndarray]:
        """``(U_oc(z), dU_oc/dz)`` with linear extension outside the rest points."""
        z = np.asarray(z, dtype=float)
        j, s = self._segment(z)
        c = np.take(self._coef, j, axis=0)  # (…, 4); np.take is much faster than fancy indexing here
        c0, c1, c2 = c[..., 0], c[..., 1], c[..., 2]
        v = ((c0 * s + c1) * s + c2) * s + c[..., 3]
        dv = (3.0 * c0 * s + 2.0 * c1) * s + c2
        lo, hi = z < self.soc[0], z > self.soc[-1]
        if lo.any() or hi.any():
            v, dv = self._extend(z, lo, hi, v, dv)
        return v, dv

    def _extend(self, z, lo, hi, v, dv=None):
        """``(v, dv)`` with the ends replaced by the clamped linear extension (module docstring)."""
        z_lo, z_hi = self.soc[0], self.soc[-1]
        d_lo = np.maximum(z - z_lo, -EXCURSION_FLAG)
        d_hi = np.minimum(z - z_hi, EXCURSION_FLAG)
        v = np.where(lo, self.voltage[0] + self._slope_lo * d_lo, v)
        v = np.where(hi, self.voltage[-1] + self._slope_hi * d_hi, v)
        if dv is not None:
            held = (z < z_lo - EXCURSION_FLAG) | (z > z_hi + EXCURSION_FLAG)
            dv = np.where(held, 0.0, np.where(lo, self._slope_lo, np.where(hi, self._slope_hi, dv)))
        return v, dv

    def value(self, z) -> np.ndarray:
        """``U_oc(z)`` alone (the same numbers as :meth:`value_and_slope`, without the slope's work)."""
        z = np.asarray(z, dtype=float)
        j, s = self._segment(z)
        c = np.take(self._coef, j, axis=0)
        v = ((c[..., 0] * s + c[..., 1]) * s + c[..., 2]) * s + c[..., 3]
        lo, hi = z < self.soc[0], z > self.soc[-1]
        if lo.any() or hi.any():
            v = self._extend(z, lo, hi, v)[0]
        return v

    def __call__(self, z) -> np.ndarray:
        return self.value(z)

    def slope(self, z) -> np.ndarray:
        return self.value_and_slope(z)[1]

    def excursion(self, z) -> np.ndarray:
        """How far ``z`` lies outside the rest points (0 inside)."""
        z = np.asarray(z, dtype=float)
        return np.maximum(self.soc[0] - z, 0.0) + np.maximum(z - self.soc[-1], 0.0)

    def inverse(self, v, tol: float = 1e-12) -> np.ndarray:
        """SOC whose OCV is ``v``; outside the curve the linear extension is inverted, up to the held ends."""
        v = np.asarray(v, dtype=float)
        lo = self.soc[0] - EXCURSION_FLAG
        hi = self.soc[-1] + EXCURSION_FLAG
        a = np.full(v.shape, lo)
        b = np.full(v.shape, hi)
        for _ in range(60):  # bisection on a monotone function: 60 halvings reach 1e-18 of the bracket
            m = 0.5 * (a + b)
            below = self(m) < v
            a = np.where(below, m, a)
            b = np.where(below, b, m)
            if np.max(b - a, initial=0.0) < tol:
                break
        return 0.5 * (a + b)

    # ----------------------------------------------------------- persistence
    def to_dict(self) -> dict:
        return {"soc": self.soc.tolist(), "voltage": self.voltage.tolist(), "source": self.source}

    @classmethod
    def from_dict(cls, d: dict) -> OCVCurve:
        try:
            return cls(d["soc"], d["voltage"], d.get("source", ""))
        except KeyError as exc:
            raise DataError(f"OCV curve needs key {exc}") from None

    def scaled(self, n_series: int) -> OCVCurve:
        """The curve of ``n_series`` identical cells in series."""
        return OCVCurve(self.soc, self.voltage * n_series, self.source + f" ×{n_series} in series")


def monotone_points(soc, voltage) -> tuple[np.ndarray, np.ndarray]:
    """Make measured rest points monotone by isotonic regression (pool adjacent violators), SOC ascending.

    Measured OCV points can wiggle by a few mV (relaxation not finished, noise); PCHIP needs monotone data.
    """
    z = np.asarray(soc, dtype=float)
    v = np.asarray(voltage, dtype=float)
    order = np.argsort(z, kind="stable")
    z, v = z[order], v[order]
    blocks: list[list[float]] = []  # [sum, count]
    for val in v:
        blocks.append([val, 1.0])
        while len(blocks) > 1 and blocks[-2][0] / blocks[-2][1] > blocks[-1][0] / blocks[-1][1]:
            s, c = blocks.pop()
            blocks[-1][0] += s
            blocks[-1][1] += c
    out = np.concatenate([np.full(int(c), s / c) for s, c in blocks])
    return z, out
