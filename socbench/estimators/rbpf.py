"""Rao–Blackwellised (marginalised) particle filter: particles on the SOC, one Kalman filter for every other state.

An ECM is nonlinear in the SOC (the OCV curve) and linear in everything else once its parameters are looked up: the
RC voltages, the hysteresis state, the noise recipe's coloured model-error states ``ε``. The marginalised particle
filter (Schön, Gustafsson & Nordlund, IEEE Trans. Signal Process. 53(7), 2005) samples only the nonlinear part and
carries the linear part ``x_L`` of each particle in closed form: particle ``j`` is ``(z_j, m_j, w_j)``, the SOC, the
conditional mean of ``x_L`` and the weight. The parameters are looked up at the particles' mean SOC ``z̄`` (the
scheduling of :func:`~socbench.estimators.base.scheduled_output`), so the linear part's matrices ``A, B_L, H_L`` are
the same for every particle and its conditional covariance ``P_L`` is one per run. For each sample k::

    update   Y_j = h([z̄, m_j], I_k) + E(z_j) − E(z̄)           (E the equilibrium curve; output at the mean's parameters)
             H_L = ∂h/∂x_L at [z̄, m̄],  R_k = σ_V² + σ_I² D²,  S_c = H_L P_L H_Lᵀ + R_k    (one per run)
             ŷ = Σ w_j Y_j,   S = Σ w_j (Y_j − ŷ)² + S_c,   e = v_k − ŷ,   NIS = e²/S     (the mixture's)
             where the χ² gate passes:
               w_j ← w_j · N(v_k; Y_j, S_c) / Σ(…)      (in tempered stages with resampling and the shrinkage kernel
                                                        between them where it would leave N_eff < temper_threshold·N:
                                                        progressive correction, as the bootstrap PF's ``assimilate``)
               K = P_L H_Lᵀ / S_c,   m_j ← m_j + K (v_k − Y_j),   P_L ← (I − K H_L) P_L (I − K H_L)ᵀ + K R_k Kᵀ
             report ẑ = Σ w_j z_j,  σ_z² = Σ w_j (z_j − ẑ)²;  x̄_L = Σ w_j m_j,  var = diag P_L + Σ w_j (m_j − x̄_L)²
    resample where N_eff = 1/Σ w_j² < threshold·N: systematic (as the PF), then the shrinkage kernel on the pairs
             (z_j, m_j): a·X_j + (1 − a)·X̄ + h·V^½·ε, a = √(1 − h²), X̄ and V the weighted mean and covariance before
             resampling (Liu & West 2001: the cloud's mean, spread and SOC–state correlation kept, duplicates distinct)
    predict  I_j = I_k + σ_I ε_j                                     (the sensor's current noise, sampled per particle)
             [z̄ + Δz_j, m_j⁺] = f([z̄, m_j], I_j, dt_k)               (one step at the mean's parameters)
             z_j ← z_j + Δz_j + √q_z ε'_j (+ σ_hold·B̄_z ε''_j),   z_j clamped to [0, 1]
             P_L ← A P_L Aᵀ + Q_L (+ σ_hold²·diag(B̄_L²)),   A = ∂f_L/∂x_L at [z̄, m̄]
             (the bracketed terms across a logger pause only: the current the hold misses, σ_hold² =
             ``Inputs.hold_var``, B̄ = ∂f/∂I at the mean; each state on its own, as ``noise.hold_cov``)

Conditioned on the sampled current noise the linear states move deterministically (``m_j⁺ = A m_j + B_L I_j``), so
``Q_L`` holds only their own random walks (the recipe's coloured-error states); ``q_z`` is the SOC's walk. A ``Q``
override array splits the same way (its SOC–state cross terms are left out). For a model whose other states are not
linear, the update and prediction of ``P_L`` are the EKF's linearisation at the mean.

Why it exists: the bootstrap PF (:mod:`~socbench.estimators.pf`) cannot carry the recipe's coloured states (its
near-deterministic dimensions collapse onto a few particles), so it takes the model error as white noise and its
band is far too narrow where the error persists. Here the coloured states sit in the Kalman part, as in the EKF, and
the particles resolve one dimension. Numpy engine only. Random numbers are the PF's counter-based draws
(:mod:`socbench.estimators.draws`).

What it does not do (measured in docs/estimators.md, its current-bias scenario): like every particle filter, its spread
depends on the data. Under a model that is wrong in a way its noise does not describe (a constant current-sensor
offset declared as white noise), reweighting concentrates the cloud and the SOC follows the voltage more slowly than
the EKF's, whose covariance never looks at the data.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import Estimator, equilibrium, restore
from .draws import StepDraws
from .estimate import Estimate
from .noise import hold_cov
from .pf import (
    _clamp_particles,
    cloud_moments,
    log_likelihood,
    progressive_correction,
    resample_degenerate,
)
from .safety import diverged, symmetrise


class RaoBlackwellPF(Estimator):
    """Batched marginalised particle filter: SOC particles, a shared-covariance Kalman filter for the other states."""

    name = "rbpf"
    defaults = {"n_particles": 200, "resample_threshold": 0.5, "kernel_h": 0.3, "max_stages": 8,
                "temper_threshold": 0.2, "temper_h": 0.5}

    def __init__(self, model, noise=None, **options):
        super().__init__(model, noise, **options)
        o = self.options
        if int(o["n_particles"]) < 2:
            raise ConfigError("rbpf: n_particles must be >= 2")
        if not 0 <= o["resample_threshold"] <= 1:
            raise ConfigError("rbpf: resample_threshold must be in [0, 1] (a fraction of n_particles)")
        if not 0 <= o["kernel_h"] < 1 or not 0 <= o["temper_h"] < 1:
            raise ConfigError("rbpf: kernel_h and temper_h must be in [0, 1)")
        if callable(self.noise.Q_override):
            raise ConfigError("rbpf: Q must be an (n, n) array for the particle filter (no callable)")
        self.n_particles = int(o["n_particles"])

    def _walks(self, R: int, dt):
        """``(q_z (R,), Q_L (R, n−1, n−1))``: the SOC's walk variance and the linear states' process noise of a step
        (the current noise is sampled, so neither holds it; a Q override: its diagonal block and its SOC entry)."""
        Q = np.broadcast_to(self.noise.Q(np.zeros((R, self.n)), dt), (R, self.n, self.n))
        return Q[:, 0, 0], Q[:, 1:, 1:]

    def _outputs(self, X, zbar, i, temp, temp_p):
        """``Y_j = h([z̄, m_j], I) + E(z_j) − E(z̄)`` (R, N): each particle's output at the mean's parameters."""
        Xs = X.copy()
        Xs[..., 0] = zbar[:, None]
        return (self.model.output(Xs, i[:, None], temp_p, jac=False)[0] + equilibrium(self.model, X[..., 0], temp_p)[0]
                - equilibrium(self.model, zbar, temp)[0][:, None])

    def _weigh(self, X, w, Y, Sc, gated, v, zbar, i, temp, temp_p, stage_draws):
        """Weights ``w ∝ w·N(v; Y_j, S_c)`` for the rows not gated, by the particle filters' progressive correction
        (:func:`~socbench.estimators.pf.progressive_correction`: tempered stages where the full likelihood would leave
        too few effective particles, the kernel on ``(z, m)`` between them, the moved particles' outputs evaluated
        again). A far-off start otherwise leaves a few particles, a cloud narrower than the posterior, that the SOC's
        small process noise never widens again. Returns ``(X, w, Y, stages (R,))``."""
        Y = Y.copy()

        def relikelihood(part, Xp):
            tp = None if temp is None else temp[part]
            Y[part] = self._outputs(Xp, zbar[part], i[part], tp, None if tp is None else tp[:, None])
            return log_likelihood(v[part][:, None], Y[part], Sc[part][:, None])

        X, w, stages = progressive_correction(X, w, log_likelihood(v[:, None], Y, Sc[:, None]), gated, self.options,
                                              stage_draws, relikelihood)
        return X, w, Y, stages

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        m, opt, noise = self.model, self.options, self.noise
        R, T, N, n = inputs.n_runs, inputs.n, self.n_particles, self.n
        sd_i = None
        if noise.Q_override is None and noise.sensor.input_var > 0:
            sd_i = float(np.sqrt(noise.sensor.input_var))
        walk_z = bool(np.any(self._walks(1, 1.0)[0] > 0))  # draw the SOC's walk noise only where there is one
        draws = StepDraws(seed, R, N, n, sd_i is not None, walk_z)
        # the initial cloud: SOC particles from the prior's SOC marginal; the linear states' conditional mean and
        # covariance given each particle's SOC (Gaussian conditioning on P0)
        pzz = P0[:, 0, 0]
        gain = P0[:, 1:, 0] / pzz[:, None]
        X = np.empty((R, N, n))
        X[..., 0] = x0[:, None, 0] + np.sqrt(pzz)[:, None] * draws.initial()[..., 0]
        X[..., 1:] = x0[:, None, 1:] + gain[:, None, :] * (X[..., :1] - x0[:, None, :1])
        PL = symmetrise(P0[:, 1:, 1:] - gain[:, :, None] * P0[:, None, 0, 1:])
        pending_clamp = _clamp_particles(X)
        w = np.full((R, N), 1.0 / N)
        X_good, w_good, PL_good = X.copy(), w.copy(), PL.copy()
        rec = self.recorder(inputs, x0, P0)
        gate = self.gate(R)
        threshold = opt["resample_threshold"] * N
        h = opt["kernel_h"]
        resampled = np.zeros(R, dtype=int)
        staged = np.zeros(R, dtype=int)
        eye = np.eye(n - 1)
        with np.errstate(all="ignore"):
            for k in range(T):
                u, eps_i, eps_q = draws.step(k)
                ik, tk = inputs.current[:, k], inputs.temp_at(k)
                tk_p = None if tk is None else tk[:, None]
                zbar = np.sum(w * X[..., 0], axis=1)
                mean = np.einsum("rp,rpi->ri", w, X)
                mean[:, 0] = zbar
                # ---------------------------------------------------------------- update
                Y = self._outputs(X, zbar, ik, tk, tk_p)
                _, H, D = m.output(mean, ik, tk, jac=True)
                HL = H[:, 1:]
                Rk = noise.R(D, (R,))
                Sc = np.einsum("ri,rij,rj->r", HL, PL, HL) + Rk
                vk = inputs.voltage[:, k]
                yhat = np.sum(w * Y, axis=1)
                S = np.sum(w * (Y - yhat[:, None]) ** 2, axis=1) + Sc
                e = vk - yhat
                nis = e * e / S
                gated = gate(nis)
                ok = ~gated
                if ok.any():
                    X, w, Y, n_stages = self._weigh(X, w, Y, Sc, gated, vk, zbar, ik, tk, tk_p,
                                                    lambda s, k=k: draws.stage(k, s))
                    staged += (n_stages > 1) & ~rec.failed
                    K = np.einsum("rij,rj->ri", PL, HL) / Sc[:, None]
                    X[..., 1:] += np.where(ok[:, None, None], K[:, None, :] * (vk[:, None] - Y)[..., None], 0.0)
                    A = eye - K[:, :, None] * HL[:, None, :]
                    PLu = symmetrise(A @ PL @ np.swapaxes(A, -1, -2) + Rk[:, None, None] * K[:, :, None] * K[:, None])
                    PL = np.where(ok[:, None, None], PLu, PL)
                mean, var = cloud_moments(w, X)
                var[:, 1:] += np.diagonal(PL, axis1=1, axis2=2)
                failed = rec.fail(k, diverged(mean, var[:, 0], nis, opt["var_max"], opt["nis_max"]))
                restore(X, X_good, failed)
                restore(w, w_good, failed)
                restore(PL, PL_good, failed)
                rec.record(k, mean[:, 0], np.sqrt(var[:, 0]), yhat, e, S, pending_clamp, gated, mean, var)
                if k + 1 == T:
                    break
                # ---------------------------------------------------------------- resample
                # the kernel keeps the cloud's mean and covariance (SOC and states jointly)
                resampled += resample_degenerate(X, w, threshold, failed, u, h, 0.0,
                                                 lambda rows, k=k: draws.roughening(k, rows))
                # ---------------------------------------------------------------- predict
                zbar = np.sum(w * X[..., 0], axis=1)
                mean = np.einsum("rp,rpi->ri", w, X)
                mean[:, 0] = zbar
                i_p = ik[:, None] if sd_i is None else ik[:, None] + sd_i * eps_i
                Xs = X.copy()
                Xs[..., 0] = zbar[:, None]
                Xf = m.step(Xs, np.broadcast_to(i_p, (R, N)), inputs.dt[k], tk_p)[0]
                _, F, B = m.step(mean, ik, inputs.dt[k], tk, jac=True)
                q_z, QL = self._walks(R, inputs.dt[k])
                X[..., 1:] = Xf[..., 1:]
                X[..., 0] += Xf[..., 0] - zbar[:, None]
                if walk_z:
                    X[..., 0] += np.sqrt(q_z)[:, None] * eps_q[..., 0]
                hold = noise.hold(inputs.hold_var[k])
                if hold > 0:  # the current the hold misses across a logger pause: the SOC and each state on its own
                    X[..., 0] += np.sqrt(hold) * B[:, None, 0] * draws.hold(k)[..., 0]
                    QL = QL + hold_cov(B[:, 1:], hold)
                AL = F[:, 1:, 1:]
                PL = symmetrise(AL @ PL @ np.swapaxes(AL, -1, -2) + QL)
                pending_clamp = _clamp_particles(X)
                failed = rec.fail(k + 1, ~(np.all(np.isfinite(X), axis=(1, 2)) & np.all(np.isfinite(PL), axis=(1, 2))))
                restore(X, X_good, failed)
                restore(PL, PL_good, failed)
                np.copyto(X_good, X, where=~failed[:, None, None])
                np.copyto(w_good, w, where=~failed[:, None])
                np.copyto(PL_good, PL, where=~failed[:, None, None])
        return rec.finish(self.name, m, {"gate_threshold": gate.threshold, "n_particles": N,
                                         "resampled": resampled, "tempered": staged, "seed": draws.seed})
