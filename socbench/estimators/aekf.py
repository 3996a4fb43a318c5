"""Adaptive extended Kalman filter: the EKF with Sage–Husa noise estimation in its fading-memory (forgetting-factor)
form, batched over runs.

Sage & Husa ("Adaptive filtering with unknown prior statistics", Proc. JACC 1969) estimate the measurement and process
noise covariances recursively from the innovations; SOC papers use it on the EKF/UKF (e.g. Sun, Hu, Zou & Li, Energy
36(5):3531–3540, 2011). The variant here, with forgetting factor ``b`` (``d = 1 − b``: memory ≈ 1/d samples)::

    update   EKF update with R̂:  S = H P⁻ Hᵀ + R̂_{k−1},  e = v_k − h(x⁻),  K = P⁻ Hᵀ / S,  x⁺, P⁺ (Joseph)
             where the sample is not gated (and the run not failed):
             R̂_k = (1 − d) R̂_{k−1} + d (e² − H P⁻ Hᵀ)                                  Sage–Husa R
                   if that is below the floor: R̂_k = (1 − d) R̂_{k−1} + d e²            (its biased, positive form)
                   then R̂_k clipped to [r_min_ratio, r_max_ratio] × R_k              (R_k = σ_V² + σ_I² D², the
                                                                                      sensor model's value)
             Q̂_k = (1 − d) Q̂_{k−1} + d K e² Kᵀ                                        Sage–Husa Q without its
                                                                                      P_k − F P_{k−1} Fᵀ term
    predict  P⁻ = F P⁺ Fᵀ + Q_k + Q̂_k                                                  (Q_k the sensor model's)

Which variant and why (the stability safeguards):

* **Fading memory, constant d.** Sage–Husa's own weight ``d_k = (1 − b)/(1 − b^{k+1})`` trusts the first innovations
  fully (``d_0 = 1``); after a 20-point initial SOC error those are the convergence transient, and ``Q̂`` would jump by
  orders of magnitude. Here the estimates start from the sensor model (``R̂ = R_0``, ``Q̂ = 0``) and forget at the
  constant rate ``d = 1 − b``.
* **R̂ first: the prior S.** The gain, the χ² gate and the reported ``innovation_var`` use ``R̂_{k−1}``: the innovation
  is scored against what the filter expected before seeing it (a self-including ``R̂_k`` would pull NIS toward 1 by
  construction).
* **Positive R̂.** ``e² − H P⁻ Hᵀ`` is negative whenever the innovation is smaller than the predicted spread;
  Sage–Husa's unbiased estimate then loses positivity. The switch to the biased form and the clip to a band around the
  sensor model's ``R_k`` keep it positive and bounded.
* **PSD Q̂.** The full Sage–Husa process-noise estimate ``K e eᵀ Kᵀ + P_k − F P_{k−1} Fᵀ`` is not positive
  semi-definite in general (the classic divergence of the adaptive filter); without the last two terms it is the
  covariance-matching estimate of Mohamed & Schwarz (J. Geodesy 73:193–203, 1999), a convex combination of rank-one
  PSD terms: PSD by construction. It is added to the sensor model's ``Q_k`` (what the model leaves unexplained), never
  replaces it.
* **Gated samples and failed runs do not adapt**: an outlier the gate rejects does not inflate the noise estimates.
* **Q adaptation is off by default** (``adapt_q=False``). On the flight scenarios the model error sits in the voltage
  map (hysteresis, an offset current): letting Q̂ grow makes the SOC follow the voltage and raised the SOC RMSE 3–5×
  over the R-only filter (docs/estimators.md), while R-only adaptation brought the NIS near 1 and the SOC RMSE at or
  below the EKF's. ``adapt_q=True`` switches it on.

``info["r_hat"]`` and ``info["q_hat_soc"]`` hold the final estimates per run. ``reference.ReferenceAEKF`` is the same
recursion written per run (plain numpy, one trajectory at a time); they agree to 1e-9.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import Estimator, scheduled_jacobian, scheduled_output, settle_predict, settle_update
from .ekf import innovation_var, kalman_update
from .estimate import Estimate
from .safety import symmetrise, widen_on_release


def sage_husa_r(r_hat, e, HPHt, d, r_nom, r_min_ratio, r_max_ratio):
    """The fading-memory Sage–Husa measurement-noise estimate with its positivity safeguards (module docstring)."""
    r = (1.0 - d) * r_hat + d * (e * e - HPHt)
    low = r < r_min_ratio * r_nom
    r = np.where(low, (1.0 - d) * r_hat + d * e * e, r)
    return np.clip(r, r_min_ratio * r_nom, r_max_ratio * r_nom)


class AdaptiveEKF(Estimator):
    """Batched EKF with fading-memory Sage–Husa estimation of R and Q."""

    name = "aekf"
    linearises_output = True  # a prior mean where the OCV is held flat is moved (base.out_of_held_ocv)
    defaults = {"forgetting": 0.99, "adapt_r": True, "adapt_q": False, "r_min_ratio": 0.1, "r_max_ratio": 1e4,
                "gate_widen": False}

    def __init__(self, model, noise=None, **options):
        super().__init__(model, noise, **options)
        o = self.options
        if not 0.0 < o["forgetting"] < 1.0:
            raise ConfigError(f"aekf: forgetting must be in (0, 1), got {o['forgetting']!r}")
        if not 0.0 < o["r_min_ratio"] <= 1.0 <= o["r_max_ratio"]:
            raise ConfigError("aekf: need 0 < r_min_ratio <= 1 <= r_max_ratio")

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        m, opt, noise = self.model, self.options, self.noise
        R, T, n = inputs.n_runs, inputs.n, self.n
        d = 1.0 - opt["forgetting"]
        lo, hi = opt["r_min_ratio"], opt["r_max_ratio"]
        x, P = x0.copy(), P0.copy()
        x_good, P_good = x.copy(), P.copy()
        rec = self.recorder(inputs, x0, P0)
        gate = self.gate(R)
        r_hat = None
        q_hat = np.zeros((R, n, n))
        with np.errstate(all="ignore"):
            for k in range(T):
                ik, tk = inputs.current[:, k], inputs.temp_at(k)
                # ---------------------------------------------------------------- update
                y, H, D = scheduled_output(m, x, ik, tk)
                r_nom = noise.R(D, (R,))
                if r_hat is None:
                    r_hat = r_nom.copy()
                Rk = r_hat if opt["adapt_r"] else r_nom
                e = inputs.voltage[:, k] - y
                S = innovation_var(P, H, Rk)
                nis = e * e / S
                gated = gate(nis)
                if opt["gate_widen"]:
                    P, S = widen_on_release(P, H, S, e, nis, gated, gate.threshold)
                HPHt = S - Rk
                x, P, K = kalman_update(x, P, H, Rk, S, e, gated)
                x, P = settle_update(rec, k, x, P, x_good, P_good, y, e, S, nis, gated, opt)
                # ---------------------------------------------------------------- noise estimates
                adapt = ~gated & ~rec.failed
                r_new = sage_husa_r(r_hat, e, HPHt, d, r_nom, lo, hi)
                r_hat = np.where(adapt, r_new, r_hat)
                Ke = K * e[:, None]
                q_new = (1.0 - d) * q_hat + d * (Ke[:, :, None] * Ke[:, None, :])
                q_hat = np.where(adapt[:, None, None], q_new, q_hat)
                if k + 1 == T:
                    break
                # ---------------------------------------------------------------- predict
                x, F, B = m.step(x, ik, inputs.dt[k], tk, jac=True)
                F = scheduled_jacobian(m, F)
                Q = noise.Q(B, inputs.dt[k], inputs.hold_var[k])
                if opt["adapt_q"]:
                    Q = Q + q_hat
                P = symmetrise(F @ P @ np.swapaxes(F, -1, -2) + Q)
                settle_predict(rec, k + 1, x, P, x_good, P_good)
        return rec.finish(self.name, m, {"gate_threshold": gate.threshold, "forgetting": opt["forgetting"],
                                         "r_hat": r_hat, "q_hat_soc": q_hat[:, 0, 0].copy()})

    def _run_compiled(self, job, seed=None):
        from ..kernels.filters import VAR_AEKF

        o = self.options
        vout = job.kalman(VAR_AEKF, (1.0 - o["forgetting"], o["r_min_ratio"], o["r_max_ratio"], float(o["adapt_r"]),
                                     float(o["adapt_q"])))
        return job.finish({"gate_threshold": job.threshold, "forgetting": o["forgetting"], "r_hat": vout[:, 0].copy(),
                           "q_hat_soc": vout[:, 1].copy()})
