"""Plett's enhanced self-correcting (ESC) model (ECM_SPEC §9.1; Plett ESC toolbox ``simCell.m``), in OCV-curve mode.

State ``x = [z, iR1, …, iRn, h, s]``: ``iRj`` the current through the resistor of RC branch j, ``h`` the dynamic
hysteresis, ``s`` the instantaneous-hysteresis sign memory (discrete only). ``κ = dt/(3600 Q)``::

    z⁺   = z − η(I) κ I                                                  (B1)
    iRj⁺ = a_j iRj + (1 − a_j) I,   a_j = e^{−dt/τj}                     (B4: a low-pass of the current)
    h⁺   = A_h h − (1 − A_h) sgn(I),   A_h = exp(−|η(I) I γ κ|)          (exact ZOH of ḣ = −|ηIγ/3600Q| (h + sgn I))
    s_k  = sgn(I) if |I| > Q/100 else s          (the same-sample sign, as in simCell.m; s⁺ = s_k)
    y    = U(z) + M0 s_k + M h − Σ Rj iRj − R0 I

Jacobians (``u = η I γ κ``, so ``A_h = e^{−|u|}``; SOC-dependent parameters add their ``p'`` terms)::

    F[iRj, 0] = a_j,z (iRj − I),   F[iRj, iRj] = a_j
    F[h, 0]   = −A_h sgn(u) η I γ' κ (h + sgn I),   F[h, h] = A_h
    F[s, s]   = 1 if |I| ≤ Q/100 else 0            (s is not differentiable: treat it as an input)
    B = [−ηκ, 1 − a_1, …, 1 − a_n, −A_h sgn(u) η γ κ (h + sgn I), 0]
    H = [U' + M0' s_k + M' h − Σ Rj' iRj − R0' I, −R1, …, −Rn, M, M0 (0 if |I| > Q/100)],   D = −R0

Parameters: ``R0, R1..Rn`` [Ω], ``tau1..taun`` [s], ``M, M0`` [V], ``gamma`` [-]; n is the number of ``R1..Rn`` keys.
"""

from __future__ import annotations

import numpy as np

from .base import KernelSpec, Model
from .blocks import R_FLOOR, eta, floor_value, lowpass_coefficients, soc_rate, soc_step
from .recurrence import hysteresis_path, lowpass_path


class ESC(Model):
    name = "esc"
    title = "Enhanced self-correcting (Plett)"
    source = "Plett 2004 Part 2 / ESC toolbox simCell.m: n RC resistor currents, one-state + instantaneous hysteresis"
    corrections = "not in the paper (ECM_SPEC §9.1 hysteresis); parameter set is a stand-in for the 22 Ah 6S pack"
    discrete_states = ("s",)
    param_units = {
        "R0": "Ω",
        "M": "V",
        "M0": "V",
        "gamma": "-",
        **{f"R{j}": "Ω" for j in range(1, 10)},
        **{f"tau{j}": "s" for j in range(1, 10)},
    }

    def __init__(self, params, mode=None):
        n = 0
        while f"R{n + 1}" in params.values:
            n += 1
        self._n = n
        super().__init__(params, mode)

    def required_params(self):
        rs = tuple(f"R{j}" for j in range(1, self._n + 1))
        taus = tuple(f"tau{j}" for j in range(1, self._n + 1))
        return ("R0",) + rs + taus + ("M", "M0", "gamma")

    @property
    def state_names(self):
        return ("z",) + tuple(f"iR{j}" for j in range(1, self._n + 1)) + ("h", "s")

    def kernel_spec(self):
        n = self._n
        params = (("R0",) + tuple(f"R{j}" for j in range(1, n + 1)) + ("M", "M0")
                  + tuple(f"tau{j}" for j in range(1, n + 1)) + ("gamma",))
        return KernelSpec("esc", params, step=(n + 3, 2 * n + 4), output=(0, n + 3), sub=n)

    def _hysteresis_rate(self, i, z, temp=None):
        """``(r, ∂r/∂z, ∂r/∂I)`` of the hysteresis rate ``r = η(I) I γ(z)/(3600 Q)`` [1/s]; ``u = r·dt``."""
        g, dg = self.p("gamma", z, temp)
        c = eta(i, self.eta_charge) / (3600.0 * self.capacity_ah)
        return c * i * g, c * i * dg, c * g

    def _sign_memory(self, s, i):
        """``(moving, s_k)``: ``s_k = sgn(I)`` where ``|I| > Q/100`` (moving), else the held ``s``."""
        moving = np.abs(i) > self.capacity_ah / 100.0
        return moving, np.where(moving, np.sign(i), s)

    def step(self, x, i, dt, temp=None, jac=False, guards=None):
        x, (i, dt) = self._broadcast(x, i, dt)
        z = x[..., 0]
        n = self._n
        jh, js = n + 1, n + 2
        xn = np.empty_like(x)
        xn[..., 0], dz_di = soc_step(z, i, dt, self.capacity_ah, self.eta_charge)
        if jac:
            F = np.zeros(x.shape + (x.shape[-1],))
            F[..., 0, 0] = 1.0
            B = np.zeros_like(x)
            B[..., 0] = dz_di
        for j in range(1, n + 1):
            a, a_z = lowpass_coefficients(*self.p(f"tau{j}", z, temp), dt)
            xn[..., j] = a * x[..., j] + (1.0 - a) * i
            if jac:
                F[..., j, 0] = a_z * (x[..., j] - i)
                F[..., j, j] = a
                B[..., j] = 1.0 - a
        rate, rate_z, rate_i = self._hysteresis_rate(i, z, temp)
        u = rate * dt
        ah = np.exp(-np.abs(u))
        sg = np.sign(i)
        h = x[..., jh]
        xn[..., jh] = ah * h - (1.0 - ah) * sg
        moving, xn[..., js] = self._sign_memory(x[..., js], i)
        if not jac:
            return xn, None, None
        dah_du = -ah * np.sign(u)
        F[..., jh, 0] = dah_du * rate_z * dt * (h + sg)
        F[..., jh, jh] = ah
        F[..., js, js] = np.where(moving, 0.0, 1.0)
        B[..., jh] = dah_du * rate_i * dt * (h + sg)
        return xn, F, B

    def _states_given_soc(self, xs, x0, i, dt, temp, guards):
        """Whole-record states (see :meth:`Model.open_loop`) by :mod:`socbench.models.recurrence`: the low-pass
        currents ``iR⁺ = a(z_k) iR + (1 − a) I`` (B4, ``lowpass_path``), the dynamic hysteresis
        ``h⁺ = a_h h − (1 − a_h) sgn I`` and the sign memory (``hysteresis_path``)."""
        z = xs[:-1, ..., 0]
        n = self._n
        for j in range(1, n + 1):
            xs[..., j] = lowpass_path(lowpass_coefficients(*self.p(f"tau{j}", z, temp), dt)[0], i, x0[..., j])
        decay = np.exp(-np.abs(self._hysteresis_rate(i, z, temp)[0] * dt))
        moving = self._sign_memory(x0[..., n + 2], i)[0]
        xs[..., n + 1], xs[..., n + 2] = hysteresis_path(decay, i, moving, x0[..., n + 1], x0[..., n + 2])

    def dxdt(self, x, i, temp=None, z_params=None):
        x, (i,) = self._broadcast(x, i)
        zp = x[..., 0] if z_params is None else np.broadcast_to(z_params, x.shape[:-1])
        d = np.zeros_like(x)
        d[..., 0] = soc_rate(i, self.capacity_ah, self.eta_charge)
        for j in range(1, self._n + 1):
            d[..., j] = (i - x[..., j]) / self.p(f"tau{j}", zp, temp)[0]
        rate = self._hysteresis_rate(i, zp, temp)[0]
        d[..., self._n + 1] = -np.abs(rate) * (x[..., self._n + 1] + np.sign(i))
        return d  # s (last) has no continuous dynamics: 0

    def output(self, x, i, temp=None, jac=False, guards=None):
        x, (i,) = self._broadcast(x, i)
        z = x[..., 0]
        n = self._n
        h = x[..., n + 1]
        moving, s = self._sign_memory(x[..., n + 2], i)
        u, du = self.ocv.value_and_slope(z, temp)
        r0, dr0 = floor_value(*self.p("R0", z, temp), R_FLOOR, self.mode, guards, "R0_floor")
        m, dm = self.p("M", z, temp)
        m0, dm0 = self.p("M0", z, temp)
        y = u + m0 * s + m * h - r0 * i
        dy_z = du + dm0 * s + dm * h - dr0 * i
        H = np.empty_like(x) if jac else None
        for j in range(1, n + 1):
            r, dr = self.p(f"R{j}", z, temp)
            y = y - r * x[..., j]
            dy_z = dy_z - dr * x[..., j]
            if jac:
                H[..., j] = -r
        if not jac:
            return y, None, None
        H[..., 0] = dy_z
        H[..., n + 1] = m
        H[..., n + 2] = np.where(moving, 0.0, m0)
        return y, H, -r0
