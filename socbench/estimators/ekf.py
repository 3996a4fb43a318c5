"""Extended Kalman filter, batched over Monte Carlo runs (one model call per step for the whole batch).

For each sample k (prior ``x⁻, P⁻``; the first prior is ``x0, P0``)::

    update   ŷ = h(x⁻, I_k)            H = ∂h/∂x,  D = ∂h/∂I        (one model.output(jac=True))
             R_k = σ_V² + σ_I² D²       S = H P⁻ Hᵀ + R_k            e = v_k − ŷ,  NIS = e²/S
             K = P⁻ Hᵀ / S               (K := 0 when the χ² gate rejects the sample)
             x⁺ = x⁻ + K e
             P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R_k Kᵀ                 (Joseph form: PSD for any K)
             symmetrise, PSD repair, clamp z to [0, 1], divergence check
    predict  x⁻ = f(x⁺, I_k, dt_k)      F = ∂f/∂x,  B = ∂f/∂I       (one model.step(jac=True), zero-order hold)
             Q_k = σ_I² B Bᵀ (+ walk)   P⁻ = F P⁺ Fᵀ + Q_k

This is filterpy's ``ExtendedKalmanFilter`` with a nonlinear ``predict_x``; ``reference.ReferenceEKF`` runs exactly
that class one trajectory at a time and the two agree to 1e-9. ``socbench.kernels.filters.ekf`` is the same loop
compiled (``engine`` option, :mod:`~socbench.estimators.base`).
"""

from __future__ import annotations

import numpy as np

from .base import Estimator, restore, settle_update
from .estimate import Estimate
from .safety import diverged, symmetrise


class EKF(Estimator):
    """Batched extended Kalman filter on any :class:`~socbench.models.base.Model`."""

    name = "ekf"

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        m, opt, noise = self.model, self.options, self.noise
        R, T, n = inputs.n_runs, inputs.n, self.n
        x, P = x0.copy(), P0.copy()
        x_good, P_good = x.copy(), P.copy()
        rec = self.recorder(inputs, x0, P0)
        gate = self.gate(R)
        eye = np.eye(n)
        with np.errstate(all="ignore"):
            for k in range(T):
                ik, tk = inputs.current[:, k], inputs.temp_at(k)
                # ---------------------------------------------------------------- update
                y, H, D = m.output(x, ik, tk, jac=True)
                Rk = noise.R(D, (R,))
                PHt = np.einsum("rij,rj->ri", P, H)
                S = np.einsum("ri,ri->r", H, PHt) + Rk
                e = inputs.voltage[:, k] - y
                nis = e * e / S
                gated = gate(nis)
                K = np.where(gated[:, None], 0.0, PHt / S[:, None])
                x = x + K * e[:, None]
                A = eye - K[:, :, None] * H[:, None, :]
                P = A @ P @ np.swapaxes(A, -1, -2) + Rk[:, None, None] * (K[:, :, None] * K[:, None, :])
                x, P = settle_update(rec, k, x, P, x_good, P_good, y, e, S, nis, gated, opt)
                if k + 1 == T:
                    break
                # ---------------------------------------------------------------- predict
                x, F, B = m.step(x, ik, inputs.dt[k], tk, jac=True)
                Q = noise.Q(B, inputs.dt[k])
                P = symmetrise(F @ P @ np.swapaxes(F, -1, -2) + Q)
                failed = rec.fail(k + 1, diverged(x, P, None, np.inf, np.inf))
                restore(x, x_good, failed)
                restore(P, P_good, failed)
                np.copyto(x_good, x, where=~failed[:, None])
                np.copyto(P_good, P, where=~failed[:, None, None])
        return rec.finish(self.name, m, {"gate_threshold": gate.threshold})

    def _run_compiled(self, job, seed=None):
        from ..kernels.engine import parallel_runs
        from ..kernels.filters import ekf

        parallel_runs(ekf, job.R, *job.model_args, *job.noise_args, job.opt, *job.out_args)
        return job.finish({"gate_threshold": job.threshold})
