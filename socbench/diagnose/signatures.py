"""Residual signatures of the effects a model lacks (ECM_SPEC §9): regress the residual on each effect's regressors.

Every signature is the *linearised* effect: what adding the effect to the current model would change in the output,
to first order, along the simulated trajectory (SOC ``z``, OCV slope ``U'(z)``, over-potential ``η = U(z) − y_model``).
Each is fitted by ordinary least squares together with a constant (an OCV offset is not an effect), over a small grid
of its non-linear parameter where it has one, and scored by the share of the residual variance it explains beyond the
constant: ``R² = 1 − SSE_effect / SSE_constant`` (0 when it explains nothing). The best grid point and the fitted
coefficients are the starting guess of the bounded non-linear fit (:mod:`socbench.diagnose.search`).

==================== ============================================================== ==========================
effect               regressor (first order Δy)                                      guess from the coefficient
==================== ============================================================== ==========================
temperature          ``−(k(T; E_a) − 1)·η`` (|I|-scaled × temperature-scaled),       E_a: grid; dU/dT = β
                     ``(T − T_ref)`` (entropic)
hysteresis           ``h_γ(t)`` (sign of recent net charge, Plett's h with unit M),   M = β_h, M0 = β_s; γ, h0: grid
                     ``s(t)``
capacity             ``U'(z)·Ah(t)/Q`` (Ah throughput)                               cap = 1 − β
current_bias         ``U'(z)·t/(3600 Q)`` (elapsed time, rests included)              b = β
coulombic_efficiency ``U'(z)·Ah_charge(t)/Q`` (steps after each charge)               η_c = 1 + β
self_discharge       ``U'(z)·∫U(z)/U(1) dt/3600`` (sag during rests)                  rate = −β
extra_rc             ``LP_τ(I)`` (low-pass current, τ grid)                           R = −β; τ: grid
butler_volmer        ``−N_s(2R_gT/F)·asinh(I/2I_0)`` (fixed coefficient), ``I``       I0: grid; dR = β_I
==================== ============================================================== ==========================

The Butler–Volmer signature is judged against a constant *and* a linear current term (a mere resistance error is not
curvature); the temperature signature needs the measured temperature column (``T_ref`` is the mean temperature of the
fit data), without one it is not a candidate.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..models.effects import FARADAY, KELVIN, R_GAS, ExtraRC, Hysteresis, n_cells
from ..profile import Profile

#: grids of the non-linear parameters
EA_GRID = np.array([0.0, 5e3, 10e3, 15e3, 20e3, 30e3, 40e3, 50e3, 60e3, 80e3, 100e3])
GAMMA_GRID = np.array([3.0, 10.0, 30.0, 100.0, 300.0])
H0_GRID = np.array([-1.0, 0.0, 1.0])
LOG10_TAU_GRID = np.linspace(0.5, 4.0, 15)
I0_OVER_Q_GRID = np.array([0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0])


@dataclass
class Signature:
    """One effect's signature on the residual: share explained, starting guess, the fitted first-order Δy."""

    effect: str
    r2: float
    guess: dict
    prediction: np.ndarray
    regressor: str
    detail: dict = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """What the signatures need from one open-loop simulation of the current model on a profile."""

    profile: Profile
    y_model: np.ndarray
    z: np.ndarray
    ocv: np.ndarray
    ocv_slope: np.ndarray

    @property
    def residual(self) -> np.ndarray:
        return self.profile.voltage_v - self.y_model

    @classmethod
    def simulate(cls, model, profile: Profile, soc0: float) -> Trajectory:
        sim = model.simulate(profile, soc0=soc0)
        u, du = model.ocv.value_and_slope(sim.soc)
        return cls(profile, sim.voltage_v, sim.soc, u, du)


def _lstsq(r, cols):
    """``(sse, coef)`` of r on [1, cols...]."""
    A = np.column_stack([np.ones_like(r)] + list(cols))
    coef, *_ = np.linalg.lstsq(A, r, rcond=None)
    e = r - A @ coef
    return float(e @ e), coef


def _r2(sse, sse_null):
    return max(0.0, 1.0 - sse / sse_null) if sse_null > 0 else 0.0


def _running_integral(values, dt):
    """``∫ values dt`` at each sample (zero-order hold, 0 at the first sample)."""
    out = np.zeros_like(values)
    out[1:] = np.cumsum(values[:-1] * dt)
    return out


def _linear_one(name, traj, col, sse_null, to_guess, regressor, bounds):
    sse, coef = _lstsq(traj.residual, [col])
    guess = {k: float(np.clip(v, *bounds[k])) for k, v in to_guess(coef[1]).items()}
    return Signature(name, _r2(sse, sse_null), guess, coef[1] * col, regressor, {"coef": float(coef[1])})


def _best_on_grid(fits, admissible=None):
    """The grid point of least SSE: ``fits`` yields ``(key, target, columns)``, each fitted as
    ``target ≈ [1, columns] β`` by least squares; with ``admissible(β)`` only fits of the physical sign count.
    Returns ``(sse, β, key)`` or None when no grid point is admissible."""
    best = None
    for key, target, cols in fits:
        sse, coef = _lstsq(target, cols)
        if (admissible is None or admissible(coef)) and (best is None or sse < best[0]):
            best = (sse, coef, key)
    return best


def _grid_states(effect, profile, model) -> np.ndarray:
    """The states of ``effect`` (its parameters a grid ``(G,)``) over ``profile`` from its initial states, driven by
    the measured current: ``(T, G, ne)`` by :meth:`~socbench.models.effects.Effect.record_states` (prefix scans)."""
    grid = np.broadcast_shapes(*(np.shape(v) for v in effect.values.values()))
    e0 = np.array(np.broadcast_to(effect.initial(), grid + (effect.n_states,)))
    g = e0.shape[0]
    i = np.broadcast_to(profile.current_a[:-1, None], (profile.n - 1, g))
    return effect.record_states(e0, i, profile.dt[:, None], model)


def signatures(model, traj: Trajectory, bounds: dict, t_ref: float) -> dict:
    """``{effect: Signature}`` on the trajectory of ``model`` (``bounds[effect]`` clip the guesses)."""
    prof = traj.profile
    r = traj.residual
    i = prof.current_a
    dt = prof.dt
    q = model.capacity_ah
    sse_null, _ = _lstsq(r, [])
    out = {}
    du = traj.ocv_slope

    # Ah throughput, elapsed time, charge after charge segments, OCV-weighted time
    ah = prof.amp_hours()
    out["capacity"] = _linear_one("capacity", traj, du * ah / q, sse_null, lambda b: {"cap0": 1.0 - b},
                                  "U'(z)·Ah/Q", bounds["capacity"])
    elapsed = prof.time_s - prof.time_s[0]
    out["current_bias"] = _linear_one("current_bias", traj, du * elapsed / (3600.0 * q), sse_null,
                                      lambda b: {"b0": b}, "U'(z)·t/(3600 Q)", bounds["current_bias"])
    ah_charge = _running_integral(np.maximum(-i, 0.0), dt) / 3600.0
    out["coulombic_efficiency"] = _linear_one("coulombic_efficiency", traj, du * ah_charge / q, sse_null,
                                              lambda b: {"eta_c": 1.0 + b}, "U'(z)·Ah_charge/Q",
                                              bounds["coulombic_efficiency"])
    u1 = float(model.ocv(1.0))
    leak = _running_integral(traj.ocv / u1, dt) / 3600.0
    out["self_discharge"] = _linear_one("self_discharge", traj, du * leak, sse_null, lambda b: {"rate": -b},
                                        "U'(z)·∫U/U(1)dt", bounds["self_discharge"])

    # hysteresis: Plett's h for a grid of (γ, h0) and the sign memory s_k (sgn I_k while moving, else s_{k−1}),
    # with M > 0 (the charge branch lies above the discharge branch)
    gam, h0 = np.meshgrid(GAMMA_GRID, H0_GRID, indexing="ij")
    gam, h0 = gam.ravel(), h0.ravel()
    states = _grid_states(Hysteresis(M=0.0, M0=0.0, gamma=gam, h0=h0), prof, model)
    hs = states[..., 0]
    moving = np.abs(i) > q / 100.0
    ss = np.where(moving, np.sign(i), states[:, 0, 1])
    best = _best_on_grid(((g, r, [hs[:, g], ss]) for g in range(gam.size)), lambda coef: coef[1] > 0)
    if best is None:
        out["hysteresis"] = Signature("hysteresis", 0.0, {}, np.zeros_like(r), "h_γ(t), s(t)")
    else:
        sse, coef, g = best
        b = bounds["hysteresis"]
        guess = {"M": float(np.clip(coef[1], *b["M"])), "M0": float(np.clip(coef[2], *b["M0"])),
                 "gamma": float(gam[g]), "h0": float(h0[g])}
        out["hysteresis"] = Signature("hysteresis", _r2(sse, sse_null), guess, coef[1] * hs[:, g] + coef[2] * ss,
                                      "h_γ(t), s(t)", {"gamma": float(gam[g]), "h0": float(h0[g])})

    # extra RC: unit-R branch voltage (low-pass current) over the τ grid, with R > 0 (the output falls by U_x)
    lp = _grid_states(ExtraRC(R=1.0, log10_tau=LOG10_TAU_GRID), prof, model)[..., 0]
    best = _best_on_grid(((g, r, [lp[:, g]]) for g in range(LOG10_TAU_GRID.size)), lambda coef: coef[1] < 0)
    if best is None:
        out["extra_rc"] = Signature("extra_rc", 0.0, {}, np.zeros_like(r), "LP_τ(I)")
    else:
        sse, coef, g = best
        b = bounds["extra_rc"]
        out["extra_rc"] = Signature("extra_rc", _r2(sse, sse_null),
                                    {"R": float(np.clip(-coef[1], *b["R"])), "log10_tau": float(LOG10_TAU_GRID[g])},
                                    coef[1] * lp[:, g], "LP_τ(I)", {"tau_s": float(10 ** LOG10_TAU_GRID[g])})

    # Butler–Volmer: fixed physical coefficient on asinh, free linear term; null = constant + linear
    tk = (prof.temperature_c if prof.temperature_c is not None else np.full(prof.n, 25.0)) + KELVIN
    gfac = n_cells(model) * 2.0 * R_GAS * tk / FARADAY
    sse_lin, _ = _lstsq(r, [i])
    shapes = {i0: -gfac * np.arcsinh(i / (2.0 * i0)) for i0 in I0_OVER_Q_GRID * q}
    sse, coef, i0 = _best_on_grid((i0, r - shape, [i]) for i0, shape in shapes.items())
    b = bounds["butler_volmer"]
    out["butler_volmer"] = Signature("butler_volmer", _r2(sse, sse_lin),
                                     {"I0": float(np.clip(i0, *b["I0"])), "dR": float(np.clip(coef[1], *b["dR"]))},
                                     shapes[i0] + coef[1] * i, "asinh(I/2I0) curvature", {"I0": float(i0)})

    # temperature: Arrhenius-scaled over-potential over the E_a grid, plus the entropic term
    if prof.temperature_c is not None:
        eta = traj.ocv - traj.y_model
        dtemp = prof.temperature_c - t_ref
        shapes = {ea: -(np.exp(ea / R_GAS * (1.0 / tk - 1.0 / (t_ref + KELVIN))) - 1.0) * eta for ea in EA_GRID}
        sse, coef, ea = _best_on_grid((ea, r - shape, [dtemp]) for ea, shape in shapes.items())
        b = bounds["temperature"]
        out["temperature"] = Signature("temperature", _r2(sse, sse_null),
                                       {"Ea": float(ea), "dUdT": float(np.clip(coef[1], *b["dUdT"]))},
                                       shapes[ea] + coef[1] * dtemp, "−(k(T)−1)·η, T−T_ref",
                                       {"Ea": float(ea), "temp_range_c": [float(prof.temperature_c.min()),
                                                                          float(prof.temperature_c.max())]})
    return out
