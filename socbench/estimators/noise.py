"""Sensor noise and the filter covariances derived from it, so nobody tunes Q and R by trial and error.

A current sensor with white noise ``n_k ~ N(0, σ_I²)`` (and a constant offset ``b ~ N(0, σ_b²)``) and a voltage
sensor with white noise ``v_k ~ N(0, σ_V²)`` enter the model through the input. With the measured current
``I_m = I + n`` the truth follows ``x_{k+1} = f(x_k, I_m − n_k) ≈ f(x_k, I_m) − B_k n_k`` and
``y_k = h(x_k, I_m − n_k) + v_k ≈ h(x_k, I_m) − D_k n_k + v_k`` with ``B = ∂f/∂I``, ``D = ∂h/∂I``. Hence::

    Q_k = (σ_I² + σ_b²) · B_k B_kᵀ  +  σ_hold,k² · diag(B_k²)  +  diag(σ_walk²) · dt_k / dt   (process noise)
    R_k = σ_V² + (σ_I² + σ_b²) · D_k²                                                          (measurement noise)

``σ_hold,k²`` is zero at a sampled step; across a logger pause it is the variance of the current the zero-order hold
did not see (:func:`socbench.segments.hold_var`), so the SOC band widens by what that current could have moved. It
enters each state on its own (``diag``): over a pause much longer than the RC time constants, the charge that flowed
(the SOC) and the current near its end (the RC voltages) are different unknowns. Entered as one (``B Bᵀ``), the
first voltage after the pause would pin both from one number: the band collapsed at once around a SOC read through
the polarisation, and missed the truth after the pause on random paused drives (seen while writing
``tests/test_hold_var.py``).

For every model ``B[0] = −η·dt/(3600 Q)`` (= −η κ), so the SOC entry is ``(κ σ_I)²`` per step: the random walk of
coulomb counting; the RC entries are ``(b_j σ_I)²`` with ``b_j = R_j(1 − e^{−dt/τ_j})``, fully correlated with the SOC
entry (one noise source). Two approximations, said out loud:

* the same ``n_k`` also enters ``y_k`` (``E[w_k e_kᵀ] = B D σ_I²``); this cross-covariance is ignored, it is
  ``O(R0·κ)`` and far below ``σ_V``;
* a constant offset is not white: here it only widens Q and R like extra white noise. The coulomb counter carries its
  exact growth ``(σ_b · Σ η dt / 3600 Q)²``; filters that must track a real offset need the ``current_bias`` effect.

``soc_walk_sd`` / ``state_walk_sd`` are optional allowances for model error (per sample period ``dt``);
``walk_sd`` gives one walk SD per state instead (e.g. the coloured model-error state of
:class:`~socbench.models.effects.ModelError`, whose walk the recipe of :mod:`socbench.estimators.model_error` sets).

``weight_extra_var`` widens the likelihood a particle filter weighs its particles with, and nothing else::

    R_w,k = R_k + weight_extra_var   (after the run's first assimilated sample, which has R_w = R)

for a voltage error that ``σ_V`` counts as white although it is correlated over time (the model-error recipe's
inflated form sets it). ``R_k`` stays the per-sample spread of the innovation (its NIS, its band); ``R_w`` counts the
correlated part as much as a Gauss–Markov error of variance ``σ_c²`` and correlation time ``τ`` informs: the first
sample one full look (``1/σ_c²``), every later one ``(1 − ρ)/(1 + ρ)/σ_c² ≈ dt/(2τ σ_c²)`` (``ρ = e^{−dt/τ}``; the
Fisher information of the mean of an AR(1) series), i.e. a variance ``σ_c²·(1 + 2τ/dt)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError


@dataclass(frozen=True)
class SensorNoise:
    """Sensor noise of a measurement chain (standard deviations per sample).

    voltage_sd       V, white noise on the terminal-voltage reading
    current_sd       A, white noise on the current reading
    dt               s, the sample period the walk allowances refer to
    current_bias_sd  A, standard deviation of a constant current offset
    soc_walk_sd      SOC random walk per ``dt`` for model error (fraction; 0 = none)
    state_walk_sd    random walk per ``dt`` on every other state (model units; 0 = none)
    walk_sd          one random-walk SD per ``dt`` for the model's states, in state order (replaces the two above
                     when given); states beyond it (an estimator's own parameter states, appended after the model's,
                     which carry their own walk) get none
    weight_extra_var V², added to R in a particle filter's weights only (module docstring; 0 = none)
    """

    voltage_sd: float
    current_sd: float
    dt: float = 1.0
    current_bias_sd: float = 0.0
    soc_walk_sd: float = 0.0
    state_walk_sd: float = 0.0
    walk_sd: tuple = ()
    weight_extra_var: float = 0.0

    def __post_init__(self):
        for name in ("voltage_sd", "current_sd", "current_bias_sd", "soc_walk_sd", "state_walk_sd",
                     "weight_extra_var"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ConfigError(f"SensorNoise.{name} must be a finite number >= 0, got {v!r}")
        walk = tuple(float(v) for v in np.ravel(self.walk_sd))
        if not all(np.isfinite(v) and v >= 0 for v in walk):
            raise ConfigError(f"SensorNoise.walk_sd must hold finite numbers >= 0, got {walk!r}")
        object.__setattr__(self, "walk_sd", walk)
        if not np.isfinite(self.dt) or self.dt <= 0:
            raise ConfigError(f"SensorNoise.dt must be > 0, got {self.dt!r}")
        if self.voltage_sd == 0 and self.current_sd == 0:
            raise ConfigError("SensorNoise needs voltage_sd > 0 or current_sd > 0 (R would be 0)")

    # ------------------------------------------------------------------ derived quantities
    @property
    def input_var(self) -> float:
        """Variance with which the current reading enters Q and R (white noise plus offset)."""
        return self.current_sd**2 + self.current_bias_sd**2

    @property
    def has_walk(self) -> bool:
        return self.soc_walk_sd > 0 or self.state_walk_sd > 0 or any(v > 0 for v in self.walk_sd)

    def walk_var(self, n_states: int, dt) -> np.ndarray:
        """Diagonal random-walk allowance ``(…, n)`` for steps ``dt``."""
        if self.walk_sd:
            if len(self.walk_sd) > n_states:
                raise ConfigError(f"SensorNoise.walk_sd has {len(self.walk_sd)} entries for a model with {n_states} "
                                  "states")
            sd = np.zeros(n_states)
            sd[: len(self.walk_sd)] = self.walk_sd
        else:
            sd = np.full(n_states, self.state_walk_sd)
            sd[0] = self.soc_walk_sd
        return sd**2 * (np.asarray(dt, dtype=float)[..., None] / self.dt)

    def process_cov(self, B, dt, input_var: float | None = None) -> np.ndarray:
        """``Q_k = σ² B Bᵀ + walk``: ``B`` is ``(…, n)``, the result ``(…, n, n)``."""
        B = np.asarray(B, dtype=float)
        var = self.input_var if input_var is None else input_var
        Q = var * B[..., :, None] * B[..., None, :]
        if self.has_walk:
            w = self.walk_var(B.shape[-1], dt)
            idx = np.arange(B.shape[-1])
            Q[..., idx, idx] += w
        return Q

    def measurement_var(self, D) -> np.ndarray:
        """``R_k = σ_V² + σ² D²`` (shape of ``D``)."""
        D = np.asarray(D, dtype=float)
        return self.voltage_sd**2 + self.input_var * D * D


def hold_cov(B, hold_var) -> np.ndarray:
    """``σ_hold²·diag(B²)`` ``(…, n, n)``: the unknown current over a logger pause (module docstring), each state's
    share independent of the others' (0 where ``hold_var`` is 0)."""
    B = np.asarray(B, dtype=float)
    out = np.zeros(B.shape + B.shape[-1:])
    if np.any(hold_var):
        idx = np.arange(B.shape[-1])
        out[..., idx, idx] = hold_var * B * B
    return out


#: Used when an estimator is given no noise spec: a 10 mV voltage reading and a 0.1 A current reading.
DEFAULT_NOISE = SensorNoise(voltage_sd=0.01, current_sd=0.1)


class NoiseModel:
    """Q and R for one estimator: derived from a :class:`SensorNoise` (plus the model's own random walks,
    ``walk_var`` per second, e.g. an effect state declared to drift), or overridden.

    ``Q`` override: an ``(n, n)`` array (per step, constant) or a callable ``Q(B, dt) -> (…, n, n)``.
    ``R`` override: a scalar variance [V²] or a callable ``R(D) -> (…)``.
    """

    def __init__(self, noise: SensorNoise | None, n_states: int, Q=None, R=None, walk_var=None):
        self.sensor = noise if noise is not None else DEFAULT_NOISE
        if not isinstance(self.sensor, SensorNoise):
            raise ConfigError(f"noise must be a SensorNoise, got {type(noise).__name__}")
        self.n = n_states
        if Q is not None and not callable(Q):
            Q = np.asarray(Q, dtype=float)
            if Q.shape != (n_states, n_states) or not np.all(np.isfinite(Q)):
                raise ConfigError(f"Q must be a finite ({n_states}, {n_states}) array, got shape {Q.shape}")
            if np.min(np.linalg.eigvalsh(0.5 * (Q + Q.T))) < -1e-12 * max(np.abs(Q).max(), 1e-300):
                raise ConfigError("Q must be positive semi-definite")
        if R is not None and not callable(R):
            R = float(R)
            if not np.isfinite(R) or R <= 0:
                raise ConfigError(f"R must be a variance > 0 [V²], got {R!r}")
        self.Q_override = Q
        self.R_override = R
        w = None if walk_var is None else np.asarray(walk_var, dtype=float)
        self.walk = w if w is not None and np.any(w > 0) else None

    @property
    def needs_B(self) -> bool:
        return self.Q_override is None or callable(self.Q_override)

    @property
    def needs_D(self) -> bool:
        return self.R_override is None or callable(self.R_override)

    def hold(self, hold_var):
        """The share of the hold's variance ``hold_var`` (scalar or array, :func:`socbench.segments.hold_var`) this
        noise takes: all of it, or none under a ``Q`` override (taken as given). For the filters that do not build
        ``Q`` through :meth:`Q` (the particle filters)."""
        return hold_var if self.Q_override is None else np.zeros_like(hold_var)

    def Q(self, B, dt, hold_var=0.0) -> np.ndarray:
        """``Q_k`` of a step of length ``dt``; ``hold_var`` [A²] the current variance the zero-order hold misses over
        it (:func:`socbench.segments.hold_var`: nonzero across a logger pause), added as ``hold_var·diag(B²)``
        (:func:`hold_cov`; an override is taken as given)."""
        if self.Q_override is None:
            Q = self.sensor.process_cov(B, dt) + hold_cov(B, hold_var)
            if self.walk is not None:  # the model's own random walks (an effect state that may drift)
                idx = np.arange(self.n)
                Q[..., idx, idx] += self.walk * np.asarray(dt, dtype=float)[..., None]
            return Q
        if callable(self.Q_override):
            return np.asarray(self.Q_override(B, dt), dtype=float)
        return self.Q_override

    def weight_extra(self, looked) -> np.ndarray:
        """What a particle filter adds to ``R_k`` in its weights, per run (module docstring): nothing before the run's
        first assimilated sample (``looked`` False: that sample is one full look at the error; a sample the innovation
        gate rejects is none), then ``weight_extra_var``."""
        return np.where(looked, self.sensor.weight_extra_var, 0.0)

    def R(self, D, shape=()) -> np.ndarray:
        if self.R_override is None:
            return self.sensor.measurement_var(D)
        if callable(self.R_override):
            return np.asarray(self.R_override(D), dtype=float)
        return np.full(shape, self.R_override)
