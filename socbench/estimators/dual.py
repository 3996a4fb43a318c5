"""Joint SOC–capacity–R0 estimation: an EKF on the model augmented with two slowly varying parameter states.

Which form and why. Plett (J. Power Sources 134:277–292, 2004, "Extended Kalman filtering for battery management
systems of LiPB-based HEV battery packs, Part 3", §4–5) gives both a *joint* EKF (parameters appended to the state)
and a *dual* EKF (a state filter and a parameter filter side by side, the parameter filter linearised through the
total derivative ``dh/dθ``). This estimator, registered as ``dual``, is the **joint** form:

* capacity is observed only through the correlation between the SOC the voltage implies and the charge counted; one
  covariance over ``[x, cap, ΔR0]`` carries exactly that cross-covariance, where the dual form has to rebuild it with
  the recursive total derivative ``dx/dθ``;
* it is the EKF's own loop (Joseph update, the same safety tail, the same filterpy-style reference), on a model that
  is an ordinary :class:`~socbench.models.base.Model` (``augment(model, [Capacity(), ResistanceOffset()])``): no
  second filter to keep consistent, and the compiled EKF runs it unchanged.

Plett reports similar accuracy for both; the joint form's weakness, a covariance spanning very different scales, is
what the Joseph form, symmetrisation and the PSD repair of the EKF tail are for.

State and model (``Q_m`` the model's capacity, ``R0(z)`` its ohmic resistance)::

    x = [x_model, cap, ΔR0],   cap = Q_m / Q_true,   ΔR0 = R0_true − R0(z)
    z⁺ = z + cap·(z_model⁺ − z)                      (the capacity effect: the model's SOC increment scaled)
    y  = h_model(x_model, I) − ΔR0·I                 (ResistanceOffset)
    cap⁺ = cap + w_c,  ΔR0⁺ = ΔR0 + w_R               (random walks: Q gets capacity_walk_sd², r0_walk_sd² per
                                                       sensor period dt, on top of the sensor model's Q_k)

The filter is :class:`~.ekf.EKF` on that model. Initial covariance: the model's states as any filter's (``P0`` of the
model's size is accepted), then ``capacity_sd²`` and ``r0_sd²`` (default: half the model's R0 at 50 % SOC) on the
parameter states, uncorrelated.

Reported (``Estimate.info``, per run; the ``*_path`` entries over time, shape ``(R, T)``)::

    capacity_ah = Q_m / cap,          capacity_ah_3sigma = 3 Q_m σ_cap / cap²          (first-order, delta method)
    r0_ohm      = R0(ẑ) + ΔR0,         r0_ohm_3sigma      = 3 σ_ΔR0

``info["parameters"]`` names them; ``socbench estimate`` writes them to metrics.json.
``reference.ReferenceJointEKF`` runs filterpy's ``ExtendedKalmanFilter`` on the same augmented model.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ConfigError
from ..models.effects import Capacity, ResistanceOffset, augment
from .base import Estimator, Recorder, initial_cov
from .ekf import EKF
from .estimate import Estimate

#: what the joint estimator reports besides SOC (info keys; each with a ``_3sigma`` and a ``_path`` twin)
PARAMETERS = ("capacity_ah", "r0_ohm")


class JointParameters:
    """The configuration shared by the batched joint EKF and its reference: the augmented model, the parameter
    states' initial spread and random walk, and the read-out of capacity and R0 (module docstring)."""

    defaults = {"capacity_sd": 0.1, "r0_sd": None, "capacity_walk_sd": 1e-5, "r0_walk_sd": None}

    def setup_joint(self, model, noise, options):
        self.base = model
        aug = augment(model, [Capacity(), ResistanceOffset()])
        Estimator.__init__(self, aug, noise, **options)
        o = self.options
        self.r0_ref = float(np.asarray(model.p("R0", 0.5)[0]).ravel()[0])
        self.r0_sd = 0.5 * abs(self.r0_ref) if o["r0_sd"] is None else float(o["r0_sd"])
        self.r0_walk = 1e-3 * abs(self.r0_ref) if o["r0_walk_sd"] is None else float(o["r0_walk_sd"])
        for key, v in (("capacity_sd", o["capacity_sd"]), ("r0_sd", self.r0_sd)):
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"{self.name}: {key} must be > 0, got {v!r}")
        for key, v in (("capacity_walk_sd", o["capacity_walk_sd"]), ("r0_walk_sd", self.r0_walk)):
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"{self.name}: {key} must be >= 0, got {v!r}")
        nb = model.n_states
        self.cap_index, self.r0_index = nb, nb + 1
        self.param_walk = np.zeros(self.n)
        self.param_walk[nb:] = [o["capacity_walk_sd"] ** 2, self.r0_walk**2]

    def initial_cov(self, R: int, P0) -> np.ndarray:
        """The model's states as every filter sets them (``P0`` may be of the model's size), then the parameters."""
        n, nb = self.n, self.base.n_states
        if P0 is not None and np.ndim(P0) >= 1 and np.shape(P0)[-1] == n:
            return Estimator.initial_cov(self, R, P0)
        if hasattr(self.base, "initial_sd"):
            sd = np.asarray(self.base.initial_sd(self.options["soc0_sd"], self.options["state0_sd"]), dtype=float)
        else:
            sd = np.full(nb, self.options["state0_sd"])
            sd[0] = self.options["soc0_sd"]
        Pb = initial_cov(R, P0, nb, sd)
        P = np.zeros((R, n, n))
        P[:, :nb, :nb] = Pb
        P[:, nb, nb] = self.options["capacity_sd"] ** 2
        P[:, nb + 1, nb + 1] = self.r0_sd**2
        return P

    def param_cov(self, dt) -> np.ndarray:
        """The parameters' random-walk covariance over a step ``dt`` (diagonal, per sensor period)."""
        return np.diag(self.param_walk * (float(dt) / self.noise.sensor.dt))

    def parameters(self, est: Estimate, temp=None) -> dict:
        """Capacity and R0 with their 3σ, final ``(R,)`` and over time ``(R, T)``, from the stored states."""
        c, vc = est.x[..., self.cap_index], est.P_diag[..., self.cap_index]
        dr, vr = est.x[..., self.r0_index], est.P_diag[..., self.r0_index]
        q = self.base.capacity_ah
        with np.errstate(all="ignore"):
            cap = q / c
            cap3 = 3.0 * q * np.sqrt(np.maximum(vc, 0.0)) / (c * c)
        r0_model = np.asarray(self.base.p("R0", np.clip(est.soc, 0.0, 1.0), temp)[0], dtype=float)
        r0 = np.broadcast_to(r0_model, dr.shape) + dr
        r03 = 3.0 * np.sqrt(np.maximum(vr, 0.0))
        info = {"parameters": list(PARAMETERS)}
        for name, path, sd3 in (("capacity_ah", cap, cap3), ("r0_ohm", r0, r03)):
            info[name] = path[:, -1].copy()
            info[f"{name}_3sigma"] = sd3[:, -1].copy()
            info[f"{name}_path"] = path
            info[f"{name}_3sigma_path"] = sd3
        return info

    def finish_joint(self, est: Estimate, inputs) -> Estimate:
        info = {**est.info, **self.parameters(est, inputs.temp)}
        if not self.options["store_states"]:
            return dataclasses.replace(est, x=None, P_diag=None, info=info)
        return dataclasses.replace(est, info=info)

    def recorder(self, inputs, x0, P0) -> Recorder:
        """Always keeps the states: the parameter estimates are read from them (dropped after if not asked for)."""
        return Recorder(inputs, self.n, True, x0[:, 0], np.sqrt(P0[:, 0, 0]))


class JointEKF(JointParameters, EKF):
    """Batched joint EKF on ``[x, cap, ΔR0]`` (registered as ``dual``)."""

    name = "dual"
    defaults = {**JointParameters.defaults, **EKF.defaults}

    def __init__(self, model, noise=None, **options):
        self.setup_joint(model, noise, options)

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        return self.finish_joint(EKF._run(self, inputs, x0, P0, seed), inputs)

    def process_cov(self, x, B, dt, hold_var=0.0):
        return self.noise.Q(B, dt, hold_var) + self.param_cov(dt)

    def _run_compiled(self, job, seed=None):
        """The EKF kernel on the augmented model, the parameters' walk added to Q (:meth:`param_cov`)."""
        job.keep_states()
        job.add_walk(self.param_walk)
        est = EKF._run_compiled(self, job, seed)
        return None if est is None else self.finish_joint(est, job.inputs)
