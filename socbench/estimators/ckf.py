"""Cubature Kalman filter (Arasaratnam & Haykin, IEEE Trans. Automatic Control 54(6):1254–1269, 2009), batched.

The third-degree spherical–radial cubature rule approximates a Gaussian integral with ``2n`` equally weighted points
on the axes of the covariance's square root::

    ξ_i = √n e_i,  ξ_{n+i} = −√n e_i   (i = 1 … n),   X_i = x + L ξ_i   (L Lᵀ = P, Cholesky),   w_i = 1/(2n)

For each sample k (the filter of the paper, Algorithm 1, with a scalar measurement)::

    update   X = cubature points of (x⁻, P⁻),  Y_i = h(X_i, I_k)        ŷ = Σ w_i Y_i
             S = Σ w_i (Y_i − ŷ)² + R_k                                  P_xy = Σ w_i (X_i − x⁻)(Y_i − ŷ)
             K = P_xy / S (0 when gated),  x⁺ = x⁻ + K e,  P⁺ = P⁻ − K S Kᵀ
             symmetrise, PSD repair, clamp, divergence check              (the UKF's safety tail)
    predict  X = cubature points of (x⁺, P⁺),  X_i⁻ = f(X_i, I_k, dt_k)   x⁻ = Σ w_i X_i⁻
             P⁻ = Σ w_i (X_i⁻ − x⁻)(X_i⁻ − x⁻)ᵀ + Q_k,  symmetrise, PSD repair

These are exactly the unscented transform's formulas with ``λ = α²(n + κ) − n = 0`` (α = 1, κ = 0) and β = 0: the
offsets are ``±√(n + λ) L = ±√n L`` and the weights ``Wm_0 = Wc_0 = 0``, ``W_i = 1/(2n)``. So this filter is the
batched :class:`~.ukf.UKF` loop with those points. The centre point carries zero weight: it only evaluates ``B`` and
``D`` at the mean, from which ``Q_k`` and ``R_k`` come (as in the UKF, and as the filterpy reference takes them).
All weights are positive, so, unlike a UKF with small α, the covariance sums cannot lose definiteness by themselves.

``reference.ReferenceCKF`` runs filterpy's ``CubatureKalmanFilter`` one trajectory at a time; they agree to 1e-9.
"""

from __future__ import annotations

from .ukf import UKF, merwe_weights


class CKF(UKF):
    """Batched cubature Kalman filter (no tuning parameters)."""

    name = "ckf"
    defaults = {}

    def weights(self):
        """The cubature rule as Merwe weights: ``λ = 0``, ``Wm_0 = Wc_0 = 0``, ``W_i = 1/(2n)``."""
        return merwe_weights(self.n, 1.0, 0.0, 0.0)
