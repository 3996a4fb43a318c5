"""The yardstick of ``socbench bench``: the filters as a filterpy user writes them, with no socbench code in the loop.

A hand-written dual-polarisation (2RC, 3-state) model — the paper's DP parameters (6th-degree polynomials in SOC, by
Horner in plain Python on one state, ``np.polyval`` on a particle cloud) on an OCV curve
(``scipy.interpolate.PchipInterpolator`` through the same rest points, its derivative, linear beyond the rest points)
— in a plain per-run loop:

* :func:`bare_ekf`  ``filterpy.kalman.ExtendedKalmanFilter``: hand-coded ``h, H`` passed to ``update`` and a
  ``predict_x`` that applies ``f`` and sets ``F, Q`` (one update + one predict per sample);
* :func:`bare_ukf`  ``filterpy.kalman.UnscentedKalmanFilter`` with ``MerweScaledSigmaPoints(3, α=1, β=2, κ=0)``,
  hand-coded ``fx, hx`` for one sigma point;
* :func:`bare_pf`   a bootstrap particle filter per run, numpy over the particles, resampling with
  ``filterpy.monte_carlo.systematic_resample`` when ``N_eff < N/2``, roughening after it.

The equations are socbench's DP model (models/rc_network.py) and noise recipe (estimators/noise.py): ``R_k = σ_V² +
σ_I² R0(z)²``, ``Q_k = σ_I² B Bᵀ``, the same samples (update, then predict), the same initial state and covariance.
Without socbench's safety rules (gate, clamp, PSD repair), the EKF and UKF estimates agree with socbench's to round-off
wherever those rules do not act (``socbench bench`` reports the difference on its sweep with the gate off).
The cost of these loops is linear in the runs, so the bench times them on a few runs and quotes µs per step.
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from filterpy.monte_carlo import systematic_resample
from scipy.interpolate import PchipInterpolator


class BareDP:
    """The DP (2RC) model written out by hand: state ``[z, U1, U2]``, current positive on discharge."""

    def __init__(self, capacity_ah, eta_charge, ocv_soc, ocv_voltage, coeffs):
        self.q = float(capacity_ah)
        self.eta = float(eta_charge)
        self.c = {k: np.asarray(coeffs[k], dtype=float) for k in ("R0", "R1", "C1", "R2", "C2")}
        self.cl = {k: [float(c) for c in v] for k, v in self.c.items()}  # plain floats for the scalar Horner
        self.ocv = PchipInterpolator(ocv_soc, ocv_voltage, extrapolate=False)
        self.docv = self.ocv.derivative()
        self.z_lo, self.z_hi = float(ocv_soc[0]), float(ocv_soc[-1])
        self.v_lo, self.v_hi = float(ocv_voltage[0]), float(ocv_voltage[-1])
        self.s_lo, self.s_hi = float(self.docv(self.z_lo)), float(self.docv(self.z_hi))

    @classmethod
    def from_params(cls, params):
        """From socbench's ``paper_params("dp")`` (only to read the numbers; nothing of socbench runs in the loop)."""
        return cls(params.capacity_ah, params.eta_charge, params.ocv.soc, params.ocv.voltage,
                   {k: params[k].coeffs for k in ("R0", "R1", "C1", "R2", "C2")})

    # ---------------------------------------------------------------- one state (EKF, UKF)
    def p(self, name, z):
        """Parameter and its z-derivative (the polynomial on z clipped to [0, 1], flat outside), Horner."""
        zp = min(max(z, 0.0), 1.0)
        c = self.cl[name]
        v, d = c[0], 0.0
        for cj in c[1:]:
            d = d * zp + v
            v = v * zp + cj
        return v, (d if 0.0 <= z <= 1.0 else 0.0)

    def u(self, z):
        if z < self.z_lo:
            return self.v_lo + self.s_lo * (z - self.z_lo), self.s_lo
        if z > self.z_hi:
            return self.v_hi + self.s_hi * (z - self.z_hi), self.s_hi
        return float(self.ocv(z)), float(self.docv(z))

    def f(self, x, i, dt):
        """``(x⁺, F, B)``: SOC counter and two exact-ZOH RC branches with parameters at ``z_k``."""
        z, u1, u2 = x
        k = (1.0 if i >= 0 else self.eta) * dt / (3600.0 * self.q)
        xn = np.empty(3)
        F = np.zeros((3, 3))
        B = np.empty(3)
        xn[0], F[0, 0], B[0] = z - k * i, 1.0, -k
        for j, (r, c, uj) in enumerate((("R1", "C1", u1), ("R2", "C2", u2)), start=1):
            R, dR = self.p(r, z)
            C, dC = self.p(c, z)
            tau = R * C
            em = math.expm1(-dt / tau)
            a, b = em + 1.0, -R * em
            a_z = a * dt * (dR * C + R * dC) / tau**2
            b_z = dR * (1.0 - a) - R * a_z
            xn[j] = a * uj + b * i
            F[j, 0], F[j, j], B[j] = a_z * uj + b_z * i, a, b
        return xn, F, B

    def h(self, x, i):
        """``(y, H, D)``: ``y = U(z) − U1 − U2 − R0(z) I``."""
        z = x[0]
        u, du = self.u(z)
        r0, dr0 = self.p("R0", z)
        return u - r0 * i - x[1] - x[2], np.array([[du - dr0 * i, -1.0, -1.0]]), -r0

    # ---------------------------------------------------------------- a particle cloud (PF)
    def f_cloud(self, X, i, dt):
        """``f`` on ``(N, 3)`` particles with per-particle currents ``i (N,)``."""
        z = X[:, 0]
        zp = np.clip(z, 0.0, 1.0)
        k = np.where(i >= 0, 1.0, self.eta) * dt / (3600.0 * self.q)
        out = np.empty_like(X)
        out[:, 0] = z - k * i
        for j, (r, c) in enumerate((("R1", "C1"), ("R2", "C2")), start=1):
            R, C = np.polyval(self.c[r], zp), np.polyval(self.c[c], zp)
            em = np.expm1(-dt / (R * C))
            out[:, j] = (em + 1.0) * X[:, j] - R * em * i
        return out

    def h_cloud(self, X, i):
        """``(y (N,), R0 (N,))`` of the particles."""
        z = X[:, 0]
        u = self.ocv(np.clip(z, self.z_lo, self.z_hi))
        u = np.where(z < self.z_lo, self.v_lo + self.s_lo * (z - self.z_lo), u)
        u = np.where(z > self.z_hi, self.v_hi + self.s_hi * (z - self.z_hi), u)
        r0 = np.polyval(self.c["R0"], np.clip(z, 0.0, 1.0))
        return u - r0 * i - X[:, 1] - X[:, 2], r0


class _DPEKF(ExtendedKalmanFilter):
    """filterpy's EKF whose ``predict_x`` applies the model (and sets ``F``, ``Q`` from its Jacobians)."""

    def __init__(self, model, var_i):
        super().__init__(dim_x=3, dim_z=1)
        self.model, self.var_i = model, var_i

    def predict_x(self, u=0):
        i, dt = u
        xn, self.F, B = self.model.f(self.x[:, 0], i, dt)
        self.Q = self.var_i * np.outer(B, B)
        self.x = xn[:, None]


def bare_ekf(model: BareDP, current, voltage, dt, soc0, P0, sigma_v, sigma_i) -> np.ndarray:
    """SOC estimates ``(T,)`` of one run: update with sample k, then predict to k + 1."""
    T = len(voltage)
    ekf = _DPEKF(model, sigma_i**2)
    ekf.x = np.array([[soc0], [0.0], [0.0]])
    ekf.P = np.array(P0, dtype=float)
    soc = np.empty(T)
    for k in range(T):
        i = current[k]
        r0 = model.p("R0", ekf.x[0, 0])[0]
        ekf.update(np.array([[voltage[k]]]), HJacobian=lambda x, i=i: model.h(x[:, 0], i)[1],
                   Hx=lambda x, i=i: np.array([[model.h(x[:, 0], i)[0]]]), R=sigma_v**2 + sigma_i**2 * r0 * r0)
        soc[k] = ekf.x[0, 0]
        if k + 1 < T:
            ekf.predict(u=(i, dt[k]))
    return soc


def bare_ukf(model: BareDP, current, voltage, dt, soc0, P0, sigma_v, sigma_i) -> np.ndarray:
    """SOC estimates ``(T,)`` of one run with filterpy's UKF (update with sample k, then predict)."""
    T = len(voltage)
    points = MerweScaledSigmaPoints(3, alpha=1.0, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(dim_x=3, dim_z=1, dt=1.0, points=points,
                                fx=lambda x, dt, i: model.f(x, i, dt)[0],
                                hx=lambda x, i: np.array([model.h(x, i)[0]]))
    ukf.x = np.array([soc0, 0.0, 0.0])
    ukf.P = np.array(P0, dtype=float)
    ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)  # the prior the first update transforms
    soc = np.empty(T)
    for k in range(T):
        i = current[k]
        r0 = model.p("R0", ukf.x[0])[0]
        ukf.update(voltage[k], R=sigma_v**2 + sigma_i**2 * r0 * r0, i=i)
        soc[k] = ukf.x[0]
        if k + 1 < T:
            B = model.f(ukf.x, i, dt[k])[2]
            ukf.Q = sigma_i**2 * np.outer(B, B)
            ukf.predict(dt=dt[k], i=i)
    return soc


def bare_pf(model: BareDP, current, voltage, dt, soc0, P0, sigma_v, sigma_i, n_particles=100, seed=0,
            roughening=0.2) -> np.ndarray:
    """SOC estimates ``(T,)`` of one run: bootstrap PF, numpy over the particles, filterpy's systematic resampling."""
    rng = np.random.default_rng(seed)
    T, N = len(voltage), n_particles
    X = np.array([soc0, 0.0, 0.0]) + rng.standard_normal((N, 3)) @ np.linalg.cholesky(P0).T
    w = np.full(N, 1.0 / N)
    soc = np.empty(T)
    for k in range(T):
        i = current[k]
        y, r0 = model.h_cloud(X, i)
        R = sigma_v**2 + sigma_i**2 * r0 * r0
        w = w * np.exp(-0.5 * (voltage[k] - y) ** 2 / R) / np.sqrt(R)
        w = w / np.sum(w) if np.sum(w) > 0 else np.full(N, 1.0 / N)
        soc[k] = w @ X[:, 0]
        if k + 1 == T:
            break
        if 1.0 / np.sum(w * w) < N / 2:
            X = X[systematic_resample(w)]
            w = np.full(N, 1.0 / N)
            X = X + roughening * np.ptp(X, axis=0) * N ** (-1.0 / 3) * rng.standard_normal((N, 3))
        X = model.f_cloud(X, i + sigma_i * rng.standard_normal(N), dt[k])
    return soc
