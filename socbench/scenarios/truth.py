"""The truth cell of the scenarios: an ESC-like pack model richer than any estimator's model.

State per run ``x = [z, U1, U2, h, s, T]`` (batched over leading axes), input ``I`` (A, positive = discharge)::

    z⁺  = z − η(I) I dt/(3600 Q)                                   B1 (socbench.models.blocks.soc_step)
    Uj⁺ = a_j Uj + b_j I,  τ_j = R_j(T) C_j                         B2 (blocks.rc_coefficients), j = 1, 2
    h⁺  = A_h h − (1 − A_h) sgn(I),  A_h = exp(−|η I γ dt/(3600 Q)|)  one-state hysteresis (ECM_SPEC §9.1)
    s⁺  = sgn(I) if |I| > Q/100 else s                              instantaneous hysteresis sign
    T⁺  = T_a + (T − T_a) e^{−dt/τ_th} + R_th (1 − e^{−dt/τ_th}) q,  τ_th = R_th C_th      lumped thermal (§9.2)
    y   = U_oc(z) + (T − T_ref) dU/dT + M h + M0 s − R0(T) I − U1 − U2 − U_ct(I, T)

with Arrhenius resistances ``R(T) = R_ref exp[(E_a/R_g)(1/T − 1/T_ref)]`` (R0, R1, R2; C fixed so τ follows R), the
Butler–Volmer charge-transfer drop ``U_ct = N_s (2 R_g T/F) asinh(I/(2 I0(T)))`` with ``I0(T) = I0_ref / arrhenius``
(§9.6), and the Bernardi heat ``q = I (U_oc − y) − I T dU/dT`` (irreversible + reversible, discharge positive).

Parameters are pack-level on the paper pack (6S 22 Ah, its OCV curve from ``socbench.models.paper_ocv``). They are
calibrated assumptions of the size of a high-rate 22 Ah LiPo pack (≈ 1.2–1.6 mΩ per cell DC), not fitted values:
the paper publishes no truth. No Jacobians: the truth is only simulated.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ..models.blocks import rc_coefficients, soc_step
from ..models.paper import paper_ocv, paper_pack
from ..ocv import OCVCurve
from .config import require

R_GAS = 8.314462618  # J/(mol K)
FARADAY = 96485.33212  # C/mol
KELVIN = 273.15

#: state layout
Z, U1, U2, HYST, SIGN, TEMP = range(6)
STATE_NAMES = ("z", "U1", "U2", "h", "s", "T")


@dataclass(frozen=True)
class TruthParams:
    """Pack-level truth parameters (units in the names). Defaults: calibrated assumptions, see the module docstring."""

    capacity_ah: float = 22.0  # the paper pack's rated capacity (ECM_SPEC §1)
    n_series: int = 6
    r0_ohm: float = 0.0015  # ohmic resistance at T_ref
    r1_ohm: float = 0.0020  # fast RC branch (charge transfer / double layer)
    tau1_s: float = 20.0
    r2_ohm: float = 0.0025  # slow RC branch (diffusion)
    tau2_s: float = 240.0
    hyst_m_v: float = 0.030  # one-state hysteresis magnitude M (pack; 5 mV per cell)
    hyst_m0_v: float = 0.006  # instantaneous hysteresis M0
    hyst_gamma: float = 50.0  # hysteresis rate γ (flips over ~1/γ of the capacity)
    eta_charge: float = 1.0  # coulombic efficiency on charge
    activation_k: float = 3600.0  # E_a/R_g [K] of the Arrhenius resistances (E_a ≈ 30 kJ/mol)
    t_ref_c: float = 25.0
    bv_i0_a: float = 60.0  # Butler–Volmer exchange current at T_ref (small-signal 2.6 mΩ for N_s = 6)
    entropic_v_per_k: float = 0.0003  # dU_oc/dT of the pack (0.05 mV/K per cell)
    thermal_capacity_j_per_k: float = 2400.0  # 2.40 kg × ≈1000 J/(kg K)
    thermal_resistance_k_per_w: float = 1.0  # pack to ambient
    ocv: OCVCurve = field(default_factory=paper_ocv, compare=False)

    def __post_init__(self):
        positive = ("capacity_ah", "tau1_s", "tau2_s", "hyst_gamma", "activation_k", "bv_i0_a",
                    "thermal_capacity_j_per_k", "thermal_resistance_k_per_w")
        for name in positive:
            require(getattr(self, name) > 0, name, f"must be > 0, got {getattr(self, name)}")
        for name in ("r0_ohm", "r1_ohm", "r2_ohm", "hyst_m_v", "hyst_m0_v"):
            require(getattr(self, name) >= 0, name, f"must be >= 0, got {getattr(self, name)}")
        require(0 < self.eta_charge <= 1, "eta_charge", f"must be in (0, 1], got {self.eta_charge}")
        require(self.n_series >= 1, "n_series", f"must be >= 1, got {self.n_series}")

    @classmethod
    def keys(cls) -> tuple:
        return tuple(f.name for f in fields(cls) if f.name != "ocv")


class TruthCell:
    """The batched truth model. Pure: methods map ``(state, input) -> new values``; nothing is stored between calls."""

    def __init__(self, params: TruthParams | None = None):
        self.params = params or TruthParams()
        p = self.params
        # a branch with R = 0 keeps U = 0 whatever C is (b = R(1 − a) = 0); C from τ otherwise
        self._r_rc = np.array([p.r1_ohm, p.r2_ohm])
        self._c_rc = np.array([p.tau1_s / max(p.r1_ohm, 1e-300), p.tau2_s / max(p.r2_ohm, 1e-300)])
        self.uv_limit_v = float(paper_pack()["under_voltage_v"])

    # ------------------------------------------------------------------ state
    def initial_state(self, soc, temp_c=25.0, hyst=0.0, batch=()) -> np.ndarray:
        """Rest state at SOC ``soc``: RC branches relaxed, hysteresis ``hyst`` (−1 discharge … +1 charge branch)."""
        shape = np.broadcast_shapes(np.shape(soc), np.shape(temp_c), tuple(np.atleast_1d(batch)) if batch else ())
        x = np.zeros(shape + (6,))
        x[..., Z] = soc
        x[..., HYST] = hyst
        x[..., SIGN] = -np.sign(hyst) if hyst else 0.0
        x[..., TEMP] = temp_c
        return x

    def arrhenius(self, temp_c):
        p = self.params
        return np.exp(p.activation_k * (1.0 / (np.asarray(temp_c) + KELVIN) - 1.0 / (p.t_ref_c + KELVIN)))

    def charge_transfer(self, i, temp_c):
        """Butler–Volmer overpotential ``U_ct(I, T)`` [V] (symmetric α = 0.5)."""
        p = self.params
        tk = np.asarray(temp_c) + KELVIN
        i0 = p.bv_i0_a / self.arrhenius(temp_c)
        return p.n_series * (2.0 * R_GAS * tk / FARADAY) * np.arcsinh(np.asarray(i) / (2.0 * i0))

    def open_circuit(self, x):
        """``U_oc(z) + (T − T_ref) dU/dT + M h`` [V]: the rest voltage the pack relaxes to."""
        p = self.params
        return p.ocv(x[..., Z]) + (x[..., TEMP] - p.t_ref_c) * p.entropic_v_per_k + p.hyst_m_v * x[..., HYST]

    def _sign(self, x, i):
        """Instantaneous hysteresis sign for this sample: sgn(I) when |I| > Q/100, else the remembered sign."""
        return np.where(np.abs(i) > self.params.capacity_ah / 100.0, np.sign(i), x[..., SIGN])

    def voltage(self, x, i):
        """Terminal voltage ``y(x, I)`` (direct feed-through of the same-sample current)."""
        p = self.params
        i = np.asarray(i, dtype=float)
        temp = x[..., TEMP]
        r0 = p.r0_ohm * self.arrhenius(temp)
        return (self.open_circuit(x) + p.hyst_m0_v * self._sign(x, i) - r0 * i - x[..., U1] - x[..., U2]
                - self.charge_transfer(i, temp))

    def step(self, x, i, dt, ambient_c) -> np.ndarray:
        """``x⁺`` after holding ``I`` for ``dt`` seconds at ambient temperature ``ambient_c``."""
        return self.advance(x, i, dt, ambient_c)[1]

    def advance(self, x, i, dt, ambient_c):
        """``(y, x⁺)``: the terminal voltage at this sample and the state one step later (one evaluation)."""
        p = self.params
        i = np.broadcast_to(np.asarray(i, dtype=float), x.shape[:-1])
        temp = x[..., TEMP]
        e, r0, a_ct, i0 = self._terms(x)
        sgn = self._sign(x, i)
        y = e + p.hyst_m0_v * sgn - r0 * i - a_ct * np.arcsinh(i / (2.0 * i0))
        xn = np.empty_like(x)
        xn[..., Z], _ = soc_step(x[..., Z], i, dt, p.capacity_ah, p.eta_charge)
        # both RC branches in one call of the shared B2 block: R_j(T) = R_j,ref·arrhenius(T), C_j fixed
        arr = self.arrhenius(temp)[..., None]
        r = self._r_rc * arr
        zero = np.zeros_like(r)
        a, b, _, _ = rc_coefficients(r, zero, np.broadcast_to(self._c_rc, r.shape), zero, dt)
        xn[..., U1:U2 + 1] = a * x[..., U1:U2 + 1] + b * i[..., None]
        eta = np.where(i >= 0, 1.0, p.eta_charge)
        a_h = np.exp(-np.abs(eta * i * p.hyst_gamma * dt / (3600.0 * p.capacity_ah)))
        xn[..., HYST] = a_h * x[..., HYST] - (1.0 - a_h) * np.sign(i)
        xn[..., SIGN] = sgn
        # Bernardi: I·(U_oc,eq − y) − I·T·dU/dT, with U_oc,eq = e + U1 + U2 − entropic shift (the equilibrium voltage)
        u_eq = e + x[..., U1] + x[..., U2] - (temp - p.t_ref_c) * p.entropic_v_per_k
        heat = i * (u_eq - y) - i * (temp + KELVIN) * p.entropic_v_per_k
        tau_th = p.thermal_resistance_k_per_w * p.thermal_capacity_j_per_k
        f = np.exp(-dt / tau_th)
        xn[..., TEMP] = ambient_c + (temp - ambient_c) * f + p.thermal_resistance_k_per_w * (1.0 - f) * heat
        return y, xn

    def rest(self, x, n: int, dt, ambient_c):
        """``n`` samples at zero current in closed form: ``(states (…, n, 6), y (…, n), x after n steps)``.

        Exactly the recursion of :meth:`step` with ``I = 0``: z, h and s hold, the temperature relaxes
        geometrically (no heat), each RC branch decays by ``a_j(T_k)`` per step (a cumulative product)."""
        p = self.params
        x = np.asarray(x, dtype=float)
        tau_th = p.thermal_resistance_k_per_w * p.thermal_capacity_j_per_k
        f = np.exp(-dt / tau_th) ** np.arange(n + 1)
        temp = ambient_c + (x[..., TEMP, None] - ambient_c) * f  # (…, n + 1)
        r = self._r_rc * self.arrhenius(temp[..., :-1])[..., None]  # (…, n, 2)
        zero = np.zeros_like(r)
        a, _, _, _ = rc_coefficients(r, zero, np.broadcast_to(self._c_rc, r.shape), zero, dt)
        decay = np.concatenate([np.ones(a.shape[:-2] + (1, 2)), np.cumprod(a, axis=-2)], axis=-2)  # (…, n + 1, 2)
        states = np.repeat(x[..., None, :], n + 1, axis=-2)
        states[..., TEMP] = temp
        states[..., U1:U2 + 1] = x[..., None, U1:U2 + 1] * decay
        y = self.voltage(states[..., :-1, :], 0.0)
        return states[..., :-1, :], y, states[..., -1, :]

    # ------------------------------------------------------------------ loads that depend on the voltage
    def _terms(self, x):
        """The current-independent parts of ``y``: ``(E, r0, a_ct, i0)`` with
        ``y = E + M0 s(I) − r0 I − a_ct asinh(I/(2 i0))``."""
        p = self.params
        temp = x[..., TEMP]
        arr = self.arrhenius(temp)
        e = self.open_circuit(x) - x[..., U1] - x[..., U2]
        a_ct = p.n_series * 2.0 * R_GAS * (temp + KELVIN) / FARADAY
        return e, p.r0_ohm * arr, a_ct, p.bv_i0_a / arr

    def current_for_power(self, x, power_w, i_guess=None, iterations: int = 3):
        """``(I, y)``: the current drawing ``power_w`` (W, positive = discharge) at the terminals, ``I·y(x, I) = P``.

        Solved by Newton from ``I = P/E``.

        The instantaneous-hysteresis sign is taken as sgn(P) (it is constant on the branch being solved). Beyond the
        pack's maximum power there is no solution; callers stop at the under-voltage limit long before that.
        ``i_guess`` (the previous step's current) speeds up convergence.
        """
        power_w = np.asarray(power_w, dtype=float)
        e, r0, a_ct, i0 = self._terms(x)
        sgn = np.where(np.abs(power_w) > 0, np.sign(power_w), x[..., SIGN])
        e = e + self.params.hyst_m0_v * sgn
        i = power_w / np.maximum(e, 1.0) if i_guess is None else np.asarray(i_guess, dtype=float)
        for _ in range(iterations):
            u = i / (2.0 * i0)
            y = e - r0 * i - a_ct * np.arcsinh(u)
            dy = -r0 - a_ct / (2.0 * i0 * np.sqrt(1.0 + u * u))
            i = i - (i * y - power_w) / (y + i * dy)
        return i, e - r0 * i - a_ct * np.arcsinh(i / (2.0 * i0))

    def current_for_voltage(self, x, v_target, iterations: int = 5):
        """Current that holds the terminal voltage at ``v_target`` (a CV phase): ``y(x, I) = V`` by Newton.

        The instantaneous-hysteresis sign is the remembered one (a CV charge keeps charging)."""
        e, r0, a_ct, i0 = self._terms(x)
        e = e + self.params.hyst_m0_v * x[..., SIGN]
        i = np.zeros(np.shape(e))
        for _ in range(iterations):
            u = i / (2.0 * i0)
            y = e - r0 * i - a_ct * np.arcsinh(u)
            dy = -r0 - a_ct / (2.0 * i0 * np.sqrt(1.0 + u * u))
            i = i - (y - v_target) / dy
        return i
