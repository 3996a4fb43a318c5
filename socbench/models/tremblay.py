"""The Tremblay & Dessaint 2009 generic battery model written in SOC: Liu (11) and Tremblay2 (13) (ECM_SPEC §5.11,
§5.13), in OCV-curve mode. After correction the two are the same model; only the Table 3 values differ.

State ``x = [z, I*]``, ``I*`` the low-pass filtered current (B4; eq. 26 corrected), ``it = Q(1 − z)`` [Ah]::

    ż   = −η(I) I/(3600 Q)                      z⁺  = z − ηκ I                         (B1)
    İ*  = (I − I*)/t_c                          I*⁺ = a_f I* + (1 − a_f) I,  a_f = e^{−dt/t_c}   (B4)

Output, branch on the sign of ``I*`` (MathWorks convention; the branches agree at ``I* = 0``)::

    discharge (I* ≥ 0): y = U(z) − K Q(1 − z)/z_s − K I*/z_s       + A e^{−B Q(1 − z)} − R0 I
    charge    (I* < 0): y = U(z) − K Q(1 − z)/z_s − K I*/(1.1 − z) + A e^{−B Q(1 − z)} − R0 I

(``Q/(Q − it) = 1/z``, ``Q/(it + 0.1 Q) = 1/(1.1 − z)``; the paper's ``I_L·t`` and ``1/(1 + z)`` are corrected.)

Jacobians (``E = d/dz A e^{−BQ(1−z)}``, constant K shown; SOC-dependent parameters add their ``p'`` terms)::

    F = [[1, 0], [a_f,z (I* − I), a_f]],   B = [−ηκ, 1 − a_f]
    discharge: H = [U' + K Q/z² + K I*/z² + E − R0' I,  −K/z_s]
    charge:    H = [U' + K Q/z² − K I*/(1.1 − z)² + E − R0' I,  −K/(1.1 − z)]
    D = −R0

``1/z`` uses the ε-guard (B6); ``1/(1.1 − z)`` is evaluated at ``max(1.1 − z, ε)`` (only reached on overcharge).
"""

from __future__ import annotations

import numpy as np

from .base import KernelSpec, Model
from .blocks import EPS_SINGULAR, R_FLOOR, floor_value, guarded_inv, lowpass_coefficients, soc_rate, soc_step
from .recurrence import lowpass_path
from .static_terms import exponential_zone


class TremblayGeneric(Model):
    """Tremblay 2009 / MathWorks generic Li-ion model in OCV-curve mode, states ``[z, Istar]``."""

    param_names = ("tc", "K", "A", "B", "R0")
    param_units = {"tc": "s", "K": "V/Ah (it-term), Ω (I*-term)", "A": "V", "B": "1/Ah", "R0": "Ω"}

    @property
    def state_names(self):
        return ("z", "Istar")

    def kernel_spec(self):
        return KernelSpec("tremblay", ("tc", "K", "A", "B", "R0"), step=(0, 1), output=(1, 5))

    def step(self, x, i, dt, temp=None, jac=False, guards=None):
        x, (i, dt) = self._broadcast(x, i, dt)
        z, istar = x[..., 0], x[..., 1]
        a, a_z = lowpass_coefficients(*self.p("tc", z, temp), dt)
        xn = np.empty_like(x)
        xn[..., 0], dz_di = soc_step(z, i, dt, self.capacity_ah, self.eta_charge)
        xn[..., 1] = a * istar + (1.0 - a) * i
        if not jac:
            return xn, None, None
        F = np.zeros(x.shape + (2,))
        F[..., 0, 0] = 1.0
        F[..., 1, 0] = a_z * (istar - i)
        F[..., 1, 1] = a
        B = np.stack([dz_di, 1.0 - a], axis=-1)
        return xn, F, B

    def _states_given_soc(self, xs, x0, i, dt, temp, guards):
        """Whole-record ``I*`` (see :meth:`Model.open_loop`): ``I*⁺ = a(z_k) I* + (1 − a) I`` (B4) by
        :func:`~socbench.models.recurrence.lowpass_path`."""
        xs[..., 1] = lowpass_path(lowpass_coefficients(*self.p("tc", xs[:-1, ..., 0], temp), dt)[0], i, x0[..., 1])

    def dxdt(self, x, i, temp=None, z_params=None):
        x, (i,) = self._broadcast(x, i)
        zp = x[..., 0] if z_params is None else np.broadcast_to(z_params, x.shape[:-1])
        tc = self.p("tc", zp, temp)[0]
        return np.stack([soc_rate(i, self.capacity_ah, self.eta_charge), (i - x[..., 1]) / tc], axis=-1)

    def output(self, x, i, temp=None, jac=False, guards=None):
        x, (i,) = self._broadcast(x, i)
        z, istar = x[..., 0], x[..., 1]
        q = self.capacity_ah
        u, du = self.ocv.value_and_slope(z, temp)
        r0, dr0 = floor_value(*self.p("R0", z, temp), R_FLOOR, self.mode, guards, "R0_floor")
        k, dk = self.p("K", z, temp)
        inv, dinv = guarded_inv(z, guards=guards)
        # it-term −K·Q/(Q − it)·it = −K Q (1 − z)/z_s
        it_term = -k * q * (1.0 - z) * inv
        d_it = -dk * q * (1.0 - z) * inv + k * q * inv - k * q * (1.0 - z) * dinv
        # I*-term: −K I*/z_s (discharge) or −K I*/(1.1 − z) (charge)
        charge = istar < 0.0
        w = 1.1 - z
        wc = np.maximum(w, EPS_SINGULAR)
        if guards is not None:
            guards.note("charge_denominator_eps", charge & (w < EPS_SINGULAR))
        inv_c = 1.0 / wc
        dinv_c = np.where(w > EPS_SINGULAR, 1.0 / wc**2, 0.0)  # d/dz 1/(1.1 − z)
        g_star = np.where(charge, inv_c, inv)
        dg_star = np.where(charge, dinv_c, dinv)
        ex, dex = exponential_zone(self, z, temp)
        y = u + it_term - k * g_star * istar + ex - r0 * i
        if not jac:
            return y, None, None
        H = np.empty_like(x)
        H[..., 0] = du + d_it - (dk * g_star + k * dg_star) * istar + dex - dr0 * i
        H[..., 1] = -k * g_star
        return y, H, -r0


class Liu(TremblayGeneric):
    name = "liu"
    title = "Liu (Tremblay 2009 in SOC)"
    paper_number = 11
    source = "Liu et al. 2013 = Tremblay & Dessaint 2009 generic model; verified via ns-3 GenericBatteryModel"
    corrections = (
        "eq. 26 filter → dI*/dt = (I − I*)/t_c; eq. 28 charge denominators (1 + z) → Tremblay form 1/(1.1 − z) on the "
        "I* term, 1/z on the it-term; K = 0 in Table 3 makes the filter inert"
    )


class Tremblay2(TremblayGeneric):
    name = "tremblay2"
    title = "Tremblay 2009 (MathWorks generic Li-ion)"
    paper_number = 13
    source = "Tremblay & Dessaint 2009; MathWorks 'Battery' block; ns-3 GenericBatteryModel"
    corrections = (
        "eqs. 33/34: I_L·t → it = Q(1 − z), charge form Q/(it + 0.1Q) on the I* term only; R0 = 0.0027 re-assigned "
        "from the '(14) Plett' label; K < 0 is unphysical (+0.75 V at z = 0.05), kept and flagged"
    )
