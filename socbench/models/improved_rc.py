"""Improved RC model (6): the ADVISOR/SAFT two-capacitor network (ECM_SPEC §5.6), in OCV-curve mode.

State ``x = [z, U_e, U_c]``: ``U_e`` (bulk capacitor ``C_e``) and ``U_c`` (surface capacitor ``C_c``) are deviation
voltages from the OCV, starting at 0. Parameter names follow Table 3 with the spec's assumed mapping
``R_c = R1, C_c = C1, R_e = R2, C_e = C2`` (flagged: the paper's text cannot confirm it). ``R_s = R_e + R_c``::

    ż   = −η(I) I/(3600 Q)                                               (B1)
    U̇_e = (−U_e + U_c − R_c I)/(C_e R_s)                                  (eq. 15 without its extra −I/C_c)
    U̇_c = ( U_e − U_c − R_e I)/(C_c R_s)
    w⁺  = Φ(z_k) w + Γ(z_k) I,   w = [U_e, U_c]                           (B5, exact ZOH, parameters at z_k)
    y   = U(z) + (R_c U_e + R_e U_c)/R_s − (R_e R_c/R_s) I − R0 I         (eq. 16 with −R0 I)

Jacobians::

    F = [[1, 0, 0], [(Φ'w + Γ'I)_1, Φ11, Φ12], [(Φ'w + Γ'I)_2, Φ21, Φ22]],   B = [−ηκ, Γ1, Γ2]
    H = [U' − R0' I + (R_c' U_e + R_e' U_c)/R_s − (R_c U_e + R_e U_c) R_s'/R_s²
           − ((R_e' R_c + R_e R_c')/R_s − R_e R_c R_s'/R_s²) I,   R_c/R_s,   R_e/R_s]
    D = −R_e R_c/R_s − R0

Guards (ECM_SPEC §7.3): with Table 3, ``C1 < 0`` on [0, 0.034], ``C2 < 0`` on [0.531, 1] and ``λ > 0`` on
[0, 0.034] ∪ (0.531, 0.573). Strict mode raises :class:`ModelError` when ``C ≤ 0`` or ``λ > 0``; robust mode uses
``C ← max(C, C_FLOOR)`` (guards ``C1_floor``, ``C2_floor``) and floors ``R0`` at 0 (``R0_floor``).
"""

from __future__ import annotations

import numpy as np

from ..errors import ModelError
from .base import KernelSpec, Model
from .blocks import C_FLOOR, R_FLOOR, STRICT, coupled_rc_coefficients, floor_value, soc_rate, soc_step
from .recurrence import matrix_affine_scan


class ImprovedRC(Model):
    name = "improved_rc"
    title = "Improved RC (ADVISOR two-capacitor network)"
    paper_number = 6
    source = "Johnson 2002 / ADVISOR RC_curr_req.m (V.H. Johnson); He, Xiong & Fan 2011 'RC model'"
    param_names = ("R0", "R1", "R2", "C1", "C2")
    param_units = {"R0": "Ω", "R1": "Ω (R_c)", "R2": "Ω (R_e)", "C1": "F (C_c)", "C2": "F (C_e)"}
    corrections = (
        "eq. 15 extra −I/C_c deleted (KCL), eq. 16 +R0 I → −R0 I; U_e, U_c are deviations from U_oc(z); "
        "assumed mapping R_c=R1, C_c=C1, R_e=R2, C_e=C2; Table 3 C1 < 0 (z < 0.034), C2 < 0 (z > 0.531): "
        "strict raises, robust floors C at 1e3 F"
    )

    @property
    def state_names(self):
        return ("z", "Ue", "Uc")

    def kernel_spec(self):
        return KernelSpec("improved_rc", ("R0", "R1", "R2", "C1", "C2"), step=(1, 5), output=(0, 3))

    # ------------------------------------------------------------------ guarded parameters
    def _capacitance(self, name, c, dc, z, guards):
        if self.mode == STRICT and np.any(c <= 0):
            k = np.argmin(c)
            zk = np.ravel(np.broadcast_to(z, c.shape))[k]
            raise ModelError(f"{self.name}: {name} = {np.ravel(c)[k]:.4g} F ≤ 0 at z = {zk:.4f}")
        return floor_value(c, dc, C_FLOOR, self.mode, guards, f"{name}_floor")

    def _network(self, z, guards=None, deriv=True, temp=None):
        """``(R_e, R_e', R_c, R_c', C_e, C_e', C_c, C_c')`` at ``z`` with the mode's guards applied (derivatives None
        unless ``deriv``)."""
        v, d = self.params_at(("R1", "R2", "C1", "C2"), z, deriv=deriv, temp=temp)
        d = [None] * 4 if d is None else d
        rc, re = v[0], v[1]
        if np.any(re + rc <= 0):
            raise ModelError(f"{self.name}: R1 + R2 ≤ 0 (min {np.min(re + rc):.3g} Ω)")
        cc, dcc = self._capacitance("C1", v[2], d[2], z, guards)
        ce, dce = self._capacitance("C2", v[3], d[3], z, guards)
        return re, d[1], rc, d[0], ce, dce, cc, dcc

    def _check_stable(self, lam, z):
        if self.mode == STRICT and np.any(lam > 0):
            k = np.argmax(lam)
            zk = np.ravel(np.broadcast_to(z, np.shape(lam)))[k]
            raise ModelError(f"{self.name}: unstable eigenvalue λ = {np.ravel(lam)[k]:.3g} 1/s at z = {zk:.4f}")

    # ------------------------------------------------------------------ dynamics
    def step(self, x, i, dt, temp=None, jac=False, guards=None):
        x, (i, dt) = self._broadcast(x, i, dt)
        z = x[..., 0]
        w = x[..., 1:]
        net = self._network(z, guards, deriv=jac, temp=temp)
        Phi, Gam, dPhi, dGam, lam = coupled_rc_coefficients(*net, dt, derivatives=jac)
        self._check_stable(lam, z)
        xn = np.empty_like(x)
        xn[..., 0], dz_di = soc_step(z, i, dt, self.capacity_ah, self.eta_charge)
        xn[..., 1:] = np.einsum("...ij,...j->...i", Phi, w) + Gam * i[..., None]
        if not jac:
            return xn, None, None
        F = np.zeros(x.shape + (3,))
        F[..., 0, 0] = 1.0
        F[..., 1:, 0] = np.einsum("...ij,...j->...i", dPhi, w) + dGam * i[..., None]
        F[..., 1:, 1:] = Phi
        B = np.empty_like(x)
        B[..., 0] = dz_di
        B[..., 1:] = Gam
        return xn, F, B

    def _states_given_soc(self, xs, x0, i, dt, temp, guards):
        """Whole-record states (see :meth:`Model.open_loop`): ``w⁺ = Φ(z_k) w + Γ(z_k) I`` (B5) by
        :func:`~socbench.models.recurrence.matrix_affine_scan`."""
        z = xs[:-1, ..., 0]
        Phi, Gam, _, _, lam = coupled_rc_coefficients(*self._network(z, guards, deriv=False, temp=temp), dt,
                                                       derivatives=False)
        self._check_stable(lam, z)
        xs[..., 1:] = matrix_affine_scan(Phi, Gam * i[..., None], x0[..., 1:])

    def dxdt(self, x, i, temp=None, z_params=None):
        x, (i,) = self._broadcast(x, i)
        zp = x[..., 0] if z_params is None else np.broadcast_to(z_params, x.shape[:-1])
        re, _, rc, _, ce, _, cc, _ = self._network(zp, temp=temp)
        rs = re + rc
        ue, uc = x[..., 1], x[..., 2]
        d = np.empty_like(x)
        d[..., 0] = soc_rate(i, self.capacity_ah, self.eta_charge)
        d[..., 1] = (-ue + uc - rc * i) / (ce * rs)
        d[..., 2] = (ue - uc - re * i) / (cc * rs)
        return d

    def output(self, x, i, temp=None, jac=False, guards=None):
        x, (i,) = self._broadcast(x, i)
        z = x[..., 0]
        ue, uc = x[..., 1], x[..., 2]
        u, du = self.ocv.value_and_slope(z, temp)
        r0, dr0 = floor_value(*self.p("R0", z, temp), R_FLOOR, self.mode, guards, "R0_floor")
        rc, drc = self.p("R1", z, temp)
        re, dre = self.p("R2", z, temp)
        rs, drs = re + rc, dre + drc
        num = rc * ue + re * uc
        par = re * rc / rs  # R_e ∥ R_c
        y = u + num / rs - par * i - r0 * i
        if not jac:
            return y, None, None
        dpar = (dre * rc + re * drc) / rs - re * rc * drs / rs**2
        H = np.empty_like(x)
        H[..., 0] = du - dr0 * i + (drc * ue + dre * uc) / rs - num * drs / rs**2 - dpar * i
        H[..., 1] = rc / rs
        H[..., 2] = re / rs
        return y, H, -par - r0
