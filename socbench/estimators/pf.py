"""Bootstrap particle filter with systematic resampling and roughening, batched: runs × particles in one model call.

Each run carries ``N`` particles ``X_j`` with weights ``w_j`` (Gordon, Salmond & Smith 1993). For each sample k::

    update    Y_j = h(X_j, I_k),  R_j = σ_V² + σ_I² D_j²
              ŷ = Σ w_j Y_j,   S = Σ w_j (Y_j − ŷ)² + Σ w_j R_j,   e = v_k − ŷ,   NIS = e²/S
              w_j ← w_j · N(v_k; Y_j, R_j + R_x) / Σ(…)     (in the log domain; skipped when the χ² gate rejects;
                                                            R_x: ``NoiseModel.weight_extra``, 0 until the run's
                                                            first assimilated sample, then
                                                            ``SensorNoise.weight_extra_var``)
              if that would leave N_eff < temper_threshold·N, the likelihood is applied in tempered stages with
              resampling and a shrinkage kernel between them (progressive correction, see ``assimilate``)
              report ẑ = Σ w_j z_j, soc_std² = Σ w_j (z_j − ẑ)²
    resample  where N_eff = 1/Σ w_j² < threshold·N: systematic resampling, positions (u + i)/N with one uniform u
              per run, particle i ← the first j with cumsum(w)_j > (u + i)/N; then w_j = 1/N and roughening
              X_j += K·E·N^(−1/d)·ε  (E = per-state spread max − min of the particles, d = n; Gordon et al. 1993)
    predict   X_j ← f(X_j, I_k + σ_I ε_j, dt_k)  (+ additive walk or Q-override noise)
              X_j ← X_j + σ_hold,k · B̄_k ⊙ ε'_j   across a logger pause (σ_hold,k² = ``Inputs.hold_var``, zero at a
                                                    sampled step; B̄ = ∂f/∂I at the cloud's mean; each state on its
                                                    own, as ``noise.hold_cov``);  z clamped to [0, 1]

The current-noise draw ``ε_j`` makes the process noise exactly the one the sensor spec describes (no Gaussian
approximation of B·σ_I). With a ``Q`` override the process noise is additive ``N(0, Q)`` instead.

Random numbers are counter-based (:mod:`socbench.estimators.draws`): each is a hash of (seed, stream, sample, run,
counter), with one stream each for the initial cloud, the resampling offset u, the current noise ε_I, the additive
noise ε_Q, the roughening and the tempering stages. So any engine computes exactly the numbers of any run without
replaying the others: the batched PF, the compiled PF (``socbench.kernels.pf``) and a per-run reference
(``reference.ReferencePF``) see the same numbers, whatever the batch shape.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import Estimator, restore
from .draws import StepDraws, seed_u64
from .estimate import Estimate
from .safety import diverged


def systematic_indices(weights: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Batched systematic resampling: ``(M, N)`` normalised weights and ``(M,)`` uniforms → ``(M, N)`` indices.

    ``idx[i] = min{j : cumsum(w)_j > (u + i)/N}`` — the rule of ``filterpy.monte_carlo.systematic_resample``,
    computed with one stable sort per row (exact comparisons, no loop): ``idx[i] = #{j : cumsum_j ≤ pos_i}``.
    """
    M, N = weights.shape
    cum = np.cumsum(weights, axis=1)
    pos = (u[:, None] + np.arange(N)) / N
    order = np.argsort(np.concatenate([cum, pos], axis=1), axis=1, kind="stable")  # ties: cumsum entries first
    is_cum = order < N
    counts = np.cumsum(is_cum, axis=1)
    idx = counts[~is_cum].reshape(M, N)  # positions are increasing, so they come out in their own order
    return np.minimum(idx, N - 1)  # cumsum may end a rounding below 1


def log_likelihood(v, Y, R):
    """``log N(v; Y, R)`` up to the constant: ``−(v − Y)²/(2R) − ½ log R``."""
    r = v - Y
    return -0.5 * r * r / R - 0.5 * np.log(R)


def normalise_log(lw: np.ndarray) -> np.ndarray:
    """Log-weights shifted so that their exponentials sum to 1 along the last axis."""
    lw = lw - np.max(lw, axis=-1, keepdims=True)
    return lw - np.log(np.sum(np.exp(lw), axis=-1, keepdims=True))


def ess(lw: np.ndarray) -> np.ndarray:
    """Effective sample size ``1/Σ w²`` of normalised log-weights."""
    return 1.0 / np.sum(np.exp(2.0 * lw), axis=-1)


def temper_exponent(lw, ll, phi_max, accept, target, iters: int = 24):
    """Per row: ``phi_max`` where ``ESS(lw + phi_max·ll) ≥ accept``; elsewhere the largest ``φ`` with
    ``ESS(lw + φ·ll) ≥ target`` (bisection, at least ``phi_max/2^iters``)."""
    phi = phi_max.copy()
    bad = ess(normalise_log(lw + phi_max[:, None] * ll)) < accept
    if not bad.any():
        return phi
    lwb, llb = lw[bad], ll[bad]
    lo, hi = np.zeros(int(bad.sum())), phi_max[bad]
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        good = ess(normalise_log(lwb + mid[:, None] * llb)) >= target
        lo = np.where(good, mid, lo)
        hi = np.where(good, hi, mid)
    phi[bad] = np.maximum(lo, phi_max[bad] * 0.5**iters)
    return phi


def roughening_sd(X: np.ndarray, K: float) -> np.ndarray:
    """``K · (max − min) · N^(−1/d)`` per run and state: ``(…, N, n)`` → ``(…, n)``."""
    N, d = X.shape[-2], X.shape[-1]
    return K * (X.max(axis=-2) - X.min(axis=-2)) * N ** (-1.0 / d)


def weighted_mean_root(X: np.ndarray, w: np.ndarray):
    """Weighted mean ``(…, n)`` and a symmetric square root ``(…, n, n)`` of the weighted covariance."""
    mean = np.einsum("...p,...pi->...i", w, X)
    d = X - mean[..., None, :]
    V = np.einsum("...p,...pi,...pj->...ij", w, d, d)
    lam, U = np.linalg.eigh(0.5 * (V + np.swapaxes(V, -1, -2)))
    root = (U * np.sqrt(np.maximum(lam, 0.0))[..., None, :]) @ np.swapaxes(U, -1, -2)
    return mean, root


def shrink(X: np.ndarray, mean: np.ndarray, root: np.ndarray, h: float, eps: np.ndarray) -> np.ndarray:
    """Kernel jitter with shrinkage (Liu & West 2001): ``a X + (1 − a) x̄ + h V^½ ε``, ``a = √(1 − h²)``.

    Keeps the cloud's mean and covariance while giving resampled duplicates distinct values.
    """
    a = np.sqrt(1.0 - h * h)
    return a * X + (1.0 - a) * mean[..., None, :] + h * np.einsum("...ij,...pj->...pi", root, eps)


def resample_rows(X, w, rows, u, h: float, K_rough: float, jitter):
    """In place: systematic resampling of the runs ``rows`` (``u`` their offsets), weights reset to ``1/N``; then,
    with ``h > 0``, the shrinkage kernel with the cloud's weighted mean and covariance from before resampling
    (:func:`shrink`), else with ``K_rough > 0`` roughening (:func:`roughening_sd`). ``jitter()`` draws the kernel's
    or the roughening's normals ``(rows, N, n)``, called only when one of them is used."""
    N = X.shape[1]
    Xr = X[rows]
    if h > 0:
        mean_r, root_r = weighted_mean_root(Xr, w[rows])
    idx = systematic_indices(w[rows], u[rows])
    Xr = np.take_along_axis(Xr, idx[:, :, None], axis=1)
    w[rows] = 1.0 / N
    if h > 0:
        Xr = shrink(Xr, mean_r, root_r, h, jitter())
    elif K_rough > 0:
        Xr += roughening_sd(Xr, K_rough)[:, None, :] * jitter()
    X[rows] = Xr


def resample_degenerate(X, w, threshold: float, failed, u, h: float, K_rough: float, jitter) -> np.ndarray:
    """In place: the runs whose effective sample size ``1/Σ w²`` fell below ``threshold`` (failed runs left as they
    are) resampled by :func:`resample_rows`; ``jitter(rows)`` draws their kernel's normals. Returns those runs."""
    rows = (1.0 / np.sum(w * w, axis=1) < threshold) & ~failed
    if rows.any():
        resample_rows(X, w, rows, u, h, K_rough, lambda: jitter(rows))
    return rows


def hold_spread(model, mean, i, dt: float, temp, hold_var: float) -> np.ndarray:
    """``σ_hold·B̄`` ``(R, n)``: each state's spread from the current the hold misses over a step (module docstring),
    ``B̄ = ∂f/∂I`` at the cloud's mean ``mean (R, n)`` with the measured current ``i (R,)``."""
    return np.sqrt(hold_var) * model.step(mean, i, dt, temp, jac=True)[2]


def cloud_moments(w: np.ndarray, X: np.ndarray):
    """``(mean, var)``, each ``(R, n)``: the weighted mean and variance of every run's particles ``X (R, N, n)``."""
    mean = np.einsum("rp,rpi->ri", w, X)
    return mean, np.einsum("rp,rpi->ri", w, (X - mean[:, None, :]) ** 2)


def progressive_correction(X, w, ll, gated, opt: dict, stage_draws, relikelihood):
    """Weights ``w ∝ w · L`` (``L = e^ll``, per particle) for the rows not gated, by progressive correction (Oudjane &
    Musso 2000); the particle filters' shared measurement step.

    When the full likelihood would leave fewer than ``temper_threshold·N`` effective particles (a peaked likelihood on
    a wide cloud: a far-off start), it is applied in stages ``L^φ1 · L^φ2 ⋯`` (Σφ = 1): each ``φ`` is the largest
    keeping ``N_eff ≥ resample_threshold·N`` (bisection), and between stages the cloud is resampled (systematic) and
    spread by the shrinkage kernel (``temper_h``), then ``relikelihood(rows, moved particles)`` gives the moved rows'
    log-likelihood. At most ``max_stages`` stages; the last takes what is left. ``opt``: the filter's options.
    Returns ``(X, w, stages (M,))``.
    """
    N = X.shape[1]
    target = opt["resample_threshold"] * N
    accept = opt["temper_threshold"] * N
    lw = np.log(w)
    left = np.where(gated, 0.0, 1.0)
    stages = np.zeros(X.shape[0], dtype=int)
    max_stages = max(int(opt["max_stages"]), 1)
    for s in range(max_stages):
        active = left > 0
        if not active.any():
            break
        phi = left if s == max_stages - 1 else temper_exponent(lw, ll, left, accept, target)
        phi = np.where(active, phi, 0.0)
        lw = normalise_log(lw + phi[:, None] * ll)
        left = left - phi
        stages += active
        part = left > 0
        if part.any():
            u, eps = stage_draws(s)
            w = np.exp(lw)
            mean, root = weighted_mean_root(X[part], w[part])
            idx = systematic_indices(w[part], u[part])
            Xp = shrink(np.take_along_axis(X[part], idx[:, :, None], axis=1), mean, root, opt["temper_h"], eps[part])
            _clamp_particles(Xp)
            X = X.copy()
            X[part] = Xp
            lw[part] = -np.log(N)
            ll = ll.copy()
            ll[part] = relikelihood(part, Xp)
    return X, np.exp(lw), stages


class ParticleFilter(Estimator):
    """Batched bootstrap particle filter."""

    name = "pf"
    #: a bootstrap PF cannot carry the recipe's coloured states: near-deterministic dimensions sampled through a
    #: likelihood narrower than the error they explain collapse onto a few particles (measured: pngv on flight-0kg,
    #: SOC RMSE 12 %, NIS 5e5 with the states; see socbench.estimators.model_error, inflated form)
    model_error_form = "inflated"
    defaults = {"n_particles": 500, "resample_threshold": 0.5, "roughening": 0.2, "kernel_h": 0.0,
                "max_stages": 8, "temper_threshold": 0.2, "temper_h": 0.5}

    def __init__(self, model, noise=None, **options):
        super().__init__(model, noise, **options)
        o = self.options
        if int(o["n_particles"]) < 2:
            raise ConfigError("pf: n_particles must be >= 2")
        if not 0 <= o["resample_threshold"] <= 1:
            raise ConfigError("pf: resample_threshold must be in [0, 1] (a fraction of n_particles)")
        if not o["roughening"] >= 0:
            raise ConfigError("pf: roughening must be >= 0")
        if not 0 <= o["kernel_h"] < 1 or not 0 <= o["temper_h"] < 1:
            raise ConfigError("pf: kernel_h and temper_h must be in [0, 1)")
        if callable(self.noise.Q_override):
            raise ConfigError("pf: Q must be an (n, n) array for the particle filter (no callable)")
        self.n_particles = int(o["n_particles"])

    # ------------------------------------------------------------------ process noise
    def process_noise(self):
        """``(σ_current or None, additive square root (…, n, n) function of dt or None)``."""
        sensor, Qo = self.noise.sensor, self.noise.Q_override
        if Qo is not None:
            w, V = np.linalg.eigh(0.5 * (Qo + Qo.T))
            root = V * np.sqrt(np.maximum(w, 0.0))
            return None, (lambda dt: root)
        sd_i = np.sqrt(sensor.input_var) if sensor.input_var > 0 else None
        if sensor.has_walk:
            return sd_i, (lambda dt: np.diag(np.sqrt(sensor.walk_var(self.n, dt))))
        return sd_i, None

    def draws(self, seed, n_runs: int, runs=None) -> StepDraws:
        sd_i, additive = self.process_noise()
        return StepDraws(seed, n_runs, self.n_particles, self.n, sd_i is not None, additive is not None, runs)

    # ------------------------------------------------------------------ measurement update with tempering
    def assimilate(self, X, w, ll, gated, v, i, temp, stage_draws, extra):
        """Weights ``w ∝ w · L`` for the rows not gated, by :func:`progressive_correction`; the moved particles'
        likelihood is the model's output at them against ``v`` (variance ``R + extra``, ``extra (M,)`` per row).
        Returns ``(X, w, stages (M,))``. Rows are independent, so a per-run caller (the reference) gets the same
        numbers from a one-row slice."""

        def relikelihood(part, Xp):
            tp = None if temp is None else temp[part][:, None]
            Yp, _, Dp = self.model.output(Xp, i[part][:, None], tp, jac=self.noise.needs_D)
            return log_likelihood(v[part][:, None], Yp, self.noise.R(Dp, Yp.shape) + extra[part][:, None])

        return progressive_correction(X, w, ll, gated, self.options, stage_draws, relikelihood)

    # ------------------------------------------------------------------ the time loop
    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        m, opt, noise = self.model, self.options, self.noise
        R, T, N = inputs.n_runs, inputs.n, self.n_particles
        sd_i, additive = self.process_noise()
        draws = self.draws(seed, R)
        L0 = np.linalg.cholesky(P0)
        X = x0[:, None, :] + np.einsum("rij,rpj->rpi", L0, draws.initial())
        pending_clamp = _clamp_particles(X)
        w = np.full((R, N), 1.0 / N)
        X_good, w_good = X.copy(), w.copy()
        rec = self.recorder(inputs, x0, P0)
        gate = self.gate(R)
        threshold = opt["resample_threshold"] * N
        K_rough, h = opt["roughening"], opt["kernel_h"]
        resampled = np.zeros(R, dtype=int)
        staged = np.zeros(R, dtype=int)
        looked = np.zeros(R, dtype=bool)  # whether the run has assimilated a sample yet (noise.NoiseModel.weight_extra)
        with np.errstate(all="ignore"):
            for k in range(T):
                u, eps_i, eps_q = draws.step(k)
                ik, tk = inputs.current[:, k], inputs.temp_at(k)
                tk_p = None if tk is None else tk[:, None]
                # ---------------------------------------------------------------- update
                Y, _, D = m.output(X, ik[:, None], tk_p, jac=noise.needs_D)
                Rk = noise.R(D, (R, N))
                yhat = np.sum(w * Y, axis=1)
                S = np.sum(w * (Y - yhat[:, None]) ** 2, axis=1) + np.sum(w * Rk, axis=1)
                vk = inputs.voltage[:, k]
                e = vk - yhat
                nis = e * e / S
                gated = gate(nis)
                extra = noise.weight_extra(looked)
                X, w, n_stages = self.assimilate(X, w, log_likelihood(vk[:, None], Y, Rk + extra[:, None]), gated, vk,
                                                 ik, tk, lambda s, k=k: draws.stage(k, s), extra)
                looked |= ~gated
                staged += (n_stages > 1) & ~rec.failed  # runs failed earlier are frozen: they count nothing
                mean, var = cloud_moments(w, X)
                failed = rec.fail(k, diverged(mean, var[:, 0], nis, opt["var_max"], opt["nis_max"]))
                restore(X, X_good, failed)
                restore(w, w_good, failed)
                rec.record(k, mean[:, 0], np.sqrt(var[:, 0]), yhat, e, S, pending_clamp, gated, mean, var)
                if k + 1 == T:
                    break
                # ---------------------------------------------------------------- resample
                resampled += resample_degenerate(X, w, threshold, failed, u, h, K_rough,
                                                 lambda rows, k=k: draws.roughening(k, rows))
                # ---------------------------------------------------------------- predict
                i_p = ik[:, None] if sd_i is None else ik[:, None] + sd_i * eps_i
                X = m.step(X, i_p, inputs.dt[k], tk_p)[0]
                if additive is not None:
                    X += np.einsum("ij,rpj->rpi", additive(inputs.dt[k]), eps_q)
                hold = noise.hold(inputs.hold_var[k])
                if hold > 0:
                    X += hold_spread(m, mean, ik, inputs.dt[k], tk, hold)[:, None, :] * draws.hold(k)
                pending_clamp = _clamp_particles(X)
                failed = rec.fail(k + 1, ~np.all(np.isfinite(X), axis=(1, 2)))
                restore(X, X_good, failed)
                np.copyto(X_good, X, where=~failed[:, None, None])
                np.copyto(w_good, w, where=~failed[:, None])
        return rec.finish(self.name, m, {"gate_threshold": gate.threshold, "n_particles": N,
                                         "resampled": resampled, "tempered": staged, "seed": draws.seed})


    def _run_compiled(self, job, seed=None):
        from ..kernels import pf as kpf
        from ..kernels.engine import parallel_runs, sensor_walk

        o, N, n = self.options, self.n_particles, self.n
        sd_i, additive = self.process_noise()
        Qroot = np.zeros((n, n))
        mode = kpf.ADD_NONE
        if self.noise.Q_override is not None:
            Qroot, mode = np.ascontiguousarray(additive(1.0), dtype=float), kpf.ADD_ROOT
        elif additive is not None:
            mode = kpf.ADD_WALK
        draws = self.draws(seed, job.R)
        pfopt = np.array([N, o["resample_threshold"], o["roughening"], o["kernel_h"], o["max_stages"],
                          o["temper_threshold"], o["temper_h"], 0.0 if sd_i is None else sd_i, mode,
                          N ** (-1.0 / n)], dtype=float)  # (no needs_D: the kernel's model output always gives D)
        L0 = np.ascontiguousarray(np.linalg.cholesky(job.P0))
        std0 = np.sqrt(job.P0[:, 0, 0])
        counts = np.zeros((job.R, 2), dtype=np.int64)
        hold = np.ascontiguousarray(self.noise.hold(job.hv))
        parallel_runs(kpf.pf, job.R, job.im, job.fm, job.x0, L0, std0, job.cur, job.volt, job.temp, job.has_temp,
                      job.dts, hold, job.nz, sensor_walk(self.noise.sensor, n), Qroot, job.opt, pfopt,
                      seed_u64(draws.seed), *job.out_args, counts, min_runs=1)  # the particles' walk: the sensor's
        return job.finish({"gate_threshold": job.threshold, "n_particles": N, "resampled": counts[:, 0].copy(),
                           "tempered": counts[:, 1].copy(), "seed": draws.seed})


def _clamp_particles(X: np.ndarray) -> np.ndarray:
    """Clip every particle's SOC into [0, 1]; (R,) flag of the runs where it acted."""
    z = X[..., 0]
    out = (z < 0.0) | (z > 1.0)
    if out.any():
        np.clip(z, 0.0, 1.0, out=z)
    return out.any(axis=-1)
