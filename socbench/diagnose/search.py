"""Ranking, augmentation and refit: the forward search over the effects the model lacks.

One round, on the current model ``m`` (the base model, then the base model with the effects added so far):

1. simulate ``m`` on the training part and compute every effect's residual signature
   (:mod:`socbench.diagnose.signatures`): evidence, and the starting guess of its parameters;
2. for every candidate effect, fit its parameters — **together with the parameters of the effects already added**
   (the refit) — inside their physical bounds (:meth:`~socbench.models.effects.Effect.bounds`) on the training part,
   with :func:`socbench.identify.fit_parameters` (bounded least squares; the base model's parameters stay as fitted on
   the fit data);
3. judge it on every sample of the held-out part (the numbers reported as before/after):
   ``score = ln(MSE_before / MSE_after) − 2·p / n_eff`` (AIC per effective sample, ``p`` the parameters the
   effect adds, ``n_eff = N·(1 − ρ)/(1 + ρ)`` from the lag-1 autocorrelation ρ of the held-out residual,
   at least 100 — neighbouring residuals of a voltage fit are far from independent);
4. add the best-scoring effect if it lowers the held-out RMSE by at least ``min_gain`` (10 %) and the model is not
   already at the noise floor (held-out RMSE ≤ ``NOISE_FLOOR`` × the voltage noise measured in the data, see
   :func:`voltage_noise`: what is left cannot be told from sensor noise); else stop.

Every candidate gets its signature; the bounded fit (the expensive part) is run for the ``max_fits`` candidates whose
signatures explain the most residual variance (at least ``MIN_SIGNATURE_R2``): an effect that leaves no trace in the
residual cannot remove error from it. Candidates whose signature ties with the last one fitted (R² within 0.01, and
at least ``TIE_R2``) are fitted too: the SOC-drift effects share one regressor shape up to U(z)/U(1) and charge
weighting, so their signatures cannot rank them. The others are reported with their signature and no score.

The current-sensor bias gets one more piece of evidence from the data: where the record holds rests (at least
``REST_MIN_S`` of steady current below C/20), the true current there is zero, so the measured rest current *is* the
offset; ``b`` is then bounded to that mean ± 3 standard errors (± C/500 for the sensor's resolution).
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field

import numpy as np

from ..identify import fit_parameters
from ..models.effects import EFFECTS, augment, make_effect
from .data import Split
from .signatures import Trajectory, signatures

#: a rest: at least this long, current below C/20 and steady (within C/200 of its mean)
REST_MIN_S = 30.0
MIN_N_EFF = 100.0
#: a candidate whose signature explains less of the residual variance is not fitted
MIN_SIGNATURE_R2 = 0.01
#: candidates tied (within 0.01) with the last one fitted are fitted too when their R² is at least this
TIE_R2 = 0.1
#: no effect is added once the held-out RMSE is within this factor of the measured voltage noise. A base model fitted
#: on its own record leaves some error of its own beside the noise (the fit is not exact), and near the noise any
#: flexible effect can take up part of it. The factor is the critical value of that null distribution: over 75
#: synthetic cases without a hidden effect (rint/thevenin/dp on steps and pulses, 1 mV noise, seeds 200–214, which
#: neither the tests nor the benchmark use) the base model's held-out RMSE was 1.1–2.3 × the measured noise, and at
#: the former factor 2.0 four of them gained an effect; on 75 more (seeds 300–314) it was 1.2–2.4 × and none gained
#: one at 2.5. Every hidden effect of the tests and the benchmark starts at ≥ 7 × the noise.
NOISE_FLOOR = 2.5
#: compression of the training record for the fits (the held-out part is scored on every sample)
FIT_COMPRESS = {"max_step_s": 60.0}


@dataclass
class Candidate:
    effect: str
    score: float
    rmse_before: float
    rmse_after: float
    params: dict
    signature_r2: float
    evidence: str
    effects: tuple = ()  # the fitted effects (all of them) if this candidate were added
    seconds: float = 0.0
    held_residual: np.ndarray | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        score = round(float(self.score), 6) if np.isfinite(self.score) else None  # None: not fitted (valid JSON)
        return {"effect": self.effect, "score": score, "evidence": self.evidence,
                "signature_r2": round(float(self.signature_r2), 6), "rmse_v_before": self.rmse_before,
                "rmse_v_after": self.rmse_after, "params": self.params, "seconds": round(self.seconds, 3)}


def initial_soc(model, profile) -> float:
    """The reference SOC at the start when the data carry one, else the OCV inverse of the first voltage."""
    if profile.soc_ref is not None:
        return float(profile.soc_ref[0])
    return float(np.clip(model.ocv.inverse(profile.voltage_v[0]), 0.0, 1.0))


def held_out(model, split: Split):
    """``(rmse, residual)`` of ``model`` on every held-out sample (each profile simulated from its start)."""
    res = []
    for prof, k in split.held:
        sim = model.simulate(prof, soc0=initial_soc(model, prof))
        res.append((prof.voltage_v - sim.voltage_v)[k:])
    r = np.concatenate(res)
    r = np.where(np.isfinite(r), r, 10.0)
    return float(np.sqrt(np.mean(r * r))), r


def effective_samples(r: np.ndarray) -> float:
    """``N (1 − ρ)/(1 + ρ)`` with ρ the lag-1 autocorrelation, floored at :data:`MIN_N_EFF`."""
    rc = r - r.mean()
    den = float(rc @ rc)
    rho = float(rc[1:] @ rc[:-1]) / den if den > 0 else 0.0
    rho = min(max(rho, 0.0), 0.999999)
    return float(min(r.size, max(MIN_N_EFF, r.size * (1 - rho) / (1 + rho))))


def voltage_noise(profiles) -> float:
    """Voltage noise sd measured in the data: ``1.4826·MAD(Δ²v)/√6`` over samples where the current is the same at
    the sample and both neighbours and the step is uniform (there the cell's own voltage is smooth, so the second
    difference is noise). 0 when fewer than 50 such samples exist (e.g. a drive cycle)."""
    d2 = []
    for p in profiles:
        i, v, t = p.current_a, p.voltage_v, p.time_s
        if p.n < 3:
            continue
        tol = 1e-3 * float(np.max(np.abs(i))) + 1e-9
        same = (np.abs(i[1:-1] - i[:-2]) <= tol) & (np.abs(i[2:] - i[1:-1]) <= tol)
        dt = np.diff(t)
        same &= np.abs(dt[1:] - dt[:-1]) <= 1e-6 * dt[1:]
        d2.append((v[2:] - 2 * v[1:-1] + v[:-2])[same])
    d2 = np.concatenate(d2) if d2 else np.zeros(0)
    if d2.size < 50:
        return 0.0
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


def rest_current(profile, capacity_ah: float):
    """``(mean, standard error, seconds)`` of the measured current over the rests, or None without rests."""
    i = profile.current_a
    quiet = np.abs(i) < capacity_ah / 20.0
    edges = np.flatnonzero(np.diff(np.r_[0, quiet.astype(int), 0]))
    vals, weights = [], []
    for a, b in zip(edges[::2], edges[1::2]):
        if b - a < 2:
            continue
        seg = i[a:b]
        dur = profile.time_s[b - 1] - profile.time_s[a]
        if dur >= REST_MIN_S and np.all(np.abs(seg - seg.mean()) < capacity_ah / 200.0):
            vals.append(seg)
            weights.append(dur)
    if not vals:
        return None
    allv = np.concatenate(vals)
    se = float(np.std(allv) / np.sqrt(allv.size)) if allv.size > 1 else 0.0
    return float(allv.mean()), se, float(sum(weights))


class Search:
    """The forward search on one base model (see the module docstring)."""

    def __init__(self, base, split: Split, t_ref: float, candidates=None, min_gain: float = 0.10,
                 max_nfev: int = 20, max_steps: int = 3, max_fits: int = 4, h_ref: float = 0.0):
        self.base = base
        self.split = split
        self.t_ref = float(t_ref)
        self.candidates = list(candidates or EFFECTS)
        self.min_gain = min_gain
        self.max_nfev = max_nfev
        self.max_steps = max_steps
        self.max_fits = max_fits
        self.h_ref = float(h_ref)
        self.train = split.train
        self.soc0 = initial_soc(base, self.train)
        self.bounds = {name: EFFECTS[name]().bounds(base) for name in EFFECTS}
        self.bias_rest = rest_current(self.train, base.capacity_ah)
        self.noise_sd = voltage_noise([self.train] + [p for p, _ in split.held])
        if self.bias_rest is not None:
            mean, se, _ = self.bias_rest
            lo, hi = self.bounds["current_bias"]["b0"]
            half = 3.0 * se + base.capacity_ah / 500.0
            self.bounds["current_bias"] = {"b0": (max(lo, mean - half), min(hi, mean + half))}

    # ------------------------------------------------------------------ pieces
    def _settings(self, name):
        if name == "temperature":
            return {"t_ref": self.t_ref}
        if name == "hysteresis":
            return {"h_ref": self.h_ref}
        return {}

    def applicable(self, name: str) -> str | None:
        """Why ``name`` cannot be a candidate here (None when it can)."""
        if name == "temperature" and self.train.temperature_c is None:
            return "no temperature column in the data"
        try:
            augment(self.base, [make_effect(name)])
        except Exception as exc:  # a state the base model already has (e.g. hysteresis in ESC)
            return str(exc)
        return None

    def fit(self, specs):
        """Fit ``[(name, start_values)]`` jointly on the training part; returns ``(effects, LsqResult)``."""
        names, theta0, lo, hi = [], [], [], []
        layout = []
        for name, start in specs:
            cls = EFFECTS[name]
            b = self.bounds[name]
            for p in cls.param_names:
                names.append(f"{name}.{p}")
                theta0.append(start.get(p, cls.defaults[p]))
                lo.append(b[p][0])
                hi.append(b[p][1])
            layout.append((name, cls.param_names))

        def build(theta):
            theta = np.asarray(theta, dtype=float)
            effects, j = [], 0
            for name, params in layout:
                vals = {p: theta[..., j + m] for m, p in enumerate(params)}
                effects.append(make_effect(name, **vals, **self._settings(name)))
                j += len(params)
            return augment(self.base, effects)

        res = fit_parameters(build, self.train, theta0, lo, hi, names=names, soc0=self.soc0,
                             compress=FIT_COMPRESS, max_nfev=self.max_nfev)
        model = build(res.theta)
        return model, res

    # ------------------------------------------------------------------ the search
    def run(self):
        """``(final model, steps, rounds, before_rmse)``: steps = accepted candidates, rounds = every round's list."""
        current = []  # [(name, fitted values)]
        model = self.base
        rmse_now, r_now = held_out(model, self.split)
        before = rmse_now
        steps, rounds = [], []
        for _ in range(self.max_steps):
            traj = Trajectory.simulate(model, self.train, self.soc0)
            sigs = signatures(model, traj, self.bounds, self.t_ref)
            n_eff = effective_samples(r_now)
            cands, ready = [], []
            for name in self.candidates:
                if name in [c for c, _ in current]:
                    continue
                why = self.applicable(name)
                if why is not None:
                    cands.append(Candidate(name, -np.inf, rmse_now, rmse_now, {}, 0.0, f"not applicable: {why}"))
                else:
                    ready.append(name)
            ready.sort(key=lambda n: sigs[n].r2 if n in sigs else 0.0, reverse=True)
            r2s = [sigs[n].r2 if n in sigs else 0.0 for n in ready]
            n_fit = min(self.max_fits, len(ready))
            while n_fit < len(ready) and n_fit > 0 and r2s[n_fit] >= max(TIE_R2, r2s[n_fit - 1] - 0.01):
                n_fit += 1  # collinear signatures (SOC drifts: capacity, bias, leak, efficiency) are fitted together
            for rank, name in enumerate(ready):
                sig = sigs.get(name)
                r2 = r2s[rank]
                if rank < n_fit and r2 >= MIN_SIGNATURE_R2:
                    cands.append(self._try(name, current, sig, rmse_now, n_eff))
                else:
                    cands.append(Candidate(name, -np.inf, rmse_now, rmse_now, {}, r2,
                                           f"residual signature {'' if sig is None else sig.regressor} explains "
                                           f"{100 * r2:.1f} % of the training residual variance: not fitted"))
            cands.sort(key=lambda c: (c.score, c.signature_r2), reverse=True)
            rounds.append({"candidates": cands, "signatures": sigs, "trajectory": traj, "model": model})
            best = cands[0] if cands else None
            if best is None or not np.isfinite(best.score) or best.score <= 0 \
                    or best.rmse_after > (1.0 - self.min_gain) * rmse_now or rmse_now <= NOISE_FLOOR * self.noise_sd:
                break
            steps.append(best)
            current = [(e.name, {p: float(e[p]) for p in e.param_names}) for e in best.effects]
            model = augment(self.base, best.effects)
            rmse_now, r_now = best.rmse_after, best.held_residual
        return model, steps, rounds, before

    def _try(self, name, current, sig, rmse_now, n_eff) -> Candidate:
        t0 = _time.perf_counter()
        start = dict(sig.guess) if sig is not None else {}
        try:
            model, res = self.fit(current + [(name, start)])
            rmse_after, r_after = held_out(model, self.split)
        except Exception as exc:  # a failed fit scores nothing but is reported
            return Candidate(name, -np.inf, rmse_now, rmse_now, {}, 0.0 if sig is None else sig.r2,
                             f"fit failed: {type(exc).__name__}: {exc}", seconds=_time.perf_counter() - t0)
        p = len(EFFECTS[name].param_names)
        score = float(np.log(rmse_now**2 / max(rmse_after**2, 1e-30)) - 2.0 * p / n_eff)
        eff = model.effect(name)
        params = {k: float(eff[k]) for k in eff.param_names}
        r2 = 0.0 if sig is None else sig.r2
        regressor = "" if sig is None else sig.regressor
        evidence = (f"residual signature {regressor}: explains {100 * r2:.0f} % of the training residual variance; "
                    f"fitted in bounds ({_fmt(params)}): held-out RMSE {1000 * rmse_now:.1f} → "
                    f"{1000 * rmse_after:.1f} mV ({100 * (1 - rmse_after / rmse_now):.0f} % lower)")
        if name == "current_bias" and self.bias_rest is not None:
            evidence += f"; rests read {1000 * self.bias_rest[0]:.1f} mA (bounds b to it)"
        return Candidate(name, score, rmse_now, rmse_after, params, r2, evidence, tuple(model.effects),
                         _time.perf_counter() - t0, r_after)


def _fmt(params: dict) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in params.items())
