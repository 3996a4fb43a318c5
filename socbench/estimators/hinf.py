"""Extended H∞ filter (game-theoretic form of Simon, "Optimal State Estimation", Wiley 2006, §11.3, eq. 11.89), as
used for SOC by Zhang, Liu, Fang & Wang (IEEE Trans. Industrial Electronics 59(2):1086–1095, 2012) and by Chen, Xiong
& Shen (IEEE Trans. Power Electronics 33(1):332–342, 2018, the SOC half of their dual H∞ filter), batched over runs.

The filter bounds the worst-case ratio of the weighted estimation error to the energies of the initial error, the
process noise and the measurement noise, whatever their statistics: with the performance bound ``θ = 1/γ``
(``γ`` the attenuation level) and the error weight ``S̄ = Lᵀ S L`` (here ``L = I`` and ``S = diag(1, 0, …)``: the
bound is on the SOC error, option ``weight="soc"``; ``weight="all"`` weighs every state, ``S̄ = I``). For each sample k
(``H, D`` and ``F, B`` the model's Jacobians at the prior and the posterior, like the EKF)::

    update   e = v_k − h(x⁻, I_k),   R_k = σ_V² + σ_I² D²,   S = H P⁻ Hᵀ + R_k,   NIS = e²/S   (χ² gate as the EKF)
             A = I − θ S̄ P⁻ + Hᵀ R_k⁻¹ H P⁻
             feasible iff  P⁻⁻¹ − θ S̄ + Hᵀ R_k⁻¹ H ≻ 0   ⇔   P⁺ = P⁻ A⁻¹ is symmetric positive definite
             K = P⁻ A⁻¹ Hᵀ R_k⁻¹ = P⁺ Hᵀ / R_k  (0 when gated),   x⁺ = x⁻ + K e
             symmetrise, PSD repair, clamp z to [0, 1], divergence check   (the EKF's safety tail)
    predict  x⁻ = f(x⁺, I_k, dt_k),   P⁻ = F P⁺ Fᵀ + Q_k                   (Q_k from the sensor model, as the EKF)

With ``θ = 0`` this is exactly the EKF (``P⁺ = (P⁻⁻¹ + HᵀR⁻¹H)⁻¹``, ``K`` the Kalman gain). ``θ > 0`` keeps ``P``,
hence the gain, larger than the Kalman filter's: the estimate leans more on the voltage, which is what protects it
against model and noise errors that the covariances do not describe.

**Riccati feasibility.** The bound ``θ`` is achievable at a step only when the matrix above is positive definite. Where
it is not (``P⁺`` not positive definite, checked without an eigen-decomposition by ``safety.psd_certified``), that
run's ``θ`` is halved for this step, up to ``theta_halvings`` times, and then set to 0 (the Kalman update, always
feasible); the count per run is ``info["theta_reductions"]``. ``P`` here is not a covariance but the Riccati matrix of
the game; the reported ``soc_std = √P[0, 0]`` is therefore an upper-bound-style spread, and the NEES is read with
that in mind.

``reference.ReferenceHInf`` is the same recursion written per run with ``numpy.linalg.inv`` (Simon's equations as
printed); they agree to 1e-9.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import Estimator, settle_predict, settle_update
from .ekf import innovation_var
from .estimate import Estimate
from .safety import psd_certified, symmetrise


def hinf_posterior(P, H, Rk, weight, theta, halvings: int, floors):
    """``(P⁺ (R, n, n), θ used (R,), reductions (R,))``: ``P⁺ = P (I − θ S̄ P + Hᵀ R⁻¹ H P)⁻¹`` with ``θ`` halved
    per run until ``P⁺`` is positive definite (then 0 after ``halvings`` tries; module docstring)."""
    R, n = H.shape
    HtH = (H[:, :, None] * H[:, None, :]) / Rk[:, None, None]
    eye = np.eye(n)
    th = np.full(R, float(theta))
    reductions = np.zeros(R, dtype=int)
    todo = np.ones(R, dtype=bool)
    Pp = np.empty_like(P)
    for attempt in range(halvings + 2):
        A = eye - th[todo, None, None] * (weight @ P[todo]) + HtH[todo] @ P[todo]
        Pt = symmetrise(np.swapaxes(np.linalg.solve(np.swapaxes(A, -1, -2), P[todo]), -1, -2))  # P A⁻¹ (P = Pᵀ)
        ok = psd_certified(Pt, *floors) | (th[todo] == 0.0)
        idx = np.flatnonzero(todo)
        Pp[idx[ok]] = Pt[ok]
        todo[idx[ok]] = False
        if not todo.any():
            break
        reductions[todo] += 1
        th[todo] = th[todo] * 0.5 if attempt < halvings else 0.0
    return Pp, th, reductions


class HInfinityFilter(Estimator):
    """Batched extended H∞ filter with a per-step Riccati feasibility check."""

    name = "hinf"
    defaults = {"theta": 1e3, "weight": "soc", "theta_halvings": 20}

    def __init__(self, model, noise=None, **options):
        super().__init__(model, noise, **options)
        o = self.options
        if not (np.isfinite(o["theta"]) and o["theta"] >= 0):
            raise ConfigError(f"hinf: theta must be a finite number >= 0 (1/γ), got {o['theta']!r}")
        if o["weight"] not in ("soc", "all"):
            raise ConfigError(f"hinf: weight must be 'soc' or 'all', got {o['weight']!r}")
        if int(o["theta_halvings"]) < 0:
            raise ConfigError("hinf: theta_halvings must be >= 0")
        self.weight = np.eye(self.n) if o["weight"] == "all" else np.diag([1.0] + [0.0] * (self.n - 1))

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        m, opt, noise = self.model, self.options, self.noise
        R, T = inputs.n_runs, inputs.n
        floors = (opt["psd_floor"], opt["psd_rel_floor"])
        x, P = x0.copy(), P0.copy()
        x_good, P_good = x.copy(), P.copy()
        rec = self.recorder(inputs, x0, P0)
        gate = self.gate(R)
        reductions = np.zeros(R, dtype=int)
        with np.errstate(all="ignore"):
            for k in range(T):
                ik, tk = inputs.current[:, k], inputs.temp_at(k)
                # ---------------------------------------------------------------- update
                y, H, D = m.output(x, ik, tk, jac=True)
                Rk = noise.R(D, (R,))
                e = inputs.voltage[:, k] - y
                S = innovation_var(P, H, Rk)
                nis = e * e / S
                gated = gate(nis)
                Pp, _, red = hinf_posterior(P, H, Rk, self.weight, opt["theta"], int(opt["theta_halvings"]), floors)
                reductions += red & ~gated
                K = np.where(gated[:, None], 0.0, np.einsum("rij,rj->ri", Pp, H) / Rk[:, None])
                x = x + K * e[:, None]
                P = np.where(gated[:, None, None], P, Pp)
                x, P = settle_update(rec, k, x, P, x_good, P_good, y, e, S, nis, gated, opt)
                if k + 1 == T:
                    break
                # ---------------------------------------------------------------- predict
                x, F, B = m.step(x, ik, inputs.dt[k], tk, jac=True)
                P = symmetrise(F @ P @ np.swapaxes(F, -1, -2) + noise.Q(B, inputs.dt[k]))
                settle_predict(rec, k + 1, x, P, x_good, P_good)
        return rec.finish(self.name, m, {"gate_threshold": gate.threshold, "theta": opt["theta"],
                                         "theta_reductions": reductions})
