"""SOC-only models with a static correction term: Shepherd (7), Unnewehr (8), Nernst (9), Fang (10), Tremblay1 (12),
Plett (14) (ECM_SPEC §5.7–5.10, §5.12, §5.14), in OCV-curve mode.

State ``x = [z]``. Every model is ``U(z) + g(z; p) − R0(z)·I`` for its own term ``g``::

    z⁺ = z − η(I) κ I                      (B1)          F = [1],  B = [−ηκ]
    y  = U(z) + g(z; p(z)) − R0(z) I                     H = [U'(z) + dg/dz − R0'(z) I],  D = −R0(z)

``dg/dz`` is the total derivative: every parameter may be a SOC function (Constant/Polynomial/Lookup), so the
``dp/dz`` chain-rule terms are included. Singular terms use the ε-guard of B6 (``z_s = clip(z, ε, 1 − ε)``,
ε = 1e-3, derivative 0 where clipped); the state ``z`` itself is never clipped. ``R0`` is floored at 0 in robust mode.

The terms (``it = Q(1 − z)`` is the extracted charge in Ah, ``Q`` the capacity)::

    Shepherd   g = −K/z_s
    Unnewehr   g = −K z
    Nernst     g = −K0 ln z_s + K1 ln(1 − z_s)
    Fang       g = −K0 ln(τ1 + z) + K1 ln(τ2 + 1 − z)   (arguments floored at ε: positive on [0, 1] only)
    Tremblay1  g = −K/z_s + A e^{−B·it}             (= Shepherd + the exponential zone term; −K·Q/(Q − it) = −K/z)
    Plett      g = K0 − K1/z_s − K2 z + K3 ln z_s + K4 ln(1 − z_s)
"""

from __future__ import annotations

import numpy as np

from .base import KernelSpec, Model
from .blocks import (
    R_FLOOR,
    clipped_exp,
    floor_value,
    floored_log,
    guarded_inv,
    guarded_log,
    guarded_log1m,
    soc_rate,
    soc_step,
)


def exponential_zone(model: Model, z, temp=None, A="A", B="B"):
    """Tremblay's exponential zone ``A·e^{−B·it}``, ``it = Q(1 − z)``, and its total z-derivative.

    ``arg = −B Q (1 − z)`` is clipped at ±50 (``clipped_exp``)::

        d/dz = A' e + A · (de/darg) · (B Q − B' Q (1 − z))

    Shared by Tremblay1 here and by Liu/Tremblay2 (``tremblay.py``).
    """
    a, da = model.p(A, z, temp)
    b, db = model.p(B, z, temp)
    q = model.capacity_ah
    arg = -b * q * (1.0 - z)
    e, de = clipped_exp(arg)
    return a * e, da * e + a * de * (b * q - db * q * (1.0 - z))


class StaticTermModel(Model):
    """``y = U(z) + g(z) − R0 I`` with state ``[z]``; subclasses implement :meth:`term`."""

    param_units = {"R0": "Ω"}

    def term(self, z, temp=None, guards=None):
        """``(g, dg/dz)`` at SOC ``z`` and cell temperature ``temp``."""
        raise NotImplementedError

    def kernel_spec(self):
        from ..kernels.lowering import STATIC_TERMS  # the compiled term of each model (kernels/evaluate.py)

        if self.name not in STATIC_TERMS:
            return None
        params = ("R0",) + tuple(p for p in self.param_names if p != "R0")
        return KernelSpec("static_terms", params, step=(0, 0), output=(0, len(params)), sub=STATIC_TERMS[self.name])

    def step(self, x, i, dt, temp=None, jac=False, guards=None):
        x, (i, dt) = self._broadcast(x, i, dt)
        zn, dz_di = soc_step(x[..., 0], i, dt, self.capacity_ah, self.eta_charge)
        xn = zn[..., None]
        if not jac:
            return xn, None, None
        return xn, np.ones(x.shape + (1,)), dz_di[..., None]

    def _states_given_soc(self, xs, x0, i, dt, temp, guards):
        """SOC is the only state: nothing beyond the SOC path (see :meth:`Model.open_loop`)."""

    def dxdt(self, x, i, temp=None, z_params=None):
        x, (i,) = self._broadcast(x, i)
        return soc_rate(i, self.capacity_ah, self.eta_charge)[..., None]

    def output(self, x, i, temp=None, jac=False, guards=None):
        x, (i,) = self._broadcast(x, i)
        z = x[..., 0]
        u, du = self.ocv.value_and_slope(z, temp)
        r0, dr0 = floor_value(*self.p("R0", z, temp), R_FLOOR, self.mode, guards, "R0_floor")
        g, dg = self.term(z, temp, guards)
        y = u + g - r0 * i
        if not jac:
            return y, None, None
        return y, (du + dg - dr0 * i)[..., None], -r0


class Shepherd(StaticTermModel):
    """(7) ``g = −K/z_s`` (Plett 2004 / Meng 2018 form of Shepherd, K in V); ``dg/dz = −K' /z_s + K/z²``."""

    name = "shepherd"
    title = "Shepherd"
    paper_number = 7
    source = "Shepherd 1965 as simplified by Plett 2004 (y = E0 − R i − K/z), E0 → U_oc(z)"
    param_names = ("K", "R0")
    param_units = {"K": "V", "R0": "Ω"}
    corrections = "K in V (printed Ω); 1/z guarded at ε = 1e-3; K < 0 raises the voltage toward z → 0 (+30 mV at 0.01)"

    def term(self, z, temp=None, guards=None):
        k, dk = self.p("K", z, temp)
        inv, dinv = guarded_inv(z, guards=guards)
        return -k * inv, -dk * inv - k * dinv


class Unnewehr(StaticTermModel):
    """(8) ``g = −K z``; ``dg/dz = −K − K' z``."""

    name = "unnewehr"
    title = "Unnewehr universal"
    paper_number = 8
    source = "Unnewehr universal model as given by Plett 2004 (y = E0 − R i − K z), E0 → U_oc(z)"
    param_names = ("K", "R0")
    param_units = {"K": "V", "R0": "Ω"}
    corrections = "K in V (printed Ω)"

    def term(self, z, temp=None, guards=None):
        k, dk = self.p("K", z, temp)
        return -k * z, -k - dk * z


class Nernst(StaticTermModel):
    """(9) ``g = −K0 ln z_s + K1 ln(1 − z_s)``; ``dg/dz = −K0/z − K1/(1 − z)`` (+ K0', K1' terms), 0 where clipped."""

    name = "nernst"
    title = "Nernst"
    paper_number = 9
    source = "Plett 2004 (y = E0 − R i + K2 ln z + K3 ln(1 − z)), paper's signs (K0 = −K2), E0 → U_oc(z)"
    param_names = ("K0", "K1", "R0")
    param_units = {"K0": "V", "K1": "V", "R0": "Ω"}
    corrections = "K's in V (printed Ω); ln z, ln(1 − z) guarded at ε = 1e-3 (finite at z = 1, the flight start)"

    def term(self, z, temp=None, guards=None):
        k0, dk0 = self.p("K0", z, temp)
        k1, dk1 = self.p("K1", z, temp)
        lz, dlz = guarded_log(z, guards=guards)
        l1z, dl1z = guarded_log1m(z)  # same clip as ln z: noted once
        return -k0 * lz + k1 * l1z, -dk0 * lz - k0 * dlz + dk1 * l1z + k1 * dl1z


class Fang(StaticTermModel):
    """(10) ``g = −K0 ln(τ1 + z) + K1 ln(τ2 + 1 − z)``; ``dg/dz = −K0/(τ1 + z) − K1/(τ2 + 1 − z)`` (+ p' terms).

    τ1, τ2 > 0 keep the logarithms finite on [0, 1]; no guard (the form is the paper's, the original unverified).
    """

    name = "fang"
    title = "Fang (improved Nernst)"
    paper_number = 10
    source = "Fang et al. 2014 (ACC), form as printed by Jung & Tullu (original not retrievable)"
    param_names = ("K0", "K1", "R0", "tau1", "tau2")
    param_units = {"K0": "V", "K1": "V", "R0": "Ω", "tau1": "-", "tau2": "-"}
    corrections = "K's in V (printed Ω); K0 ln(τ1 + z) is a near-constant offset (τ1 ≈ 847)"

    def term(self, z, temp=None, guards=None):
        k0, dk0 = self.p("K0", z, temp)
        k1, dk1 = self.p("K1", z, temp)
        t1, dt1 = self.p("tau1", z, temp)
        t2, dt2 = self.p("tau2", z, temp)
        # both arguments are positive on [0, 1] (τ1, τ2 > 0) but a fit may take τ2 near 0, and a filter's sigma
        # points or particles reach z > 1 + τ2, where ln(τ2 + 1 − z) is undefined: the B6 floor, counted
        la, dla = floored_log(t1 + z, guards=guards)
        lb, dlb = floored_log(t2 + 1.0 - z, guards=guards)
        g = -k0 * la + k1 * lb
        dg = -dk0 * la - k0 * (dt1 + 1.0) * dla + dk1 * lb + k1 * (dt2 - 1.0) * dlb
        return g, dg


class Tremblay1(StaticTermModel):
    """(12) ``g = −K/z_s + A e^{−B Q (1 − z)}`` (Tremblay 2007 with ``it = ∫ i dt = Q(1 − z)``, not ``I_L·t``)."""

    name = "tremblay1"
    title = "Tremblay 2007"
    paper_number = 12
    source = "Tremblay, Dessaint & Dekkiche 2007 (E0 − K Q/(Q − it) + A e^{−B it}), E0 → U_oc(z)"
    param_names = ("K", "A", "B", "R0")
    param_units = {"K": "V", "A": "V", "B": "1/Ah", "R0": "Ω"}
    corrections = "eq. 29 I_L·t → it = ∫i dt = Q(1 − z) (the cause of the kV errors); K in V; = Shepherd + exp term"

    def term(self, z, temp=None, guards=None):
        k, dk = self.p("K", z, temp)
        inv, dinv = guarded_inv(z, guards=guards)
        ex, dex = exponential_zone(self, z, temp)
        return -k * inv + ex, -dk * inv - k * dinv + dex


class Plett(StaticTermModel):
    """(14) ``g = K0 − K1/z_s − K2 z + K3 ln z_s + K4 ln(1 − z_s)``;
    ``dg/dz = K1/z² − K2 + K3/z − K4/(1 − z)`` (+ p' terms), singular parts 0 where clipped."""

    name = "plett"
    title = "Plett combined"
    paper_number = 14
    source = "Plett 2004 Part 2 combined model (y = K0 − R i − K1/z − K2 z + K3 ln z + K4 ln(1 − z)), + U_oc(z)"
    param_names = ("K0", "K1", "K2", "K3", "K4", "R0")
    param_units = {"K0": "V", "K1": "V", "K2": "V", "K3": "V", "K4": "V", "R0": "Ω"}
    corrections = (
        "eq. 35 SOC sign (ż = −ηI/3600Q); R0 = 0.0016 (0.0027 belongs to Tremblay2); K's in V; K0 is an offset; "
        "1/z, ln z, ln(1 − z) guarded at ε = 1e-3"
    )

    def term(self, z, temp=None, guards=None):
        k = [self.p(f"K{j}", z, temp) for j in range(5)]
        inv, dinv = guarded_inv(z, guards=guards)
        lz, dlz = guarded_log(z)  # same clip as 1/z: the guard is noted once per sample
        l1z, dl1z = guarded_log1m(z)
        (k0, d0), (k1, d1), (k2, d2), (k3, d3), (k4, d4) = k
        g = k0 - k1 * inv - k2 * z + k3 * lz + k4 * l1z
        dg = d0 - d1 * inv - k1 * dinv - d2 * z - k2 + d3 * lz + k3 * dlz + d4 * l1z + k4 * dl1z
        return g, dg
