"""Square-root unscented Kalman filter (van der Merwe & Wan, ICASSP 2001, "The square-root unscented Kalman filter for
state and parameter-estimation", Algorithm 3.1), batched over runs.

The filter carries a lower-triangular square root ``L`` of the covariance (``P = L Lᵀ``) instead of ``P``; every
covariance it forms is ``L Lᵀ`` of some real ``L``, so it is symmetric and positive semi-definite by construction, with
no symmetrisation or PSD repair. Merwe scaled sigma points with ``γ = √(n + λ)`` (the UKF's α, β, κ and weights)::

    X_0 = x,  X_i = x + γ L[:, i−1],  X_{n+i} = x − γ L[:, i−1]                        i = 1 … n

For each sample k (prior ``x⁻, L⁻``; the first is ``x0, chol(P0)``)::

    update   X = σ(x⁻, L⁻),  Y_i = h(X_i, I_k),  ŷ = Σ Wm_i Y_i
             S = Σ Wc_i (Y_i − ŷ)² + R_k        (the square of the scalar qr/cholupdate of the paper: s_y = √S)
             P_xy = Σ Wc_i (X_i − x⁻)(Y_i − ŷ),  K = P_xy / S  (0 when gated),  x⁺ = x⁻ + K e
             L⁺ = cholupdate(L⁻, K √S, −1)                               (rank-one downdate: L⁺L⁺ᵀ = P⁻ − K S Kᵀ)
             SOC bound (project_soc), divergence check, record          (settle_update with factor=True)
    predict  X = σ(x⁺, L⁺),  X_i⁻ = f(X_i, I_k, dt_k),  x⁻ = Σ Wm_i X_i⁻
             L⁻ = qr([√Wc_1 (X_1⁻ − x⁻) … √Wc_2n (X_2n⁻ − x⁻) | √Q_k])ᵀ   (triangular factor of the stacked rows,
                                                                          diagonal made ≥ 0)
             L⁻ = cholupdate(L⁻, √|Wc_0| (X_0⁻ − x⁻), sign Wc_0)

``√Q_k`` is any ``M`` with ``M Mᵀ = Q_k``: here ``V √max(Λ, 0)`` from ``Q_k = V Λ Vᵀ``. The rank-one update of a lower
Cholesky factor by ``u`` with sign ``σ`` (:func:`cholupdate`; Golub & Van Loan §6.5.4) is, for j = 1 … n::

    r = √(L_jj² + σ u_j²),  c = r / L_jj,  s = u_j / L_jj,  L_jj = r
    L_{j+1:, j} = (L_{j+1:, j} + σ s u_{j+1:}) / c,   u_{j+1:} = c u_{j+1:} − s L_{j+1:, j}

In exact arithmetic the downdate keeps ``r² = L_jj² − u_j² > 0`` (the posterior is positive definite when ``R_k > 0``);
rounding can take it to or below zero on an ill-conditioned problem, where the plain UKF's ``P⁻ − K S Kᵀ`` loses
definiteness and needs the repair. Here ``r²`` is formed as ``(L_jj − u_j)(L_jj + u_j)`` (no cancellation of squares)
and kept at least ``psd_floor``, and a predicted factor's diagonal at least ``√psd_floor`` (a direction without any
spread, e.g. a discrete state); both are counted per run in ``info["downdate_floors"]``. So the factor stays real,
finite and invertible.

On a well-conditioned problem this is the UKF to rounding (same points, same weights, the same covariance written as a
product): ``tests`` check 1e-9. ``reference.ReferenceSRUKF`` is a per-run textbook implementation (scipy's QR).
"""

from __future__ import annotations

import numpy as np

from .base import scheduled_points_output, scheduled_step, settle_predict, settle_update
from .estimate import Estimate
from .ukf import UKF


def cholupdate(L: np.ndarray, u: np.ndarray, sign: float, floor: float = 0.0):
    """Rank-one update (``sign`` +1) or downdate (−1) of lower-triangular factors, batched: ``L (R, n, n)`` and
    ``u (R, n)`` → ``(L', floored (R,) bool)`` with ``L' L'ᵀ = L Lᵀ + sign·u uᵀ`` (module docstring). A pivot
    ``r²`` below ``floor`` is raised to it and flagged."""
    L = L.copy()
    u = u.copy()
    n = L.shape[-1]
    floored = np.zeros(L.shape[0], dtype=bool)
    for j in range(n):
        d = L[:, j, j]
        uj = u[:, j]
        r2 = d * d + uj * uj if sign > 0 else (d - uj) * (d + uj)
        low = r2 < floor
        floored |= low
        r = np.sqrt(np.where(low, floor, r2))
        c = r / d
        s = uj / d
        L[:, j, j] = r
        if j + 1 < n:
            col = (L[:, j + 1:, j] + sign * s[:, None] * u[:, j + 1:]) / c[:, None]
            u[:, j + 1:] = c[:, None] * u[:, j + 1:] - s[:, None] * col
            L[:, j + 1:, j] = col
    return L, floored


def psd_root(Q: np.ndarray) -> np.ndarray:
    """``M`` with ``M Mᵀ = Q`` for symmetric PSD ``Q (…, n, n)``: ``V √max(Λ, 0)``."""
    w, V = np.linalg.eigh(Q)
    return V * np.sqrt(np.maximum(w, 0.0))[..., None, :]


def qr_factor(rows: np.ndarray, floor: float = 0.0):
    """``(L, floored (R,) bool)``: lower-triangular ``L`` with ``L Lᵀ = rowsᵀ rows`` from the QR of ``rows (R, m, n)``
    (``m ≥ n``): ``L = Rᵀ`` with the rows of ``R`` sign-flipped where its diagonal is negative. A diagonal entry below
    ``√floor`` (a direction the sigma points and ``Q`` leave without spread, e.g. a discrete state) is raised to it, so
    the next :func:`cholupdate` never divides by zero; flagged."""
    Rf = np.linalg.qr(rows, mode="r")
    sgn = np.where(np.diagonal(Rf, 0, -2, -1) < 0, -1.0, 1.0)
    L = np.swapaxes(Rf * sgn[..., :, None], -1, -2)
    d = np.diagonal(L, 0, -2, -1)  # a read-only view
    low = d < np.sqrt(floor)
    if low.any():
        r, j = np.nonzero(low)
        L[r, j, j] = np.sqrt(floor)
    return L, low.any(axis=-1)


def sqrt_sigma_points(x: np.ndarray, L: np.ndarray, gamma: float) -> np.ndarray:
    """``(R, 2n+1, n)``: ``x``, ``x + γ L[:, i]``, ``x − γ L[:, i]``."""
    n = x.shape[-1]
    offsets = gamma * np.swapaxes(L, -1, -2)  # row i = column i of L
    X = np.empty(x.shape[:-1] + (2 * n + 1, n))
    X[..., 0, :] = x
    X[..., 1 : n + 1, :] = x[..., None, :] + offsets
    X[..., n + 1 :, :] = x[..., None, :] - offsets
    return X


class SRUKF(UKF):
    """Batched square-root UKF (Merwe scaled sigma points α, β, κ, like the UKF)."""

    name = "srukf"

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        m, opt, noise = self.model, self.options, self.noise
        R, T, n = inputs.n_runs, inputs.n, self.n
        Wm, Wc = self.Wm, self.Wc
        gamma = np.sqrt(n + self.lam)
        w_rest = np.sqrt(Wc[1:])  # every Wc_i, i ≥ 1, is 1/(2(n + λ)) > 0
        sign0, w0 = (1.0 if Wc[0] >= 0 else -1.0), np.sqrt(abs(Wc[0]))
        floor = opt["psd_floor"]
        x, L = x0.copy(), np.linalg.cholesky(P0)
        x_good, L_good = x.copy(), L.copy()
        rec = self.recorder(inputs, x0, P0)
        gate = self.gate(R)
        floors = np.zeros(R, dtype=int)
        with np.errstate(all="ignore"):
            for k in range(T):
                ik, tk = inputs.current[:, k], inputs.temp_at(k)
                ik_s = ik[:, None]
                tk_s = None if tk is None else tk[:, None]
                # ---------------------------------------------------------------- update
                X = sqrt_sigma_points(x, L, gamma)
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
                L, low = cholupdate(L, K * np.sqrt(S)[:, None], -1.0, floor)
                floors += low
                x, L = settle_update(rec, k, x, L, x_good, L_good, yhat, e, S, nis, gated, opt, factor=True)
                if k + 1 == T:
                    break
                # ---------------------------------------------------------------- predict
                X = sqrt_sigma_points(x, L, gamma)
                Xf, _, B = scheduled_step(m, X, x, ik_s, inputs.dt[k], tk_s, noise.needs_B)
                Q = noise.Q(None if B is None else B[:, 0], inputs.dt[k], inputs.hold_var[k])
                x = np.einsum("s,rsi->ri", Wm, Xf)
                dX = Xf - x[:, None, :]
                rows = np.concatenate([w_rest[:, None] * dX[:, 1:],
                                       np.swapaxes(np.broadcast_to(psd_root(Q), (R, n, n)), -1, -2)], axis=1)
                L, low_qr = qr_factor(rows, floor)
                L, low = cholupdate(L, w0 * dX[:, 0], sign0, floor)
                floors += low | low_qr
                settle_predict(rec, k + 1, x, L, x_good, L_good)
        return rec.finish(self.name, m, {"gate_threshold": gate.threshold, "lambda": self.lam,
                                         "downdate_floors": floors})
