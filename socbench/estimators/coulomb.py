"""Coulomb counting: the open-loop baseline every filter has to beat.

SOC is counted with the *declared* capacity ``Q_d`` (option ``capacity_ah``, else the profile's
``meta.capacity_ah``, else the model's)::

    z_{k+1} = z_k − η(I_k) · I_k · dt_k / (3600 Q_d)

The model's other states run open loop beside it (``x⁻ = f(x, I_k)``), so the voltage it predicts, ``ŷ = h(x, I_k)``,
is scored like a filter's. No measurement ever corrects it. Its uncertainty grows like the random walk of the current
noise plus the drift of a current offset::

    P_{k+1} = F P_k Fᵀ + σ_I² B Bᵀ (+ walk)                 (white current noise; B[0] = −η dt/(3600 Q_d))
    soc_std_k = √(P_k[0, 0] + (σ_b · Σ_{j<k} η_j dt_j / (3600 Q_d))²)   (constant offset: exact linear growth)

``innovation_var = H P Hᵀ + R_k`` makes its NIS comparable with the filters'. ``socbench.kernels.filters.coulomb``
is the same loop compiled (``engine`` option).
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from .base import Estimator, restore
from .estimate import Estimate
from .noise import hold_cov
from .safety import clamp_soc, diverged, symmetrise


class CoulombCounter(Estimator):
    """Open-loop amp-hour counting with the declared capacity."""

    name = "coulomb"
    defaults = {"capacity_ah": None}

    def declared_capacity(self, profile_capacity=None) -> float:
        cap = self.options["capacity_ah"]
        if cap is None:
            cap = profile_capacity if profile_capacity else self.model.capacity_ah
        cap = float(cap)
        if not np.isfinite(cap) or cap <= 0:
            raise ConfigError(f"coulomb: capacity must be > 0 Ah, got {cap!r}")
        return cap

    def _run(self, inputs, x0, P0, seed=None) -> Estimate:
        return self._count(inputs, x0, P0, self.declared_capacity(inputs.capacity_ah))

    def _run_compiled(self, job, seed=None):
        from ..kernels.engine import parallel_runs
        from ..kernels.filters import coulomb

        cap = self.declared_capacity(job.inputs.capacity_ah)
        parallel_runs(coulomb, job.R, *job.model_args, *job.noise_args, self.model.capacity_ah / cap, *job.out_args)
        return job.finish({"capacity_ah": cap})

    def _count(self, inputs, x0, P0, capacity_ah: float) -> Estimate:
        m, noise = self.model, self.noise
        T = inputs.n
        ratio = m.capacity_ah / capacity_ah  # the model counts with its own capacity: rescale its SOC row
        bias_var = noise.sensor.current_bias_sd**2
        x, P = x0.copy(), P0.copy()
        x_good, P_good = x.copy(), P.copy()
        rec = self.recorder(inputs, x0, P0)
        drift = np.zeros(inputs.n_runs)  # Σ η dt / (3600 Q_d): the SOC error per ampere of offset
        no_gate = np.zeros(inputs.n_runs, dtype=bool)
        with np.errstate(all="ignore"):
            for k in range(T):
                ik, tk = inputs.current[:, k], inputs.temp_at(k)
                y, H, D = m.output(x, ik, tk, jac=True)
                Rk = noise.R(D, (inputs.n_runs,))
                S = np.einsum("ri,rij,rj->r", H, P, H) + Rk
                e = inputs.voltage[:, k] - y
                clamped = clamp_soc(x)
                var_z = P[:, 0, 0] + bias_var * drift**2
                failed = rec.fail(k, diverged(x, var_z, None, np.inf, np.inf))
                restore(x, x_good, failed)
                restore(P, P_good, failed)
                rec.record(k, x[:, 0], np.sqrt(var_z), y, e, S, clamped, no_gate, x, np.diagonal(P, 0, -2, -1))
                if k + 1 == T:
                    break
                z = x[:, 0]
                x, F, B = m.step(x, ik, inputs.dt[k], tk, jac=True)
                B[:, 0] *= ratio
                x[:, 0] = z + (x[:, 0] - z) * ratio
                drift -= B[:, 0]  # −∂z⁺/∂I = η dt/(3600 Q_d)
                if noise.Q_override is None:  # white part only: the offset is carried exactly by `drift`
                    Q = noise.sensor.process_cov(B, inputs.dt[k], noise.sensor.current_sd**2)
                    Q += hold_cov(B, inputs.hold_var[k])
                else:
                    Q = noise.Q(B, inputs.dt[k], inputs.hold_var[k])
                P = symmetrise(F @ P @ np.swapaxes(F, -1, -2) + Q)
                np.copyto(x_good, x, where=~failed[:, None])
                np.copyto(P_good, P, where=~failed[:, None, None])
        return rec.finish(self.name, m, {"capacity_ah": capacity_ah})
