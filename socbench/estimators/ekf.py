"""Extended Kalman filter, batched over Monte Carlo runs (one model call per step for the whole batch).

For each sample k (prior ``x⁻, P⁻``; the first prior is ``x0, P0``)::

    update   ŷ = h(x⁻, I_k)            H = ∂h/∂x,  D = ∂h/∂I        (one model.output(jac=True))
             R_k = σ_V² + σ_I² D²       S = H P⁻ Hᵀ + R_k            e = v_k − ŷ,  NIS = e²/S
             K = P⁻ Hᵀ / S               (K := 0 when the χ² gate rejects the sample)
             [gate_widen: where the gate releases (NIS > χ²_gate taken after gate_release rejections in a row),
              first P⁻_zz += max(0, e²/χ²_gate − S)/H_z² and S = e²/χ²_gate: safety.widen_on_release]
             x⁺ = x⁻ + K e
             P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R_k Kᵀ                 (Joseph form: PSD for any K)
             symmetrise, PSD repair, SOC bound (project_soc), divergence check
    predict  x⁻ = f(x⁺, I_k, dt_k)      F = ∂f/∂x,  B = ∂f/∂I       (one model.step(jac=True), zero-order hold)
             Q_k = σ_I² B Bᵀ (+ walk)   P⁻ = F P⁺ Fᵀ + Q_k

This is filterpy's ``ExtendedKalmanFilter`` with a nonlinear ``predict_x``; ``reference.ReferenceEKF`` runs exactly
that class one trajectory at a time and the two agree to 1e-9. ``socbench.kernels.filters.ekf`` is the same loop
compiled (``engine`` option, :mod:`~socbench.estimators.base`).
"""

from __future__ import annotations

import numpy as np

from .base import Estimator, scheduled_jacobian, scheduled_output, settle_predict, settle_update
from .estimate import Estimate
from .safety import symmetrise, widen_on_release


def kalman_update(x, P, H, Rk, S, e, gated):
    """The scalar-measurement Kalman update in Joseph form, batched over runs (module docstring): ``(x⁺, P⁺, K)``
    from the prior ``x (R, n)``, ``P (R, n, n)``, ``H (R, n)``, ``R_k (R,)``, ``S = H P Hᵀ + R_k (R,)``, the
    innovation ``e (R,)`` and the gate flags (``K = 0`` where gated)."""
    K = np.where(gated[:, None], 0.0, np.einsum("rij,rj->ri", P, H) / S[:, None])
    x = x + K * e[:, None]
    A = np.eye(x.shape[-1]) - K[:, :, None] * H[:, None, :]
    P = A @ P @ np.swapaxes(A, -1, -2) + Rk[:, None, None] * (K[:, :, None] * K[:, None, :])
    return x, P, K


def innovation_var(P, H, Rk):
    """``S = H P Hᵀ + R_k`` (R,)."""
    return np.einsum("ri,rij,rj->r", H, P, H) + Rk


class EKF(Estimator):
    """Batched extended Kalman filter on any :class:`~socbench.models.base.Model`."""

    name = "ekf"
    #: ``gate_widen``: where the gate releases, the SOC variance is widened first (:func:`~.safety.widen_on_release`;
    #: the compiled kernel does the same, kernels/filters.py)
    defaults = {"gate_widen": False}
    linearises_output = True  # a prior mean where the OCV is held flat is moved (base.out_of_held_ocv)
    #: methods the compiled kernel implements: a subclass overriding one runs numpy (kernels.engine.plan)
    kernel_hooks = ("process_cov", "measurement_update")

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        m, opt, noise = self.model, self.options, self.noise
        R, T = inputs.n_runs, inputs.n
        x, P = x0.copy(), P0.copy()
        x_good, P_good = x.copy(), P.copy()
        rec = self.recorder(inputs, x0, P0)
        gate = self.gate(R)
        with np.errstate(all="ignore"):
            for k in range(T):
                ik, tk = inputs.current[:, k], inputs.temp_at(k)
                # ---------------------------------------------------------------- update
                y, H, D = scheduled_output(m, x, ik, tk)
                Rk = noise.R(D, (R,))
                e = inputs.voltage[:, k] - y
                S = innovation_var(P, H, Rk)
                nis = e * e / S
                gated = gate(nis)
                if opt["gate_widen"]:
                    P, S = widen_on_release(P, H, S, e, nis, gated, gate.threshold)
                x, P = self.measurement_update(x, P, H, Rk, S, e, gated, inputs.voltage[:, k], ik, tk)
                x, P = settle_update(rec, k, x, P, x_good, P_good, y, e, S, nis, gated, opt)
                if k + 1 == T:
                    break
                # ---------------------------------------------------------------- predict
                x, F, B = m.step(x, ik, inputs.dt[k], tk, jac=True)
                F = scheduled_jacobian(m, F)
                Q = self.process_cov(x, B, inputs.dt[k], inputs.hold_var[k])
                P = symmetrise(F @ P @ np.swapaxes(F, -1, -2) + Q)
                settle_predict(rec, k + 1, x, P, x_good, P_good)
        return rec.finish(self.name, m, {"gate_threshold": gate.threshold})

    def measurement_update(self, x, P, H, Rk, S, e, gated, v, i, temp):
        """``(x⁺, P⁺)`` from the prior ``x, P`` linearised there (``H, R_k, S, e``; module docstring); ``v, i, temp``
        the sample, for subclasses that linearise again (:class:`~socbench.estimators.iekf.IteratedEKF`)."""
        x, P, _ = kalman_update(x, P, H, Rk, S, e, gated)
        return x, P

    def process_cov(self, x, B, dt, hold_var=0.0):
        """``Q_k`` of the step from the posterior: the sensor model's (subclasses add their own terms); ``hold_var``
        the current variance the hold misses over the step (:class:`~.base.Inputs`)."""
        return self.noise.Q(B, dt, hold_var)

    def _run_compiled(self, job, seed=None):
        from ..kernels.filters import VAR_EKF

        job.kalman(VAR_EKF)
        return job.finish({"gate_threshold": job.threshold})
