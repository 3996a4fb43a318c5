"""Open-circuit-voltage curves ``U_oc(z)``: monotone PCHIP through rest points (ECM_SPEC §3.3).

The interpolant is built once with :class:`scipy.interpolate.PchipInterpolator` (shape preserving, C¹, analytic
derivative per segment). Evaluation is done here from the cached piecewise-cubic coefficients, because a filter calls it
once per time step on a whole batch and scipy's per-call overhead would dominate.

Outside the rest points ``[z_lo, z_hi]`` the curve is extended linearly with its end slopes for an excursion of up to
``EXCURSION_FLAG`` = 0.05 (ECM_SPEC §3.3/§7.3: extrapolate linearly, flag ``|Δz| > 0.05``), and held at the value it
reached there beyond::

    U_oc(z) = U(z_lo) + S_lo·max(z − z_lo, −0.05)     z < z_lo      dU_oc/dz = S_lo within 0.05, else 0
    U_oc(z) = U(z_hi) + S_hi·min(z − z_hi, +0.05)     z > z_hi      dU_oc/dz = S_hi within 0.05, else 0

The end slope ``S`` is the interpolant's end derivative, but never below the mean slope of the end segment (its
secant): ``S_lo = max(U'(z_lo), (U_2 − U_1)/(z_2 − z_1))``, ``S_hi`` likewise with the last two points. PCHIP's end
derivative is a three-point formula that is set to 0 where the two end secants differ enough to overshoot (the top of
a flat LFP curve read up to 0.89: secants 0.23 and 0.057 V per unit SOC); right inside the segment, but extended past
the last rest point it makes every SOC there read one voltage, and a filter that enters the band can no longer be told
where it is (an EKF held 0.9 through a discharge to 0.17 on such a curve). Every lithium-ion OCV steepens towards both
ends (the knee at empty, the rise to full), so beyond its last rest point a curve is at least as steep as its end
segment; where the interpolant's end derivative already is, nothing changes and the curve stays C¹ there.

so an SOC driven far outside the curve (a model counting through a battery swap, a filter before its clamp) meets a
bounded voltage instead of an unbounded line (kilovolts after a few units of SOC). The derivative is the exact one of
this piecewise curve (0 on the held parts), so Jacobians stay consistent with finite differences away from the two
kinks. :meth:`OCVCurve.excursion` tells how far a SOC lies outside the rest points; ``socbench.domain`` counts the
samples where that is > 0 (extrapolated) and > 0.05 (held).

Inverse ``z = U_oc⁻¹(v)`` is found by bisection on the monotone curve (to 1e-12 in SOC); outside the curve it inverts
the linear extension and stops at the held ends (``z_lo − 0.05``, ``z_hi + 0.05``).

Temperature. Every curve takes the cell temperature ``temp`` [°C] (``None``: the reference temperature
:data:`T_REF_C`); an :class:`OCVCurve` ignores it. :class:`TemperatureOCV` holds one curve per measured temperature, on
one SOC axis (charge counted with one capacity for every temperature), and interpolates linearly in temperature
between them, holding the end curves outside: ``U(z, T) = (1 − w) U_k(z) + w U_{k+1}(z)``, exact at the measured
temperatures, monotone in ``z`` (a convex combination of monotone curves) and bounded by its two neighbours (the
entropic ``∂U/∂T`` is then piecewise constant in ``T``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from .errors import DataError

#: |Δz| beyond the rest points at which an extrapolated OCV is flagged (ECM_SPEC §7.3).
EXCURSION_FLAG = 0.05
#: Reference temperature [°C]: what ``temp=None`` means for anything temperature-dependent (curves, parameters).
T_REF_C = 25.0


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
        secant = np.diff(v) / np.diff(z)
        object.__setattr__(self, "_slope_lo", max(float(d(z[0])), float(secant[0])))
        object.__setattr__(self, "_slope_hi", max(float(d(z[-1])), float(secant[-1])))

    # ------------------------------------------------------------ evaluation
    def _segment(self, z: np.ndarray):
        # segment j of z: the interior breakpoints at or below z (= clip(searchsorted(soc) − 1, 0, segments − 1))
        j = np.searchsorted(self._inner, z, side="right")
        return j, z - np.take(self.soc, j)

    @property
    def temperatures(self) -> tuple:
        """Measured temperatures [°C] (none: this curve does not depend on temperature)."""
        return ()

    def value_and_slope(self, z, temp=None) -> tuple[np.ndarray, np.ndarray]:
        """``(U_oc(z), dU_oc/dz)``, extended outside the rest points as the module says (``temp`` is ignored)."""
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

    def value(self, z, temp=None) -> np.ndarray:
        """``U_oc(z)`` alone (the same numbers as :meth:`value_and_slope`, without the slope's work)."""
        z = np.asarray(z, dtype=float)
        j, s = self._segment(z)
        c = np.take(self._coef, j, axis=0)
        v = ((c[..., 0] * s + c[..., 1]) * s + c[..., 2]) * s + c[..., 3]
        lo, hi = z < self.soc[0], z > self.soc[-1]
        if lo.any() or hi.any():
            v = self._extend(z, lo, hi, v)[0]
        return v

    def __call__(self, z, temp=None) -> np.ndarray:
        return self.value(z, temp)

    def slope(self, z, temp=None) -> np.ndarray:
        return self.value_and_slope(z, temp)[1]

    def excursion(self, z, temp=None) -> np.ndarray:
        """How far ``z`` lies outside the rest points (0 inside; ``temp`` is ignored)."""
        z = np.asarray(z, dtype=float)
        return np.maximum(self.soc[0] - z, 0.0) + np.maximum(z - self.soc[-1], 0.0)

    def inverse(self, v, tol: float = 1e-12, temp=None) -> np.ndarray:
        """SOC whose OCV is ``v``; outside the curve the linear extension is inverted, up to the held ends."""
        v = np.asarray(v, dtype=float)
        lo = self.soc[0] - EXCURSION_FLAG
        hi = self.soc[-1] + EXCURSION_FLAG
        shape = np.broadcast_shapes(v.shape, np.shape(temp)) if temp is not None else v.shape
        a = np.full(shape, lo)
        b = np.full(shape, hi)
        for _ in range(60):  # bisection on a monotone function: 60 halvings reach 1e-18 of the bracket
            m = 0.5 * (a + b)
            below = self.value(m, temp) < v
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


class TemperatureOCV(OCVCurve):
    """OCV curves measured at several temperatures, ``curves[j]`` at ``temps[j]`` [°C], on one SOC axis; linear in
    temperature between them (module docstring). It is an :class:`OCVCurve` whose rest points (``soc``, ``voltage``)
    are those of the curve nearest :data:`T_REF_C`, so code that only needs "the" curve (level checks, plots) works."""

    def __init__(self, temps, curves, source: str = ""):
        t = np.asarray(temps, dtype=float).ravel()
        curves = tuple(curves)
        if t.size < 1 or t.size != len(curves) or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise DataError(f"a temperature OCV needs >= 1 strictly increasing temperatures and one curve per "
                            f"temperature (got {list(t)} and {len(curves)} curves)")
        if any(not isinstance(c, OCVCurve) or isinstance(c, TemperatureOCV) for c in curves):
            raise DataError("a temperature OCV's curves must be plain OCV curves")
        ref = curves[int(np.argmin(np.abs(t - T_REF_C)))]
        super().__init__(ref.soc, ref.voltage, source or ref.source)
        object.__setattr__(self, "temps", tuple(float(x) for x in t))
        object.__setattr__(self, "curves", curves)

    @property
    def temperatures(self) -> tuple:
        return self.temps

    def at(self, temp: float) -> OCVCurve:
        """The measured curve nearest ``temp``."""
        return self.curves[int(np.argmin(np.abs(np.asarray(self.temps) - float(temp))))]

    def _blend(self, z, temp, slope: bool):
        from .models.params import temperature_weights  # one weighting rule for every temperature table

        z = np.asarray(z, dtype=float)
        if len(self.curves) == 1:
            c = self.curves[0]
            return c.value_and_slope(z) if slope else (c.value(z), None)
        k, w = temperature_weights(self.temps, temp)
        shape = np.broadcast_shapes(z.shape, w.shape)
        k, zb = np.broadcast_to(k, shape).ravel(), np.broadcast_to(z, shape).ravel()
        w = np.broadcast_to(w, shape)
        v = np.empty((2, zb.size))
        d = np.empty((2, zb.size)) if slope else None
        for j in np.unique(k):
            m = k == j
            for side in (0, 1):
                c = self.curves[j + side]
                if slope:
                    v[side, m], d[side, m] = c.value_and_slope(zb[m])
                else:
                    v[side, m] = c.value(zb[m])
        val = (1.0 - w) * v[0].reshape(shape) + w * v[1].reshape(shape)
        if not slope:
            return val, None
        return val, (1.0 - w) * d[0].reshape(shape) + w * d[1].reshape(shape)

    def value_and_slope(self, z, temp=None):
        return self._blend(z, temp, True)

    def value(self, z, temp=None):
        return self._blend(z, temp, False)[0]

    def excursion(self, z, temp=None):
        """How far ``z`` lies outside the rest points of the measured curve(s) used at ``temp`` (0 inside)."""
        from .models.params import temperature_weights

        z = np.asarray(z, dtype=float)
        if len(self.curves) == 1:
            return self.curves[0].excursion(z)
        k, w = temperature_weights(self.temps, temp)
        lo_ends = np.array([c.soc[0] for c in self.curves])
        hi_ends = np.array([c.soc[-1] for c in self.curves])
        # a curve with zero weight takes no part: its range does not matter
        lo = np.maximum(np.where(w < 1.0, lo_ends[k], -np.inf), np.where(w > 0.0, lo_ends[k + 1], -np.inf))
        hi = np.minimum(np.where(w < 1.0, hi_ends[k], np.inf), np.where(w > 0.0, hi_ends[k + 1], np.inf))
        return np.maximum(lo - z, 0.0) + np.maximum(z - hi, 0.0)

    def to_dict(self) -> dict:
        return {"by_temperature": {"temps": list(self.temps), "curves": [c.to_dict() for c in self.curves]},
                "source": self.source}

    def scaled(self, n_series: int) -> TemperatureOCV:
        return TemperatureOCV(self.temps, [c.scaled(n_series) for c in self.curves], self.source + f" ×{n_series}")


def ocv_from_dict(d: dict) -> OCVCurve:
    """An :class:`OCVCurve` or :class:`TemperatureOCV` from its JSON form."""
    if isinstance(d, dict) and "by_temperature" in d:
        bt = d["by_temperature"]
        try:
            return TemperatureOCV(bt["temps"], [OCVCurve.from_dict(c) for c in bt["curves"]], d.get("source", ""))
        except (KeyError, TypeError):
            raise DataError("a 'by_temperature' OCV curve needs keys 'temps' and 'curves'") from None
    return OCVCurve.from_dict(d)


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


def collapse_ties(soc, voltage) -> tuple[np.ndarray, np.ndarray]:
    """One point per run of equal voltages (SOC ascending, voltage non-decreasing, as :func:`monotone_points` gives),
    at the run's mean SOC.

    Isotonic regression pools the points that violate the order into runs of one value: through them PCHIP draws a
    step, flat (zero slope) along each run and steep between runs. An OCV is strictly increasing; the run says only
    that the curve passes its value somewhere along it. A filter's Jacobian is the curve's slope, which such steps
    make zero or many times too steep: an EKF on an LFP curve refined from its record
    (:mod:`socbench.identify.pseudo_ocv`, 113 flat segments of 164) jumped 50 SOC points in minutes where the UKF,
    reading secants across the steps, held within a point."""
    z = np.asarray(soc, dtype=float)
    v = np.asarray(voltage, dtype=float)
    if z.size < 2:
        return z, v
    start = np.flatnonzero(np.r_[True, v[1:] != v[:-1]])  # first index of each run
    counts = np.diff(np.r_[start, v.size])
    return np.add.reduceat(z, start) / counts, v[start]
