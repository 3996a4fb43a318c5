"""Reference backends on filterpy 2.x: one trajectory at a time, the yardstick of the batched engines.

* :class:`ReferenceEKF` — ``filterpy.kalman.ExtendedKalmanFilter`` with a nonlinear ``predict_x`` (the model's step,
  which also sets ``F`` and ``Q``), ``update(z, HJacobian, Hx, R)`` (filterpy's Joseph form);
* :class:`ReferenceUKF` — ``filterpy.kalman.UnscentedKalmanFilter`` + ``MerweScaledSigmaPoints``;
* :class:`ReferencePF` — a per-run bootstrap filter whose resampling is ``filterpy.monte_carlo.systematic_resample``
  (the rare tempered updates reuse ``ParticleFilter.assimilate`` on a one-row slice: its rows are independent).

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
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from filterpy.monte_carlo import resampling as fp_resampling

from .base import Estimator, Inputs
from .estimate import Estimate
from .pf import ParticleFilter, log_likelihood, roughening_sd, shrink, weighted_mean_root
from .safety import clamp_soc, diverged, repair_psd, symmetrise
from .ukf import UKF


def _one_run(inputs: Inputs, r: int) -> Inputs:
    s = slice(r, r + 1)
    return Inputs(inputs.time_s, inputs.dt, inputs.current[s], inputs.voltage[s],
                  None if inputs.temp is None else inputs.temp[s], inputs.name)


def _stack(parts: list[Estimate], info: dict) -> Estimate:
    def cat(name):
        vals = [getattr(p, name) for p in parts]
        return None if vals[0] is None else np.concatenate(vals, axis=0)

    p0 = parts[0]
    return Estimate(p0.time_s, cat("soc"), cat("soc_std"), cat("v_pred"), cat("innovation"), cat("innovation_var"),
                    cat("failed"), cat("failed_at"), cat("clamped"), cat("gated"), cat("x"), cat("P_diag"),
                    p0.estimator, p0.model, p0.state_names, info)


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
        clamped = clamp_soc(x[None])  # x is a view of the filter's state: clamped in place
        failed = rec.fail(k, diverged(x[None], P[None], np.atleast_1d(nis), opt["var_max"], opt["nis_max"]))
        return P, clamped, bool(failed[0])

    @staticmethod
    def _freeze_rest(rec, k0: int, T: int):
        z = np.zeros(1)
        xs = None if rec.x is None else np.zeros((1, rec.x.shape[-1]))
        for k in range(k0, T):
            rec.record(k, z, z, z, z, z, np.zeros(1, bool), np.zeros(1, bool), xs, xs)


class _ModelEKF(ExtendedKalmanFilter):
    """filterpy's EKF whose prediction is the model's nonlinear step; ``u = (I, dt, T)``."""

    def __init__(self, model, noise):
        super().__init__(dim_x=model.n_states, dim_z=1)
        self.model = model
        self.noise = noise

    def predict_x(self, u=0):
        i, dt, temp = u
        xn, F, B = self.model.step(self.x[:, 0], i, dt, temp, jac=True)
        self.F = F
        self.Q = self.noise.Q(B, dt)
        self.x = xn[:, None]


class ReferenceEKF(_KalmanReference):
    """Per-run EKF on ``filterpy.kalman.ExtendedKalmanFilter``."""

    name = "ekf"

    def _filter(self, inputs, x0, P0, rec):
        m, T = self.model, inputs.n
        ekf = _ModelEKF(m, self.noise)
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
                ekf.predict(u=(i, inputs.dt[k], temp))
                ekf.P = symmetrise(ekf.P)
                if not (np.all(np.isfinite(ekf.x)) and np.all(np.isfinite(ekf.P))):
                    rec.fail(k + 1, np.ones(1, bool))
                    self._freeze_rest(rec, k + 1, T)
                    return


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
                ukf.Q = self.noise.Q(m.step(ukf.x, i, inputs.dt[k], temp, jac=True)[2], inputs.dt[k])
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
            Xs, ws, _ = self.assimilate(X[None], w[None], log_likelihood(v, Y, Rk)[None], gated, np.array([v]),
                                        np.array([i]), temp_1,
                                        lambda s, k=k: draws.stage(k, s))
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


#: name -> reference class
REFERENCES = {"ekf": ReferenceEKF, "ukf": ReferenceUKF, "pf": ReferencePF}
