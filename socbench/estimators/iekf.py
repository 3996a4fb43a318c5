"""Iterated extended Kalman filter: the EKF with its measurement update linearised again at the corrected state.

The EKF linearises ``h`` once, at the prior mean. Far from the truth (a start 20 SOC points off, where the OCV curve
bends) that one step lands where the prior's slope points, not where the measurement does, and the band it leaves is
already narrow. The iterated update is Gauss–Newton on the maximum a posteriori state of the prior and the sample
(Bell & Cathey, IEEE Trans. Autom. Control 38(2), 1993). For each sample k (prior ``x⁻, P⁻``)::

    x⁽⁰⁾ = x⁻;  H₀, R₀, S₀, e₀ = the EKF's (innovation, NIS and the χ² gate are the prior's, as in the EKF)
    for j = 0 … J − 1:
        ŷ_j = h(x⁽ʲ⁾, I_k),  H_j = ∂h/∂x (x⁽ʲ⁾),  D_j = ∂h/∂I      (parameter scheduling as in the EKF)
        R_j = σ_V² + σ_I² D_j²,   S_j = H_j P⁻ H_jᵀ + R_j,   K_j = P⁻ H_jᵀ / S_j
        x⁽ʲ⁺¹⁾ = x⁻ + K_j (v_k − ŷ_j − H_j (x⁻ − x⁽ʲ⁾))
        stop when max |x⁽ʲ⁺¹⁾ − x⁽ʲ⁾| ≤ ``iteration_tol``        (each x⁽ʲ⁾'s SOC clipped to [0, 1] first)
    x⁺ = x⁽ᴶ⁾,  P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ   with the last K, H, R (Joseph form)

``iterations = 1`` is the EKF exactly. The prediction is the EKF's. Numpy engine only (the compiled EKF kernel
linearises once: :func:`socbench.kernels.engine.plan` says so in ``Estimate.info["engine_note"]``).
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import scheduled_output
from .ekf import EKF, innovation_var, kalman_update


class IteratedEKF(EKF):
    """The EKF with an iterated (re-linearised) measurement update."""

    name = "iekf"
    defaults = {**EKF.defaults, "iterations": 5, "iteration_tol": 1e-9}

    def __init__(self, model, noise=None, **options):
        super().__init__(model, noise, **options)
        it = self.options["iterations"]
        if isinstance(it, bool) or not isinstance(it, (int, np.integer)) or it < 1:
            raise ConfigError(f"iekf: iterations must be an integer >= 1, got {it!r}")
        if not self.options["iteration_tol"] >= 0:
            raise ConfigError(f"iekf: iteration_tol must be >= 0, got {self.options['iteration_tol']!r}")

    def measurement_update(self, x, P, H, Rk, S, e, gated, v, i, temp):
        """The iterated update of the module docstring (``H, R_k, S, e``: the prior's linearisation, iteration 0)."""
        xj, Pj, _ = kalman_update(x, P, H, Rk, S, e, gated)
        active = ~gated
        for _ in range(1, int(self.options["iterations"])):
            if not active.any():
                break
            # linearised inside the SOC range: a step past full or empty (where the output's slope is held flat)
            # would leave nothing to iterate on
            xj = np.concatenate([np.clip(xj[:, :1], 0.0, 1.0), xj[:, 1:]], axis=1)
            y, Hj, D = scheduled_output(self.model, xj, i, temp)
            Rj = self.noise.R(D, (x.shape[0],))
            ej = v - y - np.einsum("ri,ri->r", Hj, x - xj)
            xn, Pn, _ = kalman_update(x, P, Hj, Rj, innovation_var(P, Hj, Rj), ej, ~active)
            moved = np.max(np.abs(xn - xj), axis=-1)
            xj = np.where(active[:, None], xn, xj)
            Pj = np.where(active[:, None, None], Pn, Pj)
            active &= moved > self.options["iteration_tol"]
        return xj, Pj
