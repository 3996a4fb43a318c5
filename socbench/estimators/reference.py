"""Reference backends on filterpy 2.x: one trajectory at a time, the yardstick of the batched engines.

* :class:`ReferenceEKF` — ``filterpy.kalman.ExtendedKalmanFilter`` with a nonlinear ``predict_x`` (the model's step,
  which also sets ``F`` and ``Q``), ``update(z, HJacobian, Hx, R)`` (filterpy's Joseph form);
* :class:`ReferenceUKF` — ``filterpy.kalman.UnscentedKalmanFilter`` + ``MerweScaledSigmaPoints``;
* :class:`ReferencePF` — a per-run bootstrap filter whose resampling is ``filterpy.monte_carlo.systematic_resample``
  (the rare tempered updates reuse ``ParticleFilter.assimilate`` on a one-row slice: its rows are independent);
* :class:`ReferenceCKF` — ``filterpy.kalman.CubatureKalmanFilter`` (Arasaratnam & Haykin 2009);
* :class:`ReferenceJointEKF` — filterpy's ``ExtendedKalmanFilter`` (as :class:`ReferenceEKF`) on the joint model
  ``[x, cap, ΔR0]`` with the parameter random walks (Plett 2004, Part 3);
* :class:`ReferenceAEKF`, :class:`ReferenceSRUKF`, :class:`ReferenceHInf` — filterpy has none of these, so each is a
  plain per-run textbook implementation, one trajectory at a time with scalar code, of the equations in its docstring
  (Sage & Husa 1969; van der Merwe & Wan 2001; Simon 2006 §11.3), written independently of the batched engine's
  algebra (e.g. the H∞ update inverts Simon's ``A`` instead of the batched Sherman–Morrison form, the SRUKF factors
  with ``scipy.linalg.qr``/``eigh`` and evaluates the model one sigma point at a time).

Around filterpy's predict/update each reference applies the same safety rules as the batched engines (gate, clamp,
symmetrise, PSD repair, divergence freeze: ``safety.py``) and records through the same :class:`~.base.Recorder`, so the
two agree to round-off on identical inputs. filterpy draws the systematic-resampling offset from numpy's global
generator; the reference hands it the run's pre-drawn offset instead, so both see the same random numbers.

These classes are slow by design (a Python loop over runs and steps); ``socbench bench`` times them against the
batched engines.
"""

from __future__ import annotations

from unittest import mock

import numpy as np
import scipy.linalg
from filterpy.kalman import CubatureKalmanFilter, ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from filterpy.kalman.CubatureKalmanFilter import spherical_radial_sigmas
from filterpy.monte_carlo import resampling as fp_resampling

from .aekf import AdaptiveEKF
from .base import Estimator, Inputs
from .dual import JointParameters
from .estimate import Estimate
from .hinf import HInfinityFilter
from .pf import ParticleFilter, hold_spread, log_likelihood, roughening_sd, shrink, weighted_mean_root
from .safety import diverged, project_soc, repair_psd, symmetrise
from .ukf import UKF, merwe_weights


def _one_run(inputs: Inputs, r: int) -> Inputs:
    s = slice(r, r + 1)
    return Inputs(inputs.time_s, inputs.dt, inputs.current[s], inputs.voltage[s],
                  None if inputs.temp is None else inputs.temp[s], inputs.name, inputs.capacity_ah, inputs.hold_var)


def _stack(parts: list[Estimate], info: dict) -> Estimate:
    def cat(name):
        vals = [getattr(p, name) for p in parts]
        return None if vals[0] is None else np.concatenate(vals, axis=0)

    p0 = parts[0]
    return Estimate(p0.time_s, cat("soc"), cat("soc_std"), cat("v_pred"), cat("innovation"), cat("innovation_var"),
                    cat("failed"), cat("failed_at"), cat("clamped"), cat("gated"), cat("x"), cat("P_diag"),
                    p0.estimator, p0.model, p0.state_names, info, failed_reason=cat("failed_reason"))


class _KalmanReference(Estimator):
    """Shared per-run loop: ``_filter(inputs_r, x0_r, P0_r)`` fills a one-run Recorder."""

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        parts = []
        for r in range(inputs.n_runs):
            one = _one_run(inputs, r)
            rec = self.recorder(one, x0[r:r + 1], P0[r:r + 1])
            self._filter(one, x0[r].copy(), P0[r].copy(), rec)
            parts.append(rec.finish(self.name, self.model))
        return _stack(parts, {"reference": "filterpy"})

    def _guard(self, rec, k, x, P, nis):
        """Symmetrise + repair P, clamp x (in place); returns (P, clamped, failed)."""
        opt = self.options
        P = repair_psd(symmetrise(P)[None], opt["psd_floor"], opt["psd_rel_floor"])[0][0]
        clamped = project_soc(x[None], P[None])  # x is a view of the filter's state: projected in place
        failed = rec.fail(k, diverged(x[None], P[None], np.atleast_1d(nis), opt["var_max"], opt["nis_max"]))
        return P, clamped, bool(failed[0])

    def _predicted_ok(self, rec, k: int, T: int, *arrays) -> bool:
        """False (the run failed at ``k``, its outputs frozen) when a predicted array is not finite."""
        if all(np.all(np.isfinite(a)) for a in arrays):
            return True
        rec.fail(k, np.ones(1, bool))
        self._freeze_rest(rec, k, T)
        return False

    @staticmethod
    def _freeze_rest(rec, k0: int, T: int):
        z = np.zeros(1)
        xs = None if rec.x is None else np.zeros((1, rec.x.shape[-1]))
        for k in range(k0, T):
            rec.record(k, z, z, z, z, z, np.zeros(1, bool), np.zeros(1, bool), xs, xs)


class _ModelEKF(ExtendedKalmanFilter):
    """filterpy's EKF whose prediction is the model's nonlinear step; ``u = (I, dt, T, hold_var)``."""

    def __init__(self, model, process_cov):
        super().__init__(dim_x=model.n_states, dim_z=1)
        self.model = model
        self.process_cov = process_cov  # (B, dt, hold_var) -> Q

    def predict_x(self, u=0):
        i, dt, temp, hold = u
        xn, F, B = self.model.step(self.x[:, 0], i, dt, temp, jac=True)
        self.F = F
        self.Q = self.process_cov(B, dt, hold)
        self.x = xn[:, None]


class ReferenceEKF(_KalmanReference):
    """Per-run EKF on ``filterpy.kalman.ExtendedKalmanFilter``."""

    name = "ekf"
    linearises_output = True  # a prior mean where the OCV is held flat is moved (base.out_of_held_ocv)

    def _filter(self, inputs, x0, P0, rec):
        m, T = self.model, inputs.n
        ekf = _ModelEKF(m, self.process_cov)
        ekf.x = x0[:, None].copy()
        ekf.P = P0.copy()
        gate = self.gate(1)
        for k in range(T):
            i, v = inputs.current[0, k], inputs.voltage[0, k]
            temp = None if inputs.temp is None else inputs.temp[0, k]
            y, _, D = m.output(ekf.x[:, 0], i, temp, jac=True)
            x_prior, P_prior = ekf.x.copy(), ekf.P.copy()
            ekf.update(np.array([[v]]),
                       HJacobian=lambda x, i=i, temp=temp: m.output(x[:, 0], i, temp, jac=True)[1][None, :],
                       Hx=lambda x, i=i, temp=temp: np.array([[m.output(x[:, 0], i, temp)[0]]]),
                       R=np.array([[float(self.noise.R(D, ()))]]))
            e, S = float(ekf.y[0, 0]), float(ekf.S[0, 0])
            gated = gate(np.array([e * e / S]))
            if gated[0]:
                ekf.x, ekf.P = x_prior, P_prior
            ekf.P, clamped, failed = self._guard(rec, k, ekf.x[:, 0], ekf.P, e * e / S)
            if failed:
                self._freeze_rest(rec, k, T)
                return
            rec.record(k, ekf.x[0], np.sqrt(ekf.P[0, 0])[None], np.atleast_1d(y), np.array([e]), np.array([S]),
                       clamped, gated, ekf.x[:, 0][None], np.diag(ekf.P)[None])
            if k + 1 < T:
                ekf.predict(u=(i, inputs.dt[k], temp, inputs.hold_var[k]))
                ekf.P = symmetrise(ekf.P)
                if not (np.all(np.isfinite(ekf.x)) and np.all(np.isfinite(ekf.P))):
                    rec.fail(k + 1, np.ones(1, bool))
                    self._freeze_rest(rec, k + 1, T)
                    return

    def process_cov(self, B, dt, hold_var=0.0):
        return self.noise.Q(B, dt, hold_var)


class ReferenceUKF(_KalmanReference):
    """Per-run UKF on ``filterpy.kalman.UnscentedKalmanFilter`` with ``MerweScaledSigmaPoints``."""

    name = "ukf"
    defaults = UKF.defaults

    def _filter(self, inputs, x0, P0, rec):
        m, T, n, opt = self.model, inputs.n, self.n, self.options
        points = MerweScaledSigmaPoints(n, alpha=opt["alpha"], beta=opt["beta"], kappa=opt["kappa"])

        def fx(s, dt, i, temp):
            return m.step(s, i, dt, temp)[0]

        def hx(s, i, temp):
            return np.atleast_1d(m.output(s, i, temp)[0])

        ukf = UnscentedKalmanFilter(dim_x=n, dim_z=1, dt=1.0, hx=hx, fx=fx, points=points)
        ukf.x = x0.copy()
        ukf.P = P0.copy()
        ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)  # the prior sigma points the first update uses
        gate = self.gate(1)
        floors = (opt["psd_floor"], opt["psd_rel_floor"])
        for k in range(T):
            i, v = inputs.current[0, k], inputs.voltage[0, k]
            temp = None if inputs.temp is None else inputs.temp[0, k]
            D = m.output(ukf.x, i, temp, jac=True)[2]
            x_prior, P_prior = ukf.x.copy(), ukf.P.copy()
            ukf.update(np.array([v]), R=np.array([[float(self.noise.R(D, ()))]]), i=i, temp=temp)
            e, S = float(ukf.y[0]), float(ukf.S[0, 0])
            yhat = float(np.dot(points.Wm, ukf.sigmas_h[:, 0]))
            gated = gate(np.array([e * e / S]))
            if gated[0]:
                ukf.x, ukf.P = x_prior, P_prior
            ukf.P, clamped, failed = self._guard(rec, k, ukf.x, ukf.P, e * e / S)
            if failed:
                self._freeze_rest(rec, k, T)
                return
            rec.record(k, ukf.x[:1], np.sqrt(ukf.P[0, 0])[None], np.array([yhat]), np.array([e]), np.array([S]),
                       clamped, gated, ukf.x[None], np.diag(ukf.P)[None])
            if k + 1 < T:
                ukf.Q = self.noise.Q(m.step(ukf.x, i, inputs.dt[k], temp, jac=True)[2], inputs.dt[k],
                                     inputs.hold_var[k])
                ukf.predict(dt=inputs.dt[k], i=i, temp=temp)
                ukf.P = repair_psd(symmetrise(ukf.P)[None], *floors)[0][0]
                if not (np.all(np.isfinite(ukf.x)) and np.all(np.isfinite(ukf.P))):
                    rec.fail(k + 1, np.ones(1, bool))
                    self._freeze_rest(rec, k + 1, T)
                    return
                ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)


class ReferencePF(ParticleFilter):
    """Per-run particle filter with ``filterpy.monte_carlo.systematic_resample``, on the batched filter's draws."""

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        R = inputs.n_runs
        seed = self.draws(seed, R).seed  # one seed for every run (drawn here when None)
        parts = []
        for r in range(R):
            one = _one_run(inputs, r)
            rec = self.recorder(one, x0[r:r + 1], P0[r:r + 1])
            self._filter_one(one, x0[r], P0[r], self.draws(seed, 1, runs=[r]), rec)  # exactly run r's numbers
            parts.append(rec.finish(self.name, self.model))
        return _stack(parts, {"reference": "filterpy.monte_carlo.systematic_resample", "seed": seed})

    def _filter_one(self, inputs, x0, P0, draws, rec):
        m, opt, noise = self.model, self.options, self.noise
        T, N = inputs.n, self.n_particles
        sd_i, additive = self.process_noise()
        X = x0 + draws.initial()[0] @ np.linalg.cholesky(P0).T
        clamp = _clamp_one(X)
        w = np.full(N, 1.0 / N)
        gate = self.gate(1)
        looked = False  # whether the run has assimilated a sample yet (noise.NoiseModel.weight_extra)
        for k in range(T):
            u, eps_i, eps_q = draws.step(k)
            i, v = inputs.current[0, k], inputs.voltage[0, k]
            temp = None if inputs.temp is None else inputs.temp[0, k]
            Y, _, D = m.output(X, i, temp, jac=noise.needs_D)
            Rk = noise.R(D, (N,))
            yhat = np.sum(w * Y)
            S = np.sum(w * (Y - yhat) ** 2) + np.sum(w * Rk)
            e = v - yhat
            gated = gate(np.array([e * e / S]))
            temp_1 = None if temp is None else np.array([temp])
            extra = noise.weight_extra(looked)
            Xs, ws, _ = self.assimilate(X[None], w[None], log_likelihood(v, Y, Rk + extra)[None], gated, np.array([v]),
                                        np.array([i]), temp_1, lambda s, k=k: draws.stage(k, s), np.array([extra]))
            looked = looked or not gated[0]
            X, w = Xs[0], ws[0]
            mean = w @ X
            var = w @ (X - mean) ** 2
            failed = rec.fail(k, diverged(mean[None], var[:1], np.array([e * e / S]), opt["var_max"], opt["nis_max"]))
            if failed[0]:
                _KalmanReference._freeze_rest(rec, k, T)
                return
            rec.record(k, mean[:1], np.sqrt(var[:1]), np.array([yhat]), np.array([e]), np.array([S]),
                       np.array([clamp]), gated, mean[None], var[None])
            if k + 1 == T:
                break
            if 1.0 / np.sum(w * w) < opt["resample_threshold"] * N:
                if opt["kernel_h"] > 0:
                    mean_w, root_w = weighted_mean_root(X, w)
                with mock.patch.object(fp_resampling, "random", lambda u_r=u[0]: u_r):
                    idx = fp_resampling.systematic_resample(w)
                X = X[idx]
                w = np.full(N, 1.0 / N)
                if opt["kernel_h"] > 0:
                    X = shrink(X, mean_w, root_w, opt["kernel_h"], draws.roughening(k)[0])
                elif opt["roughening"] > 0:
                    X = X + roughening_sd(X, opt["roughening"]) * draws.roughening(k)[0]
            X = m.step(X, i if sd_i is None else i + sd_i * eps_i[0], inputs.dt[k], temp)[0]
            if additive is not None:
                X = X + eps_q[0] @ additive(inputs.dt[k]).T
            hold = noise.hold(inputs.hold_var[k])
            if hold > 0:
                X = X + hold_spread(m, mean, i, inputs.dt[k], temp, hold) * draws.hold(k)[0]
            clamp = _clamp_one(X)
            if not np.all(np.isfinite(X)):
                rec.fail(k + 1, np.ones(1, bool))
                _KalmanReference._freeze_rest(rec, k + 1, T)
                return


def _clamp_one(X: np.ndarray) -> bool:
    z = X[:, 0]
    out = (z < 0.0) | (z > 1.0)
    np.clip(z, 0.0, 1.0, out=z)
    return bool(out.any())


class ReferenceCKF(_KalmanReference):
    """Per-run CKF on ``filterpy.kalman.CubatureKalmanFilter``; the update's cubature points are redrawn from the
    prior ``(x⁻, P⁻)`` (Arasaratnam & Haykin's measurement update), ``Q_k``, ``R_k`` from ``B``, ``D`` at the mean."""

    name = "ckf"

    def _filter(self, inputs, x0, P0, rec):
        m, T, n, opt = self.model, inputs.n, self.n, self.options

        def fx(s, dt, i, temp):
            return m.step(s, i, dt, temp)[0]

        def hx(s, i, temp):
            return np.atleast_1d(m.output(s, i, temp)[0])

        ckf = CubatureKalmanFilter(dim_x=n, dim_z=1, dt=1.0, hx=hx, fx=fx)
        ckf.x = x0[:, None].copy()  # filterpy's CKF keeps a column state
        ckf.P = P0.copy()
        ckf.sigmas_f = spherical_radial_sigmas(ckf.x, ckf.P)
        gate = self.gate(1)
        floors = (opt["psd_floor"], opt["psd_rel_floor"])
        for k in range(T):
            i, v = inputs.current[0, k], inputs.voltage[0, k]
            temp = None if inputs.temp is None else inputs.temp[0, k]
            D = m.output(ckf.x[:, 0], i, temp, jac=True)[2]
            x_prior, P_prior = ckf.x.copy(), ckf.P.copy()
            ckf.update(np.array([v]), R=np.array([[float(self.noise.R(D, ()))]]), hx_args=(i, temp))
            e, S = float(np.ravel(ckf.y)[0]), float(ckf.S[0, 0])
            yhat = float(np.mean(ckf.sigmas_h[:, 0]))
            gated = gate(np.array([e * e / S]))
            if gated[0]:
                ckf.x, ckf.P = x_prior, P_prior
            ckf.P, clamped, failed = self._guard(rec, k, ckf.x[:, 0], ckf.P, e * e / S)
            if failed:
                self._freeze_rest(rec, k, T)
                return
            rec.record(k, ckf.x[0], np.sqrt(ckf.P[0, 0])[None], np.array([yhat]), np.array([e]), np.array([S]),
                       clamped, gated, ckf.x[:, 0][None], np.diag(ckf.P)[None])
            if k + 1 < T:
                ckf.Q = self.noise.Q(m.step(ckf.x[:, 0], i, inputs.dt[k], temp, jac=True)[2], inputs.dt[k],
                                     inputs.hold_var[k])
                ckf.predict(dt=inputs.dt[k], fx_args=(i, temp))
                ckf.P = repair_psd(symmetrise(ckf.P)[None], *floors)[0][0]
                if not self._predicted_ok(rec, k + 1, T, ckf.x, ckf.P):
                    return
                ckf.sigmas_f = spherical_radial_sigmas(ckf.x, ckf.P)


class ReferenceJointEKF(JointParameters, ReferenceEKF):
    """Per-run joint EKF: :class:`ReferenceEKF` (filterpy) on ``[x, cap, ΔR0]`` with the parameters' random walks."""

    name = "dual"
    defaults = JointParameters.defaults

    def __init__(self, model, noise=None, **options):
        self.setup_joint(model, noise, options)

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        return self.finish_joint(ReferenceEKF._run(self, inputs, x0, P0, seed), inputs)

    def process_cov(self, B, dt, hold_var=0.0):
        return self.noise.Q(B, dt, hold_var) + self.param_cov(dt)


class ReferenceAEKF(_KalmanReference):
    """Per-run adaptive EKF: the textbook EKF with the fading-memory Sage–Husa recursions of :mod:`.aekf`, scalar
    code, one trajectory at a time."""

    name = "aekf"
    linearises_output = True  # a prior mean where the OCV is held flat is moved (base.out_of_held_ocv)
    defaults = AdaptiveEKF.defaults

    def _filter(self, inputs, x0, P0, rec):
        m, T, n, opt = self.model, inputs.n, self.n, self.options
        d = 1.0 - opt["forgetting"]
        lo, hi = opt["r_min_ratio"], opt["r_max_ratio"]
        x, P = x0.copy(), P0.copy()
        r_hat, q_hat = None, np.zeros((n, n))
        gate = self.gate(1)
        for k in range(T):
            i, v = inputs.current[0, k], inputs.voltage[0, k]
            temp = None if inputs.temp is None else inputs.temp[0, k]
            y, H, D = m.output(x, i, temp, jac=True)
            r_nom = float(self.noise.R(D, ()))
            if r_hat is None:
                r_hat = r_nom
            Rk = r_hat if opt["adapt_r"] else r_nom
            hph = float(H @ P @ H)
            S = hph + Rk
            e = float(v - y)
            gated = gate(np.array([e * e / S]))
            K = np.zeros(n) if gated[0] else P @ H / S
            x = x + K * e
            A = np.eye(n) - np.outer(K, H)
            P = A @ P @ A.T + Rk * np.outer(K, K)
            P, clamped, failed = self._guard(rec, k, x, P, e * e / S)
            if failed:
                self._freeze_rest(rec, k, T)
                return
            rec.record(k, x[:1], np.sqrt(P[0, 0])[None], np.atleast_1d(y), np.array([e]), np.array([S]), clamped,
                       gated, x[None], np.diag(P)[None])
            if not gated[0]:
                r = (1.0 - d) * r_hat + d * (e * e - hph)
                if r < lo * r_nom:  # Sage–Husa's estimate lost positivity: its biased form
                    r = (1.0 - d) * r_hat + d * e * e
                r_hat = min(max(r, lo * r_nom), hi * r_nom)
                q_hat = (1.0 - d) * q_hat + d * np.outer(K * e, K * e)
            if k + 1 < T:
                x, F, B = m.step(x, i, inputs.dt[k], temp, jac=True)
                Q = self.noise.Q(B, inputs.dt[k], inputs.hold_var[k]) + (q_hat if opt["adapt_q"] else 0.0)
                P = symmetrise(F @ P @ F.T + Q)
                if not self._predicted_ok(rec, k + 1, T, x, P):
                    return


class ReferenceHInf(_KalmanReference):
    """Per-run extended H∞ filter in Simon's printed form (2006, eq. 11.89): ``A = I − θ S̄ P + Hᵀ R⁻¹ H P``
    inverted with ``numpy.linalg.inv``, ``K = P A⁻¹ Hᵀ R⁻¹``, ``P⁺ = P A⁻¹``; θ capped per step as in :mod:`.hinf`."""

    name = "hinf"
    linearises_output = True  # a prior mean where the OCV is held flat is moved (base.out_of_held_ocv)
    defaults = HInfinityFilter.defaults

    def _filter(self, inputs, x0, P0, rec):
        m, T, n, opt = self.model, inputs.n, self.n, self.options
        Sbar = np.zeros((n, n))
        Sbar[0, 0] = 1.0
        x, P = x0.copy(), P0.copy()
        gate = self.gate(1)
        for k in range(T):
            i, v = inputs.current[0, k], inputs.voltage[0, k]
            temp = None if inputs.temp is None else inputs.temp[0, k]
            y, H, D = m.output(x, i, temp, jac=True)
            Rk = float(self.noise.R(D, ()))
            PH = P @ H
            S = float(H @ PH) + Rk
            e = float(v - y)
            gated = gate(np.array([e * e / S]))
            if not gated[0]:
                pzz_kalman = P[0, 0] - PH[0] * PH[0] / S  # the Kalman posterior's SOC variance
                theta = min(opt["theta"], opt["feasibility_margin"] / pzz_kalman)
                if opt["prior_cap"]:  # the update leaves the SOC no wider than its prior P[0, 0]
                    theta = min(theta, max(1.0 / pzz_kalman - 1.0 / P[0, 0], 0.0))
                A = np.eye(n) - theta * Sbar @ P + np.outer(H, H) @ P / Rk
                P_new = P @ np.linalg.inv(A)
                x = x + P_new @ H / Rk * e
                P = P_new
            P, clamped, failed = self._guard(rec, k, x, P, e * e / S)
            if failed:
                self._freeze_rest(rec, k, T)
                return
            rec.record(k, x[:1], np.sqrt(P[0, 0])[None], np.atleast_1d(y), np.array([e]), np.array([S]), clamped,
                       gated, x[None], np.diag(P)[None])
            if k + 1 < T:
                x, F, B = m.step(x, i, inputs.dt[k], temp, jac=True)
                P = symmetrise(F @ P @ F.T + self.noise.Q(B, inputs.dt[k], inputs.hold_var[k]))
                if not self._predicted_ok(rec, k + 1, T, x, P):
                    return


def cholupdate_one(L: np.ndarray, u: np.ndarray, sign: float, floor: float) -> np.ndarray:
    """Textbook rank-one update/downdate of one lower Cholesky factor (Golub & Van Loan §6.5.4), column by column."""
    L, u = L.copy(), u.copy()
    n = L.shape[0]
    for j in range(n):
        r2 = L[j, j] ** 2 + u[j] ** 2 if sign > 0 else (L[j, j] - u[j]) * (L[j, j] + u[j])
        r = np.sqrt(max(r2, floor))
        c, s = r / L[j, j], u[j] / L[j, j]
        L[j, j] = r
        for i in range(j + 1, n):
            L[i, j] = (L[i, j] + sign * s * u[i]) / c
            u[i] = c * u[i] - s * L[i, j]
    return L


class ReferenceSRUKF(_KalmanReference):
    """Per-run square-root UKF (van der Merwe & Wan 2001, Algorithm 3.1): ``scipy.linalg.qr`` of the weighted
    deviations and ``√Q``, :func:`cholupdate_one`, the model evaluated one sigma point at a time."""

    name = "srukf"
    defaults = UKF.defaults

    def _filter(self, inputs, x0, P0, rec):
        m, T, n, opt = self.model, inputs.n, self.n, self.options
        lam, Wm, Wc = merwe_weights(n, opt["alpha"], opt["beta"], opt["kappa"])
        gamma = np.sqrt(n + lam)
        floor = opt["psd_floor"]
        x, L = x0.copy(), scipy.linalg.cholesky(P0, lower=True)
        gate = self.gate(1)

        def points(x, L):
            return np.array([x] + [x + gamma * L[:, j] for j in range(n)] + [x - gamma * L[:, j] for j in range(n)])

        for k in range(T):
            i, v = inputs.current[0, k], inputs.voltage[0, k]
            temp = None if inputs.temp is None else inputs.temp[0, k]
            X = points(x, L)
            Y = np.array([float(m.output(p, i, temp)[0]) for p in X])
            Rk = float(self.noise.R(m.output(x, i, temp, jac=True)[2], ()))
            yhat = float(Wm @ Y)
            S = float(Wc @ (Y - yhat) ** 2) + Rk
            Pxy = sum(Wc[j] * (X[j] - x) * (Y[j] - yhat) for j in range(2 * n + 1))
            e = v - yhat
            gated = gate(np.array([e * e / S]))
            if not gated[0]:
                K = Pxy / S
                x = x + K * e
                L = cholupdate_one(L, K * np.sqrt(S), -1.0, floor)
            clamped = project_soc(x[None], L[None], factor=True)
            var = np.sum(L * L, axis=1)
            if rec.fail(k, diverged(x[None], var[:1], np.array([e * e / S]), opt["var_max"], opt["nis_max"])
                        | ~np.all(np.isfinite(var)))[0]:
                self._freeze_rest(rec, k, T)
                return
            rec.record(k, x[:1], np.sqrt(var[:1]), np.array([yhat]), np.array([e]), np.array([S]), clamped, gated,
                       x[None], var[None])
            if k + 1 < T:
                X = points(x, L)
                Xf = np.array([m.step(p, i, inputs.dt[k], temp)[0] for p in X])
                Q = self.noise.Q(m.step(x, i, inputs.dt[k], temp, jac=True)[2], inputs.dt[k], inputs.hold_var[k])
                x = Wm @ Xf
                w, V = scipy.linalg.eigh(Q)
                rows = np.vstack([np.sqrt(Wc[j]) * (Xf[j] - x) for j in range(1, 2 * n + 1)]
                                 + [np.sqrt(max(w[j], 0.0)) * V[:, j] for j in range(n)])
                Rf = scipy.linalg.qr(rows, mode="r")[0][:n]
                L = (Rf * np.where(np.diag(Rf) < 0, -1.0, 1.0)[:, None]).T
                for j in range(n):
                    L[j, j] = max(L[j, j], np.sqrt(floor))
                L = cholupdate_one(L, np.sqrt(abs(Wc[0])) * (Xf[0] - x), 1.0 if Wc[0] >= 0 else -1.0, floor)
                if not self._predicted_ok(rec, k + 1, T, x, L):
                    return


#: name -> reference class
REFERENCES = {"ekf": ReferenceEKF, "ukf": ReferenceUKF, "pf": ReferencePF, "ckf": ReferenceCKF,
              "dual": ReferenceJointEKF, "aekf": ReferenceAEKF, "hinf": ReferenceHInf, "srukf": ReferenceSRUKF}
