"""Unscented Kalman filter with Merwe scaled sigma points, batched: runs × sigma points in one model call per step.

Sigma points of ``(x, P)`` in ``n`` dimensions (Van der Merwe 2004; filterpy's ``MerweScaledSigmaPoints``)::

    λ = α² (n + κ) − n,   L Lᵀ = (n + λ) P   (Cholesky)
    X_0 = x,   X_i = x + L[:, i−1],   X_{n+i} = x − L[:, i−1]                         i = 1 … n
    Wm_0 = λ/(n + λ),   Wc_0 = Wm_0 + 1 − α² + β,   Wm_i = Wc_i = 1/(2(n + λ))

For each sample k::

    update   X = σ(x⁻, P⁻),  Y_i = h(X_i, I_k)          ŷ = Σ Wm_i Y_i
             S = Σ Wc_i (Y_i − ŷ)² + R_k                 P_xy = Σ Wc_i (X_i − x⁻)(Y_i − ŷ)
             K = P_xy / S  (0 when gated)               x⁺ = x⁻ + K e,   P⁺ = P⁻ − K S Kᵀ
             symmetrise, PSD repair, clamp, divergence check
    predict  X = σ(x⁺, P⁺),  X_i⁻ = f(X_i, I_k, dt_k)   x⁻ = Σ Wm_i X_i⁻
             P⁻ = Σ Wc_i (X_i⁻ − x⁻)(X_i⁻ − x⁻)ᵀ + Q_k,  symmetrise, PSD repair

``R_k`` and ``Q_k`` come from ``D`` and ``B`` at the mean (sigma point 0), as in the EKF;
``socbench.kernels.filters.ukf`` is the same loop compiled (``engine`` option). The update draws fresh sigma
points from the prior, exactly as filterpy's ``UnscentedKalmanFilter.predict`` leaves them. Defaults α = 1, β = 2,
κ = 0 keep every weight but Wm_0 positive (small α makes Wc_0 ≈ −1/α², which breaks PSD on 2–5 state models).
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import Estimator, scheduled_points_output, scheduled_step, settle_predict, settle_update
from .estimate import Estimate
from .safety import repair_psd, symmetrise


def merwe_weights(n: int, alpha: float, beta: float, kappa: float):
    """``(λ, Wm (2n+1,), Wc (2n+1,))`` of the Merwe scaled sigma points."""
    lam = alpha**2 * (n + kappa) - n
    c = 0.5 / (n + lam)
    Wm = np.full(2 * n + 1, c)
    Wc = np.full(2 * n + 1, c)
    Wm[0] = lam / (n + lam)
    Wc[0] = lam / (n + lam) + (1.0 - alpha**2 + beta)
    return lam, Wm, Wc


def sigma_points(x: np.ndarray, P: np.ndarray, lam: float) -> np.ndarray:
    """``(…, 2n+1, n)`` sigma points; the offsets are the columns of the lower Cholesky factor of ``(n+λ)P``."""
    n = x.shape[-1]
    try:
        L = np.linalg.cholesky((n + lam) * P)
    except np.linalg.LinAlgError:  # only reachable after a failed repair: fall back to a symmetric square root
        w, V = np.linalg.eigh((n + lam) * P)
        L = V * np.sqrt(np.maximum(w, 0.0))[..., None, :]
    offsets = np.swapaxes(L, -1, -2)  # row i = column i of L
    X = np.empty(x.shape[:-1] + (2 * n + 1, n))
    X[..., 0, :] = x
    X[..., 1 : n + 1, :] = x[..., None, :] + offsets
    X[..., n + 1 :, :] = x[..., None, :] - offsets
    return X


class UKF(Estimator):
    """Batched unscented Kalman filter (Merwe scaled sigma points α, β, κ)."""

    name = "ukf"
    #: methods the compiled kernel implements (weights() only feeds it λ, Wm, Wc: a subclass may change those)
    kernel_hooks = ("points",)
    defaults = {"alpha": 1.0, "beta": 2.0, "kappa": 0.0}

    def __init__(self, model, noise=None, **options):
        super().__init__(model, noise, **options)
        self.lam, self.Wm, self.Wc = self.weights()

    def weights(self):
        """``(λ, Wm, Wc)`` of the Merwe scaled sigma points with this filter's α, β, κ."""
        n = self.n
        a, b, kp = self.options["alpha"], self.options["beta"], self.options["kappa"]
        if not a > 0 or not n + kp > 0:
            raise ConfigError(f"ukf: need alpha > 0 and n + kappa > 0 (n={n}, alpha={a}, kappa={kp})")
        return merwe_weights(n, a, b, kp)

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        m, opt, noise = self.model, self.options, self.noise
        R, T = inputs.n_runs, inputs.n
        Wm, Wc = self.Wm, self.Wc
        x, P = x0.copy(), P0.copy()
        x_good, P_good = x.copy(), P.copy()
        rec = self.recorder(inputs, x0, P0)
        gate = self.gate(R)
        floors = (opt["psd_floor"], opt["psd_rel_floor"])
        with np.errstate(all="ignore"):
            for k in range(T):
                ik, tk = inputs.current[:, k], inputs.temp_at(k)
                ik_s = ik[:, None]
                tk_s = None if tk is None else tk[:, None]
                # ---------------------------------------------------------------- update
                X = self.points(x, P)
                Y, _, D = scheduled_points_output(m, X, ik_s, tk_s, noise.needs_D)
                Rk = noise.R(None if D is None else D[:, 0], (R,))
                yhat = Y @ Wm
                dY = Y - yhat[:, None]
                S = (dY * dY) @ Wc + Rk
                Pxy = np.einsum("rsi,rs->ri", X - x[:, None, :], dY * Wc)
                e = inputs.voltage[:, k] - yhat
                nis = e * e / S
                gated = gate(nis)
                K = np.where(gated[:, None], 0.0, Pxy / S[:, None])
                x = x + K * e[:, None]
                P = P - S[:, None, None] * (K[:, :, None] * K[:, None, :])
                x, P = settle_update(rec, k, x, P, x_good, P_good, yhat, e, S, nis, gated, opt)
                if k + 1 == T:
                    break
                # ---------------------------------------------------------------- predict
                X = self.points(x, P)
                Xf, _, B = scheduled_step(m, X, x, ik_s, inputs.dt[k], tk_s, noise.needs_B)
                Q = noise.Q(None if B is None else B[:, 0], inputs.dt[k], inputs.hold_var[k])
                x = np.einsum("s,rsi->ri", Wm, Xf)
                dX = Xf - x[:, None, :]
                P = np.einsum("rsi,rsj->rij", dX * Wc[:, None], dX) + Q
                P, repaired = repair_psd(symmetrise(P), *floors)
                rec.psd_repairs += repaired & ~rec.failed
                settle_predict(rec, k + 1, x, P, x_good, P_good)
        return rec.finish(self.name, m, {"gate_threshold": gate.threshold, "lambda": self.lam})

    def points(self, x, P):
        """The sigma points of ``(x, P)``, ``(R, 2n+1, n)``: point 0 is the mean (``R_k``, ``Q_k`` are taken there)."""
        return sigma_points(x, P, self.lam)

    def _run_compiled(self, job, seed=None):
        from ..kernels.engine import parallel_runs
        from ..kernels.filters import ukf

        parallel_runs(ukf, job.R, *job.model_args, *job.noise_args, job.opt, self.Wm, self.Wc, float(self.lam),
                      bool(self.noise.needs_D), bool(self.noise.needs_B), *job.out_args)
        return job.finish({"gate_threshold": job.threshold, "lambda": self.lam})
