"""Residual signatures of the effects a model lacks (ECM_SPEC §9): regress the residual on each effect's regressors.

Every signature is the *linearised* effect: what adding the effect to the current model would change in the output,
to first order, along the simulated trajectory (SOC ``z``, OCV slope ``U'(z)``, over-potential ``η = U(z) − y_model``).
Each is fitted by ordinary least squares together with one constant per record (an OCV offset is not an effect), over
a small grid of its non-linear parameter where it has one, and scored by the share of the residual variance it explains
beyond the constants: ``R² = 1 − SSE_effect / SSE_constant`` (0 when it explains nothing). The best grid point and the
fitted coefficients are the starting guess of the bounded non-linear fit (:mod:`socbench.diagnose.search`).

==================== ============================================================== ==========================
effect               regressor (first order Δy)                                      guess from the coefficient
==================== ============================================================== ==========================
temperature          ``−(k(T; E_a) − 1)·η`` (|I|-scaled × temperature-scaled),       E_a: grid; dU/dT = β
                     ``(T − T_ref)`` (entropic)
hysteresis           ``h_γ(t)`` (sign of recent net charge, Plett's h with unit M),   M = β_h, M0 = β_s; γ, h0: grid
                     ``s(t)``
capacity             ``U'(z)·Ah(t)/Q`` (Ah throughput); with ``r_growth`` bounded     cap = 1 − β_Ah,
                     also ``y_model − U(z)`` (the over-potential the growth scales)   r_growth = β_η
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


class Residuals:
    """The trajectories of one model on several records, stacked: every regressor is computed record by record
    (integrals run from each record's start) and concatenated; each record gets its own constant (an OCV or sensor
    offset between records is not an effect). ``rows`` (a mask over the concatenated samples) keeps only those
    samples in every regression: the regressors still run over whole records."""

    def __init__(self, trajectories, rows=None):
        self.trajs = list(trajectories)
        self.rows = rows
        self.r = self.cat(lambda tr: tr.residual)
        sizes = [tr.profile.n for tr in self.trajs]
        offsets = np.zeros((sum(sizes), len(sizes)))
        k = 0
        for j, n in enumerate(sizes):
            offsets[k:k + n, j] = 1.0
            k += n
        offsets = self._pick(offsets)
        self.offsets = offsets[:, offsets.any(axis=0)]

    def _pick(self, a):
        return a if self.rows is None else a[self.rows]

    def cat(self, fn) -> np.ndarray:
        """``fn(trajectory)`` of every record, concatenated along time (the first axis), on the kept rows."""
        return self._pick(np.concatenate([np.asarray(fn(tr)) for tr in self.trajs], axis=0))

    def lstsq(self, target, cols):
        """``(sse, coef)`` of ``target`` on [record constants, cols...]; ``coef`` holds the columns' coefficients
        after one leading entry (so ``coef[1]`` is the first column's, as with a single constant)."""
        A = np.column_stack([self.offsets] + list(cols))
        coef, *_ = np.linalg.lstsq(A, target, rcond=None)
        e = target - A @ coef
        m = self.offsets.shape[1]
        return float(e @ e), np.r_[0.0, coef[m:]]


def _r2(sse, sse_null):
    return max(0.0, 1.0 - sse / sse_null) if sse_null > 0 else 0.0


def _running_integral(values, dt):
    """``∫ values dt`` at each sample (zero-order hold, 0 at the first sample)."""
    out = np.zeros_like(values)
    out[1:] = np.cumsum(values[:-1] * dt)
    return out


def _linear(name, res, cols, sse_null, to_guess, regressor, bounds):
    """The signature of an effect linear in its regressors ``cols``: ``to_guess(β)`` maps their coefficients to the
    starting guess (clipped to ``bounds``)."""
    sse, coef = res.lstsq(res.r, cols)
    beta = coef[1:]
    guess = {k: float(np.clip(v, *bounds[k])) for k, v in to_guess(beta).items()}
    return Signature(name, _r2(sse, sse_null), guess, sum(b * c for b, c in zip(beta, cols)), regressor,
                     {"coef": [float(b) for b in beta]})


def _best_on_grid(res, fits, admissible=None):
    """The grid point of least SSE: ``fits`` yields ``(key, target, columns)``, each fitted as
    ``target ≈ [constants, columns] β`` by least squares; with ``admissible(β)`` only fits of the physical sign
    count. Returns ``(sse, β, key)`` or None when no grid point is admissible."""
    best = None
    for key, target, cols in fits:
        sse, coef = res.lstsq(target, cols)
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


def signatures(model, trajectories, bounds: dict, t_ref: float, rows=None) -> dict:
    """``{effect: Signature}`` on the trajectories of ``model`` over the records (a :class:`Trajectory` or a list of
    them; ``bounds[effect]`` clip the guesses); ``rows`` restricts the regressions to those samples (a fold's
    training samples: its starting guesses never see its held-out block)."""
    res = Residuals([trajectories] if isinstance(trajectories, Trajectory) else trajectories, rows)
    r = res.r
    i = res.cat(lambda tr: tr.profile.current_a)
    q = model.capacity_ah
    sse_null, _ = res.lstsq(r, [])
    out = {}
    du = res.cat(lambda tr: tr.ocv_slope)

    # Ah throughput, elapsed time, charge after charge segments, OCV-weighted time
    ah = res.cat(lambda tr: tr.profile.amp_hours())
    # the capacity effect's Δy: the fade's SOC drift and, where its resistance growth is fitted (bounded), the
    # grown over-potential g·(y_model − U(z)) of ageing
    if "r_growth" in bounds["capacity"]:
        out["capacity"] = _linear("capacity", res, [du * ah / q, res.cat(lambda tr: tr.y_model - tr.ocv)], sse_null,
                                  lambda b: {"cap0": 1.0 - b[0], "r_growth": b[1]}, "U'(z)·Ah/Q, y − U(z)",
                                  bounds["capacity"])
    else:
        out["capacity"] = _linear("capacity", res, [du * ah / q], sse_null, lambda b: {"cap0": 1.0 - b[0]},
                                  "U'(z)·Ah/Q", bounds["capacity"])
    elapsed = res.cat(lambda tr: tr.profile.time_s - tr.profile.time_s[0])
    out["current_bias"] = _linear("current_bias", res, [du * elapsed / (3600.0 * q)], sse_null,
                                  lambda b: {"b0": b[0]}, "U'(z)·t/(3600 Q)", bounds["current_bias"])
    ah_charge = res.cat(lambda tr: _running_integral(np.maximum(-tr.profile.current_a, 0.0), tr.profile.dt) / 3600.0)
    out["coulombic_efficiency"] = _linear("coulombic_efficiency", res, [du * ah_charge / q], sse_null,
                                          lambda b: {"eta_c": 1.0 + b[0]}, "U'(z)·Ah_charge/Q",
                                          bounds["coulombic_efficiency"])
    u1 = float(model.ocv(1.0))
    leak = res.cat(lambda tr: _running_integral(tr.ocv / u1, tr.profile.dt) / 3600.0)
    out["self_discharge"] = _linear("self_discharge", res, [du * leak], sse_null, lambda b: {"rate": -b[0]},
                                    "U'(z)·∫U/U(1)dt", bounds["self_discharge"])

    # hysteresis: Plett's h for a grid of (γ, h0) and the sign memory s_k (sgn I_k while moving, else s_{k−1}),
    # with M > 0 (the charge branch lies above the discharge branch)
    gam, h0 = np.meshgrid(GAMMA_GRID, H0_GRID, indexing="ij")
    gam, h0 = gam.ravel(), h0.ravel()
    hyst = Hysteresis(M=0.0, M0=0.0, gamma=gam, h0=h0)
    states = res.cat(lambda tr: _grid_states(hyst, tr.profile, model))
    hs = states[..., 0]
    moving = np.abs(i) > q / 100.0
    ss = np.where(moving, np.sign(i), states[:, 0, 1])
    best = _best_on_grid(res, ((g, r, [hs[:, g], ss]) for g in range(gam.size)), lambda coef: coef[1] > 0)
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
    rc = ExtraRC(R=1.0, log10_tau=LOG10_TAU_GRID)
    lp = res.cat(lambda tr: _grid_states(rc, tr.profile, model)[..., 0])
    best = _best_on_grid(res, ((g, r, [lp[:, g]]) for g in range(LOG10_TAU_GRID.size)), lambda coef: coef[1] < 0)
    if best is None:
        out["extra_rc"] = Signature("extra_rc", 0.0, {}, np.zeros_like(r), "LP_τ(I)")
    else:
        sse, coef, g = best
        b = bounds["extra_rc"]
        out["extra_rc"] = Signature("extra_rc", _r2(sse, sse_null),
                                    {"R": float(np.clip(-coef[1], *b["R"])), "log10_tau": float(LOG10_TAU_GRID[g])},
                                    coef[1] * lp[:, g], "LP_τ(I)", {"tau_s": float(10 ** LOG10_TAU_GRID[g])})

    # Butler–Volmer: fixed physical coefficient on asinh, free linear term; null = constant + linear
    has_temp = all(tr.profile.temperature_c is not None for tr in res.trajs)
    tk = res.cat(lambda tr: tr.profile.temperature_c if has_temp else np.full(tr.profile.n, 25.0)) + KELVIN
    gfac = n_cells(model) * 2.0 * R_GAS * tk / FARADAY
    sse_lin, _ = res.lstsq(r, [i])
    shapes = {i0: -gfac * np.arcsinh(i / (2.0 * i0)) for i0 in I0_OVER_Q_GRID * q}
    sse, coef, i0 = _best_on_grid(res, ((i0, r - shape, [i]) for i0, shape in shapes.items()))
    b = bounds["butler_volmer"]
    out["butler_volmer"] = Signature("butler_volmer", _r2(sse, sse_lin),
                                     {"I0": float(np.clip(i0, *b["I0"])), "dR": float(np.clip(coef[1], *b["dR"]))},
                                     shapes[i0] + coef[1] * i, "asinh(I/2I0) curvature", {"I0": float(i0)})

    # temperature: Arrhenius-scaled over-potential over the E_a grid, plus the entropic term
    if has_temp:
        eta = res.cat(lambda tr: tr.ocv - tr.y_model)
        temp = tk - KELVIN
        dtemp = temp - t_ref
        shapes = {ea: -(np.exp(ea / R_GAS * (1.0 / tk - 1.0 / (t_ref + KELVIN))) - 1.0) * eta for ea in EA_GRID}
        sse, coef, ea = _best_on_grid(res, ((ea, r - shape, [dtemp]) for ea, shape in shapes.items()))
        b = bounds["temperature"]
        out["temperature"] = Signature("temperature", _r2(sse, sse_null),
                                       {"Ea": float(ea), "dUdT": float(np.clip(coef[1], *b["dUdT"]))},
                                       shapes[ea] + coef[1] * dtemp, "−(k(T)−1)·η, T−T_ref",
                                       {"Ea": float(ea), "temp_range_c": [float(temp.min()), float(temp.max())]})
    return out
