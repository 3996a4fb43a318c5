"""Shared building blocks of the ECMs (ECM_SPEC §4), each with its exact ZOH form and derivatives.

Every model is written with these; none re-derives them. All functions are batched: arguments broadcast.

B1  SOC counter            z⁺ = z − η(I)·κ·I,  κ = dt/(3600 Q)
B2  parallel RC branch     U⁺ = a U + b I,  a = e^{−dt/τ}, b = R(1 − a) = −R·expm1(−dt/τ), τ = R C
B3  pure integrator        U0⁺ = U0 + dt·I/C0(z)
B4  low-pass current       I*⁺ = a_f I* + (1 − a_f) I,  a_f = e^{−dt/t_c}
B5  coupled two-capacitor  w⁺ = Φ w + Γ I,  Φ = I₂ + φ1 A,  Γ = (dt I₂ + φ2 A) B  (Improved RC; A² = λA)
B6  singular-term guard    1/z, ln z, ln(1−z) evaluated at z_s = clip(z, ε, 1−ε), derivative 0 when clipped;
                           a logarithm of any argument a at max(a, ε) (floored_log), derivative 0 when floored

Guards (ECM_SPEC §7.3) act in ``robust`` mode and raise :class:`~socbench.errors.ModelError` in ``strict`` mode; a
:class:`GuardLog`, passed explicitly by the caller (no hidden state), counts on how many samples each guard acted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ModelError

#: ε of the singular-term guard (ECM_SPEC §4 B6 and §7.3).
EPS_SINGULAR = 1e-3
#: τ below this fraction of dt uses the algebraic limit a = 0, b = R.
TAU_ALGEBRAIC = 1e-3
#: capacitance floor of robust mode [F].
C_FLOOR = 1e3
#: resistance floor of robust mode [Ω].
R_FLOOR = 0.0
#: clip of exponent arguments (Liu/Tremblay e^{−B·it}).
EXP_CLIP = 50.0

ROBUST = "robust"
STRICT = "strict"


@dataclass
class GuardLog:
    """Counts, per guard, the samples on which it acted. Pass one to a model call to collect; None to skip."""

    counts: dict = field(default_factory=dict)
    samples: int = 0

    def note(self, name: str, mask) -> None:
        n = int(np.count_nonzero(mask))
        if n:
            self.counts[name] = self.counts.get(name, 0) + n

    def fractions(self) -> dict:
        return {k: v / max(self.samples, 1) for k, v in sorted(self.counts.items())}


def _check_mode(mode: str) -> None:
    if mode not in (ROBUST, STRICT):
        raise ValueError(f"mode must be '{ROBUST}' or '{STRICT}', got {mode!r}")


# ----------------------------------------------------------------------------------------------------------- B1
def eta(i, eta_charge: float):
    """Coulombic efficiency η(I): 1 on discharge (I ≥ 0), η_c on charge."""
    return np.where(np.asarray(i) >= 0.0, 1.0, eta_charge)


def soc_step(z, i, dt, capacity_ah: float, eta_charge: float = 1.0):
    """B1. Returns ``(z⁺, ∂z⁺/∂I)``; ``∂z⁺/∂z = 1``."""
    k = eta(i, eta_charge) * np.asarray(dt) / (3600.0 * capacity_ah)
    return z - k * i, -k


# ----------------------------------------------------------------------------------------------------------- floors
def floor_value(p, dp, lower: float, mode: str, guards: GuardLog | None, name: str):
    """Robust mode: ``max(p, lower)`` with zero derivative where floored. Strict mode: keep (R) — see callers."""
    low = p < lower
    if guards is not None:
        guards.note(name, low)
    if mode == ROBUST and np.any(low):
        return np.where(low, lower, p), None if dp is None else np.where(low, 0.0, dp)
    return p, dp


# ----------------------------------------------------------------------------------------------------------- B2
def rc_coefficients(R, dR, C, dC, dt, mode: str = ROBUST, guards: GuardLog | None = None, name="rc",
                    derivatives: bool = True):
    """B2 coefficients ``(a, b, a_z, b_z)`` of ``U⁺ = a U + b I`` for branch ``R(z), C(z)`` with z-derivatives.

    ``τ = R C``, ``a = e^{−dt/τ}``, ``b = −R·expm1(−dt/τ)``,
    ``τ_z = R' C + R C'``, ``a_z = a·dt·τ_z/τ²``, ``b_z = R'(1 − a) − R a_z``.
    ``τ < 10⁻³ dt`` → algebraic limit ``a = 0, b = R``. ``τ ≤ 0``: strict raises, robust floors ``R ≥ 0, C ≥ 10³ F``.

    Several branches at once: ``name`` a sequence of branch names, one per entry of the first axis of ``R, C``
    (guards and errors then name the branch). ``derivatives=False`` returns ``a_z = b_z = None`` (``dR, dC`` unused).
    """
    R = np.asarray(R, dtype=float)
    C = np.asarray(C, dtype=float)
    names = (name,) if isinstance(name, str) else tuple(name)
    bad = (R < 0) | (C <= 0)
    if np.any(bad):
        which = [0] if len(names) == 1 else [j for j in range(len(names)) if np.any(bad[j])]
        if mode == STRICT:
            j = which[0]
            Rj, Cj = (R, C) if len(names) == 1 else (R[j], C[j])
            raise ModelError(f"{names[j]}: non-positive time constant (R={np.min(Rj):.3g} Ω, C={np.min(Cj):.3g} F)")
        if guards is not None:
            for j in which:
                guards.note(f"{names[j]}_floor", bad if len(names) == 1 else bad[j])
        negR = R < 0
        lowC = (C < C_FLOOR) & bad
        R, C = np.where(negR, R_FLOOR, R), np.where(lowC, C_FLOOR, C)
        if derivatives:
            dR, dC = np.where(negR, 0.0, dR), np.where(lowC, 0.0, dC)
    tau = R * C
    dt = np.asarray(dt, dtype=float)
    algebraic = tau < TAU_ALGEBRAIC * dt
    if not algebraic.any():  # the usual case: the same operations without the algebraic-limit selections
        em = np.expm1(-dt / tau)
        a = em + 1.0
        b = -R * em
        if not derivatives:
            return a, b, None, None
        a_z = a * dt * (dR * C + R * dC) / tau**2
        return a, b, a_z, dR * (1.0 - a) - R * a_z
    safe_tau = np.where(algebraic, 1.0, tau)
    em = np.expm1(-dt / safe_tau)
    a = np.where(algebraic, 0.0, em + 1.0)
    b = np.where(algebraic, R, -R * em)
    if not derivatives:
        return a, b, None, None
    tau_z = dR * C + R * dC
    a_z = np.where(algebraic, 0.0, a * dt * tau_z / safe_tau**2)
    b_z = np.where(algebraic, dR, dR * (1.0 - a) - R * a_z)
    return a, b, a_z, b_z


# ----------------------------------------------------------------------------------------------------------- B3
def integrator_coefficients(C0, dC0, dt):
    """B3 ``U0⁺ = U0 + g I`` with ``g = dt/C0`` and ``g_z = −dt·C0'/C0²``. ``C0 = inf`` disables it (g = 0)."""
    C0 = np.asarray(C0, dtype=float)
    g = np.asarray(dt) / C0
    g_z = -np.asarray(dt) * dC0 / C0**2
    return g, np.where(np.isinf(C0), 0.0, g_z)


# ----------------------------------------------------------------------------------------------------------- B4
def lowpass_coefficients(tc, dtc, dt):
    """B4 ``I*⁺ = a_f I* + (1 − a_f) I`` with ``a_f = e^{−dt/t_c}`` and ``∂a_f/∂z = a_f·dt·t_c'/t_c²``."""
    tc = np.asarray(tc, dtype=float)
    a = np.exp(-np.asarray(dt) / tc)
    return a, a * dt * dtc / tc**2


# ----------------------------------------------------------------------------------------------------------- B6
def _clip_singular(z, eps):
    z = np.asarray(z, dtype=float)
    zs = np.clip(z, eps, 1.0 - eps)
    inside = (z > eps) & (z < 1.0 - eps)
    return zs, inside


def guarded_inv(z, eps: float = EPS_SINGULAR, guards: GuardLog | None = None):
    """``(1/z_s, d/dz)`` — derivative 0 where clipped."""
    zs, inside = _clip_singular(z, eps)
    if guards is not None:
        guards.note("singular_eps", ~inside)
    return 1.0 / zs, np.where(inside, -1.0 / zs**2, 0.0)


def guarded_log(z, eps: float = EPS_SINGULAR, guards: GuardLog | None = None):
    """``(ln z_s, d/dz)``."""
    zs, inside = _clip_singular(z, eps)
    if guards is not None:
        guards.note("singular_eps", ~inside)
    return np.log(zs), np.where(inside, 1.0 / zs, 0.0)


def guarded_log1m(z, eps: float = EPS_SINGULAR, guards: GuardLog | None = None):
    """``(ln(1 − z_s), d/dz)``."""
    zs, inside = _clip_singular(z, eps)
    if guards is not None:
        guards.note("singular_eps", ~inside)
    return np.log1p(-zs), np.where(inside, -1.0 / (1.0 - zs), 0.0)


def floored_log(a, eps: float = EPS_SINGULAR, guards: GuardLog | None = None, name: str = "singular_eps"):
    """``(ln max(a, ε), d/da)`` — derivative 0 where floored. For logarithms whose argument is positive on the
    model's domain but not beyond it (Fang's ``ln(τ2 + 1 − z)`` at a sigma point or particle above ``1 + τ2``)."""
    a = np.asarray(a, dtype=float)
    floored = ~(a > eps)
    if guards is not None:
        guards.note(name, floored)
    a_s = np.where(floored, eps, a)
    return np.log(a_s), np.where(floored, 0.0, 1.0 / a_s)


def clipped_exp(arg):
    """``(e^{arg_c}, d/d arg)`` with ``arg_c = clip(arg, −50, 50)``; derivative 0 where clipped."""
    arg = np.asarray(arg, dtype=float)
    c = np.clip(arg, -EXP_CLIP, EXP_CLIP)
    e = np.exp(c)
    return e, np.where(c == arg, e, 0.0)


# ------------------------------------------------------------------------------------------------ B1 (continuous)
def soc_rate(i, capacity_ah: float, eta_charge: float = 1.0):
    """B1 in continuous time: ``ż = −η(I)·I/(3600 Q)``."""
    return -eta(i, eta_charge) * np.asarray(i, dtype=float) / (3600.0 * capacity_ah)


# ----------------------------------------------------------------------------------------------------------- B5
#: below this |λ·dt| the φ functions are summed as power series (the closed forms cancel near 0: relative error
#: ≈ 6ε/x² for e2', i.e. 6e-14 at the switch; the 10-term series is exact to 1e-19 there).
_PHI_SERIES_BELOW = 0.1
_PHI_TERMS = 10
_INV_FACT = 1.0 / np.cumprod(np.r_[1.0, np.arange(1.0, _PHI_TERMS + 3.0)])  # 1/n!, n = 0 … _PHI_TERMS + 2


def _phi_functions(x, derivatives: bool = True):
    """``e1 = expm1(x)/x``, ``e2 = (expm1(x) − x)/x²`` and (optionally) their x-derivatives ``e1', e2'``.

    Series (|x| < 0.1): ``e1 = Σ x^k/(k+1)!``, ``e2 = Σ x^k/(k+2)!``, ``e1' = Σ k x^{k−1}/(k+1)!``,
    ``e2' = Σ k x^{k−1}/(k+2)!``. Closed forms otherwise: ``e1' = (x e^x − expm1 x)/x²``,
    ``e2' = (x expm1 x − 2(expm1 x − x))/x³``.
    """
    x = np.asarray(x, dtype=float)
    small = np.abs(x) < _PHI_SERIES_BELOW
    out = [None] * 4
    if small.any():
        xs = np.where(small, x, 0.0)
        e1, e2, d1, d2 = (np.zeros_like(xs) for _ in range(4))
        for k in range(_PHI_TERMS, -1, -1):  # Horner, highest power first
            e1 = e1 * xs + _INV_FACT[k + 1]
            e2 = e2 * xs + _INV_FACT[k + 2]
            if derivatives and k >= 1:
                d1 = d1 * xs + k * _INV_FACT[k + 1]
                d2 = d2 * xs + k * _INV_FACT[k + 2]
        out = [e1, e2, d1, d2]
    if not small.all():
        xl = np.where(small, 1.0, x)
        em = np.expm1(xl)
        closed = [em / xl, (em - xl) / xl**2]
        if derivatives:
            closed += [(xl * (em + 1.0) - em) / xl**2, (xl * em - 2.0 * (em - xl)) / xl**3]
        else:
            closed += [None, None]
        out = [c if o is None or c is None else np.where(small, o, c) for o, c in zip(out, closed)]
    return tuple(out) if derivatives else (out[0], out[1], None, None)


def _mv(M, v):
    """Batched matrix–vector product ``M v`` for ``M (..., 2, 2)``, ``v (..., 2)``."""
    return np.einsum("...ij,...j->...i", M, v)


def coupled_rc_coefficients(Re, dRe, Rc, dRc, Ce, dCe, Cc, dCc, dt, derivatives: bool = True):
    """B5: exact ZOH ``w⁺ = Φ w + Γ I`` of the coupled two-capacitor network and its z-derivatives.

    ``w = [U_e, U_c]``, ``R_s = R_e + R_c``, ``α = 1/C_e``, ``β = 1/C_c``::

        ẇ = A w + B I,   A = (1/R_s)[[−α, α], [β, −β]],   B = −(1/R_s)[R_c α, R_e β]ᵀ
        A² = λA,  λ = −(α + β)/R_s
        Φ = I₂ + φ1 A,            φ1 = expm1(λ dt)/λ
        Γ = (dt I₂ + φ2 A) B,     φ2 = (expm1(λ dt) − λ dt)/λ²

    z-derivatives (primes), from ``R_e', R_c', C_e', C_c'``::

        α' = −C_e'/C_e²,  β' = −C_c'/C_c²,  R_s' = R_e' + R_c'
        A' = −(R_s'/R_s) A + (1/R_s)[[−α', α'], [β', −β']]
        B' = −(R_s'/R_s) B − (1/R_s)[R_c' α + R_c α',  R_e' β + R_e β']ᵀ
        λ' = −(α' + β')/R_s − λ R_s'/R_s
        Φ' = φ1 A' + (dφ1/dλ) λ' A
        Γ' = (dt I₂ + φ2 A) B' + (φ2 A' + (dφ2/dλ) λ' A) B

    Returns ``(Φ (…,2,2), Γ (…,2), Φ', Γ', λ)`` (``Φ', Γ'`` None unless ``derivatives``). No guards here: the
    caller checks ``C > 0``, ``R_s > 0`` and ``λ ≤ 0`` (strict) or floors ``C`` (robust) first (ECM_SPEC §7.3).
    """
    Re, dRe, Rc, dRc, Ce, dCe, Cc, dCc, dt = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (Re, dRe, Rc, dRc, Ce, dCe, Cc, dCc, dt))
    )
    Rs = Re + Rc
    dRs = dRe + dRc
    al, be = 1.0 / Ce, 1.0 / Cc
    lam = -(al + be) / Rs

    def mat(a, b):
        return np.stack([np.stack([-a, a], axis=-1), np.stack([b, -b], axis=-1)], axis=-2)

    A = mat(al, be) / Rs[..., None, None]
    B = -np.stack([Rc * al, Re * be], axis=-1) / Rs[..., None]
    e1, e2, d1, d2 = _phi_functions(lam * dt, derivatives)
    phi1, phi2 = dt * e1, dt**2 * e2
    eye = np.eye(2)
    Phi = eye + phi1[..., None, None] * A
    G = dt[..., None, None] * eye + phi2[..., None, None] * A  # ∫₀^dt e^{As} ds
    Gamma = _mv(G, B)
    if not derivatives:
        return Phi, Gamma, None, None, lam
    dal, dbe = -dCe / Ce**2, -dCc / Cc**2
    dlam = -(dal + dbe) / Rs - lam * dRs / Rs
    dA = -(dRs / Rs)[..., None, None] * A + mat(dal, dbe) / Rs[..., None, None]
    dB = -(dRs / Rs)[..., None] * B - np.stack([dRc * al + Rc * dal, dRe * be + Re * dbe], axis=-1) / Rs[..., None]
    dphi1, dphi2 = dt**2 * d1, dt**3 * d2  # d/dλ
    dPhi = phi1[..., None, None] * dA + (dphi1 * dlam)[..., None, None] * A
    dG = phi2[..., None, None] * dA + (dphi2 * dlam)[..., None, None] * A
    dGamma = _mv(G, dB) + _mv(dG, B)
    return Phi, Gamma, dPhi, dGamma, lam
