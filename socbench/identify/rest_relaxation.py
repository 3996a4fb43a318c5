"""The time constants an HPPC's rests show: the model's branches fitted on the relaxation alone, each rest's OCV free.

During a rest no charge moves, so the SOC, hence the OCV, stays where the rest began, and the voltage moves only
through the cell's relaxing states (its RC branches). A model's residual over one rest, less its own mean over that
rest, is therefore free of every OCV error — a rest point read before the cell settled, a curve that bends between
its points, an OCV offset — and holds the error of the relaxation alone. On the whole record a branch the structure
lacks is a small share of an error the OCV between the rest points dominates (5–20 % SOC steps on a curve with knees:
tens of mV), and a fit with the branch beside the base spends it on that error; on the rests it shows as a tail the
base's own branches cannot follow.

The fit (:func:`fit_rests`): with ``R`` the rests after the test's first (which has no history to relax from), each
past its first sample and at least :data:`MIN_REST_S` long, and ``e = v − y(θ)`` the residual of the fitted set with
its branches' resistances and capacitances scaled by ``θ`` (and, with ``extra``, one more branch ``R_x``, ``τ_x``),
open loop over the whole record from the fit's start and current offset::

    θ̂ = argmin Σ_r Σ_{t ∈ r} (e_t − ē_r)²          ē_r the mean of e over rest r (its OCV level, free)
    RMS² = that minimum / N                          N the samples read
    σ = max(sd(Δ²v) / √6,  q / √12)                  the voltage noise (second differences within the rests at the
                                                     record's own sampling, past 5 robust deviations left out; q
                                                     the voltage's quantisation step)
    S = √max(RMS² − σ², 0)                           the relaxation error beyond the noise

The record is read as the fit reads it (:func:`~socbench.identify.lsq.fitting_view`: its segments, their restarts
and SOC jumps), on compressed steps (samples kept geometrically after every current change, then every
:data:`REST_STEP_S` s), which simulate exactly what the full record would at the samples kept; a rest where a segment
restarts (after a gap in the record, a step it does not hold) is not read. :func:`rest_evidence` fits the base's
branches alone and with one more, from several starting time constants: ``cut = 1 − S_with/S_without`` is how much
of the relaxation the branch explains, ``χ² = N·(RMS²_without − RMS²_with)/σ²`` how far beyond what two parameters
take from white noise. The fit test uses it (:mod:`socbench.identify.fit_test_effect`): a branch the rests show is
fitted at the time constant and resistance they read, the base refitted around it on the whole record.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..errors import ConfigError, DataError, ModelError
from ..models.effects import augment, make_effect, resistance_scale
from ..models.registry import make_model
from ..models.scaling import branch_params, scaled_model
from ..profile import Profile
from .fit import FitResult, branch_time_constants, setup_fit
from .hppc import analyze_hppc, quantisation_step
from .lsq import fitting_view, one_blas_thread, simulate_voltage

#: the shortest rest read [s]; shorter ones hold few samples beside their mean
MIN_REST_S = 60.0
#: … and the fewest samples a rest must keep past its first
MIN_REST_SAMPLES = 8
#: the spacing the compressed record keeps within a rest once its geometric spacing reaches it [s]
REST_STEP_S = 30.0
#: how far the rest fit may scale each branch parameter of the fitted set, either way (×10⁴: the whole record's fit
#: can put a branch far from where the rests want it, and a bound the base's branch rests on would leave the extra
#: branch to take its place)
BRANCH_SCALE = float(np.log(1e4))
#: starting time constants of the extra branch [log10 s], and its starting resistance as a share of R0
TAU_STARTS = (2.0, 2.7, 3.4)
R_START_SHARE = 0.5
#: evaluations of each bounded least-squares fit
MAX_NFEV = 30


@dataclass(frozen=True)
class RestFit:
    """The relaxation fit of :func:`fit_rests`."""

    n: int  # samples read (on the compressed record)
    n_rests: int
    rms_v: float  # RMS of the residual, each rest less its own mean [V]
    noise_sd_v: float  # σ [V]
    scales: dict  # branch parameter -> fitted scale
    taus_s: dict  # the base's branches' time constants as fitted on the rests ({"R1C1": τ, …}) [s]
    extra: dict = field(default_factory=dict)  # {"R": Ω, "log10_tau": log10 s} of the extra branch (empty: none)

    @property
    def structure_v(self) -> float:
        """``S``: the relaxation error beyond the noise [V]."""
        return float(np.sqrt(max(self.rms_v**2 - self.noise_sd_v**2, 0.0)))


def rest_windows(profile: Profile, capacity_ah: float | None = None) -> list:
    """``[(first, stop)]`` sample ranges of the rests read (module docstring): every rest of the HPPC analysis after
    the test's first, within the test, past its first sample, at least :data:`MIN_REST_S` long and
    :data:`MIN_REST_SAMPLES` samples. Raises :class:`~socbench.errors.DataError` when the record is not an HPPC."""
    a = analyze_hppc(profile, capacity_ah=capacity_ah)
    stop = profile.n if a.end_index is None else a.end_index
    out = []
    for r in a.rests:
        if r.start <= a.start_index or r.stop > stop or r.duration_s < MIN_REST_S:
            continue
        if r.stop - (r.start + 1) >= MIN_REST_SAMPLES:
            out.append((r.start + 1, r.stop))
    return out


def noise_sd(voltage, windows) -> float:
    """σ of the module docstring over the samples of ``windows``: the standard deviation of the second differences
    (over √6) within 5 robust deviations of their median — the MAD alone is lumpy on a quantised reading (+11 % for
    2.7 mV of noise read in 1 mV steps), the plain deviation sees the relaxation's curvature right after an edge."""
    d = np.concatenate([np.diff(voltage[a:b], 2) for a, b in windows if b - a >= 3] or [np.zeros(0)])
    q = quantisation_step(voltage)
    if d.size == 0:
        return q / np.sqrt(12.0)
    mid = float(np.median(d))
    spread = max(1.4826 * float(np.median(np.abs(d - mid))), q)
    kept = d[np.abs(d - mid) <= 5.0 * spread]
    return max(float(np.std(kept)) / np.sqrt(6.0), q / np.sqrt(12.0))


class _Rests:
    """The rest residual of one fitted set as a function of its branch scales (and the extra branch)."""

    def __init__(self, fit: FitResult, profile: Profile, windows):
        prob = setup_fit(fit.name, profile, "constant", fit.params.ocv, fit.params.capacity_ah)
        self.base = make_model(fit.name, fit.params.replace(effects=()))
        view = fitting_view(prob.fit_profile(profile), self.base, None,
                            {"max_step_s": REST_STEP_S, "growth": 1.5}, prob.soc_jumps, prob.gap_steps)
        self.view, self.windows = view, windows
        # a segment restarts from rest where the record has a gap: a rest there relaxes from a step the record does not
        # hold, which no branch of the model can follow
        starts = {int(view.index[k]) for k, _ in view.restarts or ()}
        measured = np.ones(view.index.size, dtype=bool) if view.measured is None else view.measured
        kept = [np.flatnonzero((view.index >= a) & (view.index < b) & measured) for a, b in windows
                if not any(a - 1 <= k < b for k in starts)]
        kept = [k for k in kept if k.size >= 2]
        self.idx = np.concatenate(kept) if kept else np.zeros(0, dtype=int)
        self.rest = np.concatenate([np.full(k.size, j) for j, k in enumerate(kept)]) if kept else self.idx
        self.counts = np.bincount(self.rest).astype(float)
        self.v = view.profile.voltage_v[self.idx]
        self.soc0 = float(np.clip(prob.soc0, 0.0, 1.0))
        self.names = branch_params(self.base)
        r0 = fit.params.values.get("R0")
        self.r0 = float(np.median(np.atleast_1d(r0(0.5)))) if r0 is not None else 1e-3
        self.r_max = resistance_scale(self.base)
        self.noise = noise_sd(profile.voltage_v, windows)

    def model(self, x, extra: bool):
        x = np.atleast_2d(x)
        m = scaled_model(self.base, self.names, np.exp(x[:, :len(self.names)]))
        if extra:
            m = augment(m, [make_effect("extra_rc", R=np.exp(x[:, -2]), log10_tau=x[:, -1])])
        return m

    def residual(self, x, extra: bool) -> np.ndarray:
        """``(B, N)``: each rest's residual less its mean, for the rows of ``x``."""
        x = np.atleast_2d(x)
        m, rec = self.model(x, extra), self.view.profile
        try:
            with np.errstate(all="ignore"):
                y = simulate_voltage(m, rec.time_s, rec.current_a, rec.temperature_c, m.x0(self.soc0, (x.shape[0],)),
                                     self.view.jumps, self.view.restarts)
        except (ModelError, ConfigError, FloatingPointError):  # parameters the model rejects
            y = np.full((x.shape[0], rec.n), np.nan)
        e = self.v[None] - np.broadcast_to(y, (x.shape[0], rec.n))[:, self.idx]
        means = np.stack([np.bincount(self.rest, weights=row) / self.counts for row in e])
        e = e - means[:, self.rest]
        return np.where(np.isfinite(e), e, 1.0)

    def fit(self, extra: bool, starts=None) -> RestFit:
        """The fit without (``extra`` False) or with the extra branch, from each row of branch scales in ``starts``
        (log; default: the fitted set as it is) and, with the extra branch, each of its starting time constants; the
        best kept."""
        n = len(self.names)
        lo, hi = np.full(n, -BRANCH_SCALE), np.full(n, BRANCH_SCALE)
        starts = [np.zeros(n)] if starts is None else [np.asarray(x, dtype=float) for x in starts]
        if extra:
            lo, hi = np.r_[lo, np.log(1e-6), 0.5], np.r_[hi, np.log(self.r_max), 4.0]
            starts = [np.r_[x, np.log(R_START_SHARE * self.r0), t] for x in starts for t in TAU_STARTS]
        if lo.size == 0:  # nothing to fit: the set's own residual
            x = np.zeros(0)
            cost = 0.5 * float(np.sum(self.residual(x[None], False)[0] ** 2))
        else:
            best = None
            for s in starts:
                s = np.clip(s, lo + 1e-9, hi - 1e-9)

                def jac(x):
                    h = 1e-6 * np.maximum(1.0, np.abs(x))
                    rows = self.residual(np.vstack([x, x[None] + np.diag(h)]), extra)
                    return ((rows[1:] - rows[:1]) / h[:, None]).T

                with one_blas_thread():
                    sol = least_squares(lambda x: self.residual(x, extra)[0], s, jac=jac, bounds=(lo, hi),
                                        method="trf", x_scale="jac", max_nfev=MAX_NFEV)
                if best is None or sol.cost < best.cost:
                    best = sol
            x, cost = best.x, float(best.cost)
        m = self.model(x, extra)
        base = m.base if extra else m
        taus = branch_time_constants(base.params)
        return RestFit(int(self.idx.size), int(self.counts.size), float(np.sqrt(2.0 * cost / self.idx.size)),
                       self.noise, {p: float(np.exp(v)) for p, v in zip(self.names, x[:n])},
                       {k: float(np.ravel(v)[0]) for k, v in taus.items()},
                       {"R": float(np.exp(x[-2])), "log10_tau": float(x[-1])} if extra else {})


def _log_scales(fit: RestFit, names) -> np.ndarray:
    return np.log([fit.scales[p] for p in names])


def _swapped(rests: _Rests, fit: RestFit) -> list:
    """Rows of log branch scales that put ``fit``'s extra branch in the place of each of the base's branches (the
    others as ``fit`` has them): a fit without the extra branch started there is at least as good as ``fit`` with
    that base branch dropped, so an extra branch that only took a base branch's place shows no gain."""
    rows = []
    at = {p: float(np.median(np.atleast_1d(rests.base.params.values[p](0.5)))) for p in rests.names}
    r, tau = fit.extra["R"], 10.0 ** fit.extra["log10_tau"]
    for p in rests.names:
        if p[:1] != "R" or f"C{p[1:]}" not in at:
            continue
        row = _log_scales(fit, rests.names).copy()
        row[rests.names.index(p)] = np.log(r / at[p])
        row[rests.names.index(f"C{p[1:]}")] = np.log(tau / r / at[f"C{p[1:]}"])
        rows.append(np.clip(row, -BRANCH_SCALE, BRANCH_SCALE))
    return rows


def _read_rests(fit: FitResult, profile: Profile, windows=None) -> _Rests | None:
    """The rests of ``profile`` (``windows``, default :func:`rest_windows`) set up for ``fit``; None when fewer than
    two are left to read (not an HPPC, or none long enough)."""
    if windows is None:
        try:
            windows = rest_windows(profile, fit.params.capacity_ah)
        except DataError:
            return None
    rests = _Rests(fit, profile, windows)
    return rests if rests.counts.size >= 2 else None


def fit_rests(fit: FitResult, profile: Profile, extra: bool = False, windows=None) -> RestFit | None:
    """The relaxation fit of the module docstring for ``fit`` on ``profile`` (the record it was fitted on): its branch
    parameters scaled, and with ``extra`` one more branch; None when the record has no rests to read (not an HPPC, or
    none long enough)."""
    rests = _read_rests(fit, profile, windows)
    return None if rests is None else rests.fit(extra)


def rest_evidence(fit: FitResult, profile: Profile) -> dict | None:
    """The rests' verdict on one more branch beside ``fit``'s (module docstring): ``{"structure_v": [S_without,
    S_with], "cut", "chi2", "rests", "longest_rest_s", "noise_sd_v", "R", "log10_tau", "taus_s", "scales"}``
    (``taus_s``: the base's branches as fitted beside the extra one; ``scales``: the factors on ``fit``'s branch
    parameters that put them there), or None where the record has no rests to read."""
    rests = _read_rests(fit, profile)
    if rests is None:
        return None
    # without, from the fitted set; with, from there; without again from where the fit with it put the base's
    # branches, and with the extra branch in each one's place (it may only have taken a base branch's place)
    first = rests.fit(False)
    with_ = rests.fit(True, [_log_scales(first, rests.names)])
    without = rests.fit(False, [_log_scales(first, rests.names), _log_scales(with_, rests.names)]
                        + _swapped(rests, with_))
    if without.rms_v < first.rms_v:  # a better place for the base's branches: the extra one from there too
        again = rests.fit(True, [_log_scales(without, rests.names)])
        with_ = again if again.rms_v < with_.rms_v else with_
    s0, s1, sigma = without.structure_v, with_.structure_v, without.noise_sd_v
    chi2 = without.n * (without.rms_v**2 - with_.rms_v**2) / sigma**2 if sigma > 0 else float("inf")
    longest = max(float(profile.time_s[b - 1] - profile.time_s[a - 1]) for a, b in rests.windows)
    return {"structure_v": [s0, s1], "cut": float(1.0 - s1 / s0) if s0 > 0 else 0.0, "chi2": float(chi2),
            "rests": without.n_rests, "longest_rest_s": longest, "noise_sd_v": sigma, **with_.extra,
            "taus_s": with_.taus_s, "scales": with_.scales}
