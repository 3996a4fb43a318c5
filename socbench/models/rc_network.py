"""The RC-network family: Rint (1), Thevenin (2), PNGV (3), DP (4), GNL (5) and a generic R0 + N RC (`nrc`).

State ``x = [z, (U0), U1, …, Un]`` (``U0`` only for PNGV/GNL), every ``Uj`` an RC branch (B2), ``U0`` the PNGV
integrator (B3). In OCV-curve mode (ECM_SPEC §3.3)::

    z⁺  = z − η(I) κ I                                   (B1)
    U0⁺ = U0 + dt·I/C0(z)                                (B3; disabled by default: 1/C0 := 0, ECM_SPEC §5.3)
    Uj⁺ = a_j Uj + b_j I,  a_j = e^{−dt/(Rj Cj)},  b_j = Rj(1 − a_j)      (B2, R and C evaluated at z_k)
    y   = U_oc(z) − U0 − Σ Uj − R0(z)·I

Jacobians::

    F[0, 0] = 1,   F[U0, 0] = −dt I C0'/C0²,   F[Uj, 0] = a_j,z Uj + b_j,z I,   F[Uj, Uj] = a_j,  F[U0, U0] = 1
    B = [−ηκ, dt/C0, b_1, …, b_n]
    H = [U'(z) − R0'(z) I, −1, …, −1],   D = −R0(z)

``R0`` is floored at 0 in robust mode (Rint ``R0 < 0`` for z > 0.903; PNGV/GNL ``R0 ≤ 0`` at low z: ECM_SPEC §5).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from ..errors import ConfigError
from .base import KernelSpec, Model
from .blocks import R_FLOOR, floor_value, integrator_coefficients, rc_coefficients, soc_rate, soc_step
from .recurrence import affine_scan, running_sum

C0_DISABLED = "disabled"
C0_AS_PRINTED = "as_printed"


def _front(a):
    """View of ``a`` with its last axis first (``np.moveaxis(a, -1, 0)`` without its per-call overhead)."""
    return a.transpose((a.ndim - 1,) + tuple(range(a.ndim - 1)))


def _back(a):
    """View of ``a`` with its first axis last."""
    return a.transpose(tuple(range(1, a.ndim)) + (0,))


class RCNetwork(Model):
    """R0 in series with ``n_rc`` parallel RC branches, optionally a PNGV integrator ``C0``."""

    n_rc: ClassVar[int | None] = 0
    has_integrator: ClassVar[bool] = False
    param_units = {"R0": "Ω", "C0": "F", **{f"R{j}": "Ω" for j in range(1, 10)}, **{f"C{j}": "F" for j in range(1, 10)}}

    def __init__(self, params, mode=None):
        n = self.n_rc
        if n is None:  # generic: as many branches as the parameter set has R1..Rn
            n = 0
            while f"R{n + 1}" in params.values:
                n += 1
        self._n = n
        self._branch_params = tuple(f"R{j}" for j in range(1, n + 1)) + tuple(f"C{j}" for j in range(1, n + 1))
        self._branch_names = tuple(f"RC{j}" for j in range(1, n + 1))
        self._branch_cols = np.arange(n) + (2 if self.has_integrator else 1)
        super().__init__(params, mode)
        self.c0_mode = params.options.get("c0", C0_DISABLED)
        if self.c0_mode not in (C0_DISABLED, C0_AS_PRINTED):
            raise ConfigError(f"option c0 must be '{C0_DISABLED}' or '{C0_AS_PRINTED}', got {self.c0_mode!r}")

    def required_params(self):
        names = ["R0"] + [f"R{j}" for j in range(1, self._n + 1)] + [f"C{j}" for j in range(1, self._n + 1)]
        if self.has_integrator and self.params.options.get("c0", C0_DISABLED) == C0_AS_PRINTED:
            names.append("C0")
        return tuple(names)

    @property
    def state_names(self):
        return ("z",) + (("U0",) if self.has_integrator else ()) + tuple(f"U{j}" for j in range(1, self._n + 1))

    def kernel_spec(self):
        printed = self.has_integrator and self.c0_mode == C0_AS_PRINTED
        # kernels.lowering RC_INTEGRATOR, RC_C0_PRINTED
        flags = (1 if self.has_integrator else 0) | (2 if printed else 0)
        params = ("R0",) + self._branch_params + (("C0",) if printed else ())
        return KernelSpec("rc_network", params, step=(1, len(params)), output=(0, 1), sub=self._n, flags=flags)

    @property
    def _first_branch(self) -> int:
        return 2 if self.has_integrator else 1

    def step(self, x, i, dt, temp=None, jac=False, guards=None):
        x, (i, dt) = self._broadcast(x, i, dt)
        z = x[..., 0]
        xn = np.empty_like(x)
        xn[..., 0], dz_di = soc_step(z, i, dt, self.capacity_ah, self.eta_charge)
        if jac:
            F = np.zeros(x.shape + (x.shape[-1],))
            F[..., 0, 0] = 1.0
            B = np.empty_like(x)
            B[..., 0] = dz_di
        if self.has_integrator:
            if self.c0_mode == C0_AS_PRINTED:
                g, g_z = integrator_coefficients(*self.p("C0", z, temp), dt)
            else:
                g, g_z = np.zeros_like(z), np.zeros_like(z)
            xn[..., 1] = x[..., 1] + g * i
            if jac:
                F[..., 1, 0] = g_z * i
                F[..., 1, 1] = 1.0
                B[..., 1] = g
        n = self._n
        if n:  # every branch at once: parameters stacked on a first axis (n, …), one B2 evaluation
            vals, ders = self.params_at(self._branch_params, z, deriv=jac, temp=temp)
            a, b, a_z, b_z = rc_coefficients(vals[:n], None if ders is None else ders[:n], vals[n:],
                                             None if ders is None else ders[n:], dt, self.mode, guards,
                                             name=self._branch_names, derivatives=jac)
            cols = slice(self._first_branch, self._first_branch + n)
            u = _front(x[..., cols])
            _front(xn[..., cols])[...] = a * u + b * i
            if jac:
                idx = self._branch_cols
                F[..., idx, 0] = _back(a_z * u + b_z * i)
                F[..., idx, idx] = _back(a)
                _front(B[..., cols])[...] = b
        return (xn, F, B) if jac else (xn, None, None)

    def _states_given_soc(self, xs, x0, i, dt, temp, guards):
        """Whole-record states (see :meth:`Model.open_loop`): the integrator a running sum of ``dt·I/C0(z_k)`` (B3),
        each branch the affine recurrence ``U⁺ = a(z_k) U + b(z_k) I`` (B2) by
        :func:`~socbench.models.recurrence.affine_scan`."""
        z = xs[:-1, ..., 0]
        if self.has_integrator:
            if self.c0_mode == C0_AS_PRINTED:
                g = integrator_coefficients(*self.p("C0", z, temp), dt)[0]
                xs[..., 1] = running_sum(x0[..., 1], g * i)
            else:
                xs[..., 1] = x0[..., 1]
        n = self._n
        if n:
            vals, _ = self.params_at(self._branch_params, z, deriv=False, temp=temp)
            a, b, _, _ = rc_coefficients(vals[:n], None, vals[n:], None, dt, self.mode, guards,
                                         name=self._branch_names, derivatives=False)  # (n, T − 1, …)
            cols = slice(self._first_branch, self._first_branch + n)
            xs[..., cols] = affine_scan(np.moveaxis(a, 0, -1), np.moveaxis(b * i, 0, -1), x0[..., cols])

    def dxdt(self, x, i, temp=None, z_params=None):
        x, (i,) = self._broadcast(x, i)
        zp = x[..., 0] if z_params is None else np.broadcast_to(z_params, x.shape[:-1])
        d = np.empty_like(x)
        d[..., 0] = soc_rate(i, self.capacity_ah, self.eta_charge)
        if self.has_integrator:
            d[..., 1] = i / self.p("C0", zp, temp)[0] if self.c0_mode == C0_AS_PRINTED else 0.0
        for j in range(1, self._n + 1):
            col = self._first_branch + j - 1
            R, C = self.p(f"R{j}", zp, temp)[0], self.p(f"C{j}", zp, temp)[0]
            d[..., col] = -x[..., col] / (R * C) + i / C
        return d

    @staticmethod
    def _polarisation(x):
        """``U0 + Σ Uj``, added column by column (a last-axis ``sum`` over 1–3 entries is slow on large batches)."""
        if x.shape[-1] == 1:
            return np.zeros(x.shape[:-1])
        total = x[..., 1].copy()
        for col in range(2, x.shape[-1]):
            total += x[..., col]
        return total

    def output(self, x, i, temp=None, jac=False, guards=None):
        x, (i,) = self._broadcast(x, i)
        z = x[..., 0]
        if not jac:
            r0 = floor_value(self.params_at(("R0",), z, deriv=False, temp=temp)[0][0], None, R_FLOOR, self.mode, guards,
                             "R0_floor")[0]
            return self.ocv.value(z, temp) - r0 * i - self._polarisation(x), None, None
        u, du = self.ocv.value_and_slope(z, temp)
        r0, dr0 = floor_value(*self.p("R0", z, temp), R_FLOOR, self.mode, guards, "R0_floor")
        y = u - r0 * i - self._polarisation(x)
        H = np.full(x.shape, -1.0)
        H[..., 0] = du - dr0 * i
        return y, H, -r0


class Rint(RCNetwork):
    name = "rint"
    title = "Rint (internal resistance)"
    paper_number = 1
    source = "He, Xiong & Fan 2011 (Energies 4:582); R0(z) 6th-degree polynomial as in Jung & Tullu"
    n_rc = 0
    corrections = "R0 < 0 for z > 0.903 in Table 3: floored at 0 in robust mode"


class Thevenin(RCNetwork):
    name = "thevenin"
    title = "Thevenin (1 RC)"
    paper_number = 2
    source = "He, Xiong & Fan 2011; Jung & Tullu eqs. 3-5"
    n_rc = 1
    corrections = "none needed (cleanest Table 3 set)"


class PNGV(RCNetwork):
    name = "pngv"
    title = "PNGV (1 RC + bulk capacitor C0)"
    paper_number = 3
    source = "PNGV Battery Test Manual lumped model; He et al. 2011"
    n_rc = 1
    has_integrator = True
    corrections = "C0 double-counts the OCV decline (43 V drift): disabled by default (1/C0 := 0), 'as_printed' option"


class DP(RCNetwork):
    name = "dp"
    title = "Dual polarization (2 RC)"
    paper_number = 4
    source = "He, Xiong & Fan 2011"
    n_rc = 2
    corrections = "Table 3 C2 z⁴, z³ coefficients de-garbled (ECM_SPEC §6); R2 unit read as Ω"


class GNL(RCNetwork):
    name = "gnl"
    title = "General non-linear (PNGV + 2nd RC)"
    paper_number = 5
    source = "Shen & Gao 2019"
    n_rc = 2
    has_integrator = True
    corrections = "C0 disabled by default like PNGV; missing Table 3 C2 replaced by DP's C2 (flagged)"


class NRC(RCNetwork):
    name = "nrc"
    title = "R0 + N RC branches (generic)"
    source = "generic Thevenin chain; N is the number of R1..Rn in the parameter set"
    n_rc = None
    corrections = "not in the paper"
