"""The generic fitting building block: bounded least squares of a model's voltage against a measured profile.

``fit_parameters(build, profile, theta0, lower, upper)`` minimises ``Σ_k (y_model,k(θ) − y_meas,k)²`` over the
samples of ``profile`` with :func:`scipy.optimize.least_squares` (trust-region reflective, bounds on θ). ``build(θ)``
returns a :class:`~socbench.models.base.Model`; positivity is the caller's choice of parametrisation (bounds, or
``θ = log p``), and a constraint the parametrisation cannot hold is a ``penalty``: residuals appended to the voltage's
(the RMSE and covariance returned are the voltage's alone).

Speed. The Jacobian is a forward difference in every parameter, and all ``P + 1`` parameter variants run as **one
batched simulation**: ``build`` is called once with a ``(P + 1, P)`` array and must return a model whose parameters
carry that leading batch axis (the SOC functions in :mod:`socbench.models.params` broadcast it against the state
batch). Row 0 is the unperturbed θ. Because the time loop's per-step overhead dominates, the batch costs about as
much as a single run, so *every* residual evaluation runs the whole batch: when the optimiser accepts the point, its
Jacobian is already there, and a fit costs about one simulation per iteration. A ``build`` that cannot take a batch
(or returns a model whose batched output differs from the one-at-a-time output — checked once on a short prefix) is run
one variant at a time instead; the result says which path was taken (``batched``) and how many simulations ran.

Uncertainty. At the optimum, with ``s² = Σr²/(N − P)``, ``cov = (JᵀJ)⁻¹ s²``; ``stderr = √diag(cov)`` and
``corr = cov / (σ σᵀ)``. The inverse is taken through an SVD of the column-scaled ``J``; directions with a singular
value below ``1e-12`` of the largest get a huge variance instead of being dropped, so a non-identifiable parameter
shows up as a huge standard error rather than a deceptively small one. The residuals of a voltage fit are
autocorrelated, so these standard errors are optimistic lower bounds; use them to rank identifiability, not as
confidence intervals.
"""

from __future__ import annotations

import contextlib
import functools
import time as _time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..errors import ConfigError, DataError, ModelError
from ..profile import Profile
from ..segments import resolve as resolve_segments
from ..segments import restart_soc
from .compress import compress_profile
from .gap_fill import fill_gaps

#: residual substituted for a non-finite model voltage, or for parameters the model rejects (ModelError) [V]: keeps
#: the optimiser away from unstable parameter regions
NONFINITE_RESIDUAL = 10.0
#: largest SOC change of one merged (compressed) step
MAX_SOC_STEP = 5e-3


@dataclass(frozen=True, eq=False)
class LsqResult:
    """Outcome of :func:`fit_parameters` (θ-space: the caller maps θ to physical parameters)."""

    theta: np.ndarray
    stderr: np.ndarray
    corr: np.ndarray
    cov: np.ndarray
    names: tuple
    rmse: float
    residual: np.ndarray
    jac: np.ndarray
    success: bool
    message: str
    nfev: int
    njev: int
    nsim: int
    n_samples: int
    seconds: float
    batched: bool
    at_bounds: tuple = ()
    rmse_start: float = float("nan")  # at theta0 (how much the fit improved on its start)
    profile: Profile | None = field(default=None, repr=False)
    domain: dict = field(default_factory=dict)  # socbench.domain report of the fitted model on the fitted record

    def as_dict(self) -> dict:
        return dict(zip(self.names, self.theta.tolist()))


def one_blas_thread():
    """A context in which BLAS/LAPACK run on one thread (``threadpoolctl``; a no-op without it).

    The optimiser factors a small Jacobian (a few hundred rows × tens of parameters) by SVD on every iteration: far
    too small to gain from threads, and on a busy machine (or next to other worker processes) OpenBLAS's threads
    wait on each other — an SVD that takes 2 ms on one thread took 0.3 s with two (``improved_rc``'s paper fit: 31 s
    → 1.4 s at load 8, benchmarks/default_leaderboard.py and docs/performance.md).
    """
    try:
        controller = _blas_controller()
    except ImportError:  # pragma: no cover - a declared dependency
        return contextlib.nullcontext()
    return controller.limit(limits=1, user_api="blas")


@functools.cache
def _blas_controller():
    """The process's BLAS thread pools, found once (``threadpoolctl.ThreadpoolController``): ``threadpool_limits``
    scans the loaded libraries on every call (0.5 ms, more than a small fit's SVD; the diagnosis enters
    :func:`one_blas_thread` for each of its ~200 fold fits a case), the controller's ``limit`` does not (0.02 ms).
    Created at the first fit, when numpy's and scipy's BLAS are loaded (this module imports scipy.optimize)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def simulate_voltage(model, time_s, current, temp=None, x0=None, soc_jumps=None, restarts=None,
                     engine: str = "auto") -> np.ndarray:
    """Open-loop voltage ``(…, T)`` of ``model`` from state ``x0 (…, n)`` (``soc_jumps[k]`` is added to the SOC after
    the step into sample ``k``). ``restarts`` ``[(k, z), ...]``: the record is simulated in segments, the one starting
    at sample ``k`` from rest at SOC ``z`` (socbench.segments). See :func:`open_loop_segments` for ``engine``."""
    return open_loop_segments(model, time_s, current, temp, x0, soc_jumps, restarts, engine=engine, states=False)[1]


def _open_loop(model, x0, time_s, current, temp, soc_jumps, guards, engine, states):
    """One segment: the compiled step loop (:func:`socbench.kernels.openloop.open_loop`, one parameter variant per
    row) when ``engine`` is not "numpy", numba is installed, the model lowers and no guard log is asked for (the
    compiled loop does not count guards); else :meth:`~socbench.models.base.Model.open_loop`. The two agree to
    ~1e-15 relative (tests/test_kernels.py)."""
    if engine != "numpy" and guards is None:
        from ..kernels import jit

        if jit.available():
            from ..kernels.openloop import open_loop

            out = open_loop(model, x0, time_s, current, temp, soc_jumps, states=states)
            if out is not None:
                return out
    return model.open_loop(x0, time_s, current, temp, soc_jumps, guards=guards)


def open_loop_segments(model, time_s, current, temp=None, x0=None, soc_jumps=None, restarts=None, guards=None,
                       engine: str = "auto", states: bool = True):
    """``(states, voltage)`` of the open loop, segment by segment when ``restarts`` (see :func:`simulate_voltage`) is
    given: no current is integrated across a restart. ``states=False``: the states may come back None (the compiled
    loop then does not store them)."""
    if not restarts:
        return _open_loop(model, x0, time_s, current, temp, soc_jumps, guards, engine, states)
    bounds = [0] + [int(k) for k, _ in restarts] + [np.size(time_s)]
    parts = []
    for s, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        xs = x0 if s == 0 else model.x0(np.broadcast_to(float(restarts[s - 1][1]), np.shape(x0)[:-1]))
        parts.append(_open_loop(model, xs, time_s[a:b], current[..., a:b], None if temp is None else temp[..., a:b],
                                None if soc_jumps is None else soc_jumps[a:b], guards, engine, states))
    xs_all = None if any(p[0] is None for p in parts) else np.concatenate([p[0] for p in parts], axis=-2)
    return xs_all, np.concatenate([p[1] for p in parts], axis=-1)


def _initial_soc(model, profile: Profile, soc0):
    if soc0 is not None:
        return float(soc0)
    return float(restart_soc(profile, 0, model))


def covariance(jac: np.ndarray, residual: np.ndarray, n_params: int):
    """``(cov, stderr, corr)`` from ``(JᵀJ)⁻¹ s²`` via an SVD of the column-scaled Jacobian (see the module doc)."""
    n = residual.size
    dof = max(n - n_params, 1)
    s2 = float(residual @ residual) / dof
    scale = np.linalg.norm(jac, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    js = jac / scale
    _, sv, vt = np.linalg.svd(js, full_matrices=False)
    floor = max(sv.max(initial=0.0), 1e-300) * 1e-12
    inv2 = 1.0 / np.maximum(sv, floor) ** 2
    cov_s = (vt.T * inv2) @ vt
    cov = cov_s / np.outer(scale, scale) * s2
    var = np.diag(cov).copy()
    stderr = np.sqrt(np.maximum(var, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(stderr, stderr)
    corr = np.clip(np.nan_to_num(corr), -1.0, 1.0)
    np.fill_diagonal(corr, 1.0)
    return cov, stderr, corr


def fit_parameters(
    build: Callable[[np.ndarray], object],
    profile: Profile,
    theta0: Sequence[float],
    lower: Sequence[float],
    upper: Sequence[float],
    *,
    names: Sequence[str] | None = None,
    soc0: float | None = None,
    x0=None,
    soc_jumps: np.ndarray | None = None,
    gap_steps=None,
    segments=None,
    weights: np.ndarray | None = None,
    compress: bool | dict = True,
    time_weighted: bool = False,
    loss: str = "linear",
    batch: bool = True,
    f_scale: float = 0.01,
    diff_step: float = 1e-6,
    max_nfev: int | None = None,
    ftol: float = 1e-6,
    xtol: float = 1e-6,
    gtol: float = 1e-8,
    penalty: Callable[[np.ndarray], np.ndarray] | None = None,
) -> LsqResult:
    """Fit θ so that ``build(θ).simulate(profile)`` matches the measured voltage (see the module docstring).

    Parameters
    ----------
    build : callable
        ``θ (P,) -> Model``; called with ``(B, P)`` for the batched Jacobian when ``batch`` (falls back if it cannot).
    profile : Profile
        Plain profile with a voltage column. Compressed first (``compress=True`` or a dict of
        :func:`~socbench.identify.compress.compress_profile` options); ``False`` fits every sample.
    theta0, lower, upper : array-like (P,)
        Start and bounds (``±inf`` allowed). ``theta0`` is clipped into the bounds.
    soc0, x0 :
        Initial SOC (default: ``soc_ref[0]``, else the SOC read off the first voltage, ``Model.soc_from_voltage``) or
        a full initial state.
    soc_jumps : array (T,) on the *original* samples, optional
        SOC added after the step into a sample (unrecorded charge at gaps; see :func:`simulate_voltage`).
    gap_steps : :class:`~socbench.identify.gap_fill.GapSteps`, optional
        Gaps whose jump is simulated as the step that moved it (:mod:`socbench.identify.gap_fill`); the samples
        the step adds have weight 0.
    segments :
        A record of several discharges (:mod:`socbench.segments`) is fitted segment by segment, each later segment
        from rest at its reference SOC (else the SOC read off its first voltage): None finds the segments (with
        the model's OCV and capacity at ``theta0``), False fits the record as one piece, or a ``Segments``.
    weights : array (T,) on the original samples, optional
        Residual weights; a sample of weight 0 is left out of the fit (its residual, the RMSE, ``n_samples`` and the
        covariance's degrees of freedom), though the simulation runs through it.
    time_weighted : bool
        Weight each (compressed) sample by the time it stands for, as a fit of the uniformly sampled record would.
    loss, f_scale :
        :func:`scipy.optimize.least_squares` loss (``"linear"`` = least squares; ``"soft_l1"``, ``"huber"`` are
        robust) and its residual scale [V].
    diff_step : float
        Forward-difference step, relative to ``max(1, |θ_j|)``.
    penalty : callable, optional
        ``θ (B, P) -> (B, K)`` residuals appended to the voltage residual (a constraint held softly, e.g.
        :meth:`~socbench.identify.fit.FitProblem.positivity`); the RMSE, the residual, ``n_samples`` and the
        covariance returned are the voltage's alone.
    """
    t_start = _time.perf_counter()
    if profile.batched:
        raise DataError("fit_parameters needs a plain profile (one run)", file=profile.meta.source or profile.name)
    profile.require("voltage_v")
    theta0 = np.asarray(theta0, dtype=float).ravel()
    lower = np.broadcast_to(np.asarray(lower, dtype=float), theta0.shape).copy()
    upper = np.broadcast_to(np.asarray(upper, dtype=float), theta0.shape).copy()
    P = theta0.size
    if np.any(lower >= upper):
        raise ConfigError("fit_parameters: every lower bound must be below its upper bound")
    names = tuple(names) if names is not None else tuple(f"theta{j}" for j in range(P))
    if len(names) != P:
        raise ConfigError(f"fit_parameters: {len(names)} names for {P} parameters")
    span = upper - lower
    inner = np.where(np.isfinite(span), 1e-9 * span, 1e-9)
    theta0 = np.clip(theta0, lower + inner, upper - inner)

    model0 = build(theta0)
    view = fitting_view(profile, model0, segments, compress, soc_jumps, gap_steps)  # the data the residual is on
    prof, idx, jumps, restarts = view.profile, view.index, view.jumps, view.restarts
    w = None if weights is None else np.asarray(weights, dtype=float)[idx]
    if view.measured is not None:
        w = (np.ones(idx.size) if w is None else w) * view.measured
    if time_weighted:
        # each kept sample stands for the time until the next one: weight its squared residual by that span, as a
        # fit of the uniformly sampled record would (normalised to a mean weight of 1)
        last = np.median(np.diff(prof.time_s)) if prof.n > 1 else 1.0
        dur = np.diff(prof.time_s, append=prof.time_s[-1] + last)
        for k, _ in restarts or ():  # the last sample of a segment stands for one step, not for the gap after it
            dur[k - 1] = last
        tw = np.sqrt(dur / dur.mean())
        w = tw if w is None else w * tw
    v_meas = prof.voltage_v
    temp = prof.temperature_c
    t, cur = prof.time_s, prof.current_a

    z0 = None if x0 is not None else _initial_soc(model0, prof, soc0)

    def start_state(model, n_batch):
        if x0 is not None:
            base = np.asarray(x0, dtype=float)
            return np.broadcast_to(base, ((n_batch,) if n_batch else ()) + base.shape[-1:]).copy()
        return model.x0(z0, (n_batch,) if n_batch else ())

    kept = None if w is None or np.all(w > 0) else w > 0  # masked samples leave the residual vector

    def residual_of(y):
        r = y - v_meas
        r = np.where(np.isfinite(r), r, NONFINITE_RESIDUAL)
        r = r * w if w is not None else r
        return r if kept is None else r[kept]

    def penalised(r, thetas):  # voltage residual rows r (B, N) of thetas (B, P), the penalty's rows appended
        return r if penalty is None else np.hstack([r, np.atleast_2d(penalty(thetas))])

    def simulate_one(theta):
        try:
            model = build(theta)
            return simulate_voltage(model, t, cur, temp, start_state(model, 0), jumps, restarts)
        except (ModelError, ConfigError, FloatingPointError):  # parameters outside the model's admissible region
            return np.full(t.size, np.nan)

    def simulate_many(thetas):
        if use_batch[0]:
            try:
                model = build(thetas)
                return simulate_voltage(model, t, cur, temp, start_state(model, thetas.shape[0]), jumps, restarts)
            except (ModelError, ConfigError, FloatingPointError):
                pass  # one variant is inadmissible: run them one by one so that only it gets the penalty
        return np.stack([simulate_one(th) for th in thetas])

    # ---- decide once, on a short prefix, whether the batched path is available and agrees with the plain one
    use_batch = [False]
    if batch and P > 0:
        n_probe = min(t.size, 64)
        step = np.where(theta0 + 1e-3 * np.minimum(span, 1.0) < upper, 1e-3, -1e-3) * np.minimum(span, 1.0)
        probe = np.stack([theta0, theta0 + step])
        try:
            models = [build(probe), build(probe[0]), build(probe[1])]
            args = (t[:n_probe], cur[:n_probe], None if temp is None else temp[:n_probe])
            jp = None if jumps is None else jumps[:n_probe]
            yb = simulate_voltage(models[0], *args, start_state(models[0], 2), jp)
            y0 = simulate_voltage(models[1], *args, start_state(models[1], 0), jp)
            y1 = simulate_voltage(models[2], *args, start_state(models[2], 0), jp)
            tol = 1e-9 * (1.0 + np.abs(y0))
            ok = yb.shape == (2, n_probe) and bool(np.all(np.abs(yb[0] - y0) <= tol)
                                                  and np.all(np.abs(yb[1] - y1) <= tol))
        except Exception:  # a build that cannot take a parameter batch: run variants one at a time
            ok = False
        use_batch[0] = ok

    # Every residual evaluation also simulates the P perturbed variants when batching (the batch costs about as much
    # as one run, the per-step overhead dominates), so the Jacobian at an accepted point is already there.
    cache: dict = {}
    counts = {"njev": 0, "nsim": 0}

    def steps_for(theta):
        h = diff_step * np.maximum(1.0, np.abs(theta))
        return np.where(theta + h > upper, -h, h)

    def evaluate(theta, need_jac):
        key = theta.tobytes()
        hit = cache.get(key)
        if hit is not None and (hit[1] is not None or not need_jac):
            return hit
        counts["nsim"] += 1
        if use_batch[0] or need_jac:
            h = steps_for(theta)
            thetas = np.vstack([theta, theta + np.diag(h)])
            r = penalised(np.stack([residual_of(row) for row in simulate_many(thetas)]), thetas)
            entry = (r[0], ((r[1:] - r[0]) / h[:, None]).T)
        else:
            entry = (penalised(residual_of(simulate_one(theta))[None], theta[None])[0], None)
        cache.clear()
        cache[key] = entry
        return entry

    def fun(theta):
        return evaluate(theta, False)[0]

    def jac(theta):
        counts["njev"] += 1
        return evaluate(theta, True)[1]

    n_voltage = residual_of(np.zeros(t.size)).size  # the residual's voltage entries (the penalty's follow)
    r0 = fun(theta0)[:n_voltage]
    rmse_start = float(np.sqrt(np.mean(r0 * r0))) if r0.size else float("nan")
    with one_blas_thread():
        if P == 0:
            r = fun(theta0)[:n_voltage]
            J = np.zeros((r.size, 0))
            res_x, success, message, nfev = theta0, True, "no parameters", 1
        else:
            sol = least_squares(fun, theta0, jac=jac, bounds=(lower, upper), method="trf", x_scale="jac", loss=loss,
                                f_scale=f_scale, ftol=ftol, xtol=xtol, gtol=gtol, max_nfev=max_nfev)
            res_x, success, message, nfev = sol.x, bool(sol.success), str(sol.message), int(sol.nfev)
            r = fun(res_x)[:n_voltage]
            J = jac(res_x)[:n_voltage]
        cov, stderr, corr = covariance(J, r, P)
    domain = _domain(build, res_x, t, cur, temp, start_state, jumps, restarts, kept)
    domain["segments"] = 1 + len(restarts or ())
    rmse = float(np.sqrt(np.mean(r * r))) if r.size else float("nan")
    rel = np.where(np.isfinite(span), 1e-4 * span, 0.0)
    at_bounds = tuple(n for n, th, lo, hi, tol in zip(names, res_x, lower, upper, rel)
                      if (np.isfinite(lo) and th - lo <= tol) or (np.isfinite(hi) and hi - th <= tol))
    return LsqResult(theta=np.asarray(res_x, dtype=float), stderr=stderr, corr=corr, cov=cov, names=names, rmse=rmse,
                     residual=r, jac=J, success=success, message=message, nfev=nfev, njev=counts["njev"],
                     nsim=counts["nsim"],
                     n_samples=int(r.size), seconds=_time.perf_counter() - t_start, batched=bool(use_batch[0]),
                     at_bounds=at_bounds, rmse_start=rmse_start, profile=prof, domain=domain)


@dataclass(frozen=True, eq=False)
class FittingView:
    """The record a fit simulates: ``profile`` (compressed, or the record itself), the original sample of each of its
    samples (``index``), the SOC jumps moved onto its samples, and the segment restarts ``[(sample, SOC)]`` (None:
    one piece)."""

    profile: Profile
    index: np.ndarray
    jumps: np.ndarray | None
    restarts: list | None
    #: per sample, whether it is one of the record's (False: a sample a record gap's filled step added, which
    #: measures nothing; :mod:`socbench.identify.gap_fill`); None: all are
    measured: np.ndarray | None = None


def fitting_view(profile: Profile, model, segments=None, compress: bool | dict = True,
                 soc_jumps=None, gap_steps=None) -> FittingView:
    """The :class:`FittingView` of ``profile`` for ``model`` (its OCV and capacity find the segments and their restart
    SOC; ``segments`` as :func:`fit_parameters` takes it): every segment compressed on its own (``compress``: True,
    or a dict of :func:`~socbench.identify.compress.compress_profile` options; a merged step never spans a segment
    boundary nor moves more than :data:`MAX_SOC_STEP` of the capacity), and the jumps landing in
    ``(idx_{j−1}, idx_j]`` applied at ``idx_j``; the gaps of ``gap_steps``
    (:class:`~socbench.identify.gap_fill.GapSteps`) filled with their step
    (:func:`~socbench.identify.gap_fill.fill_gaps`), the samples it adds marked not ``measured``."""
    segs = resolve_segments(segments, profile, model.ocv, getattr(model, "capacity_ah", None))
    if compress:
        opts = dict(compress) if isinstance(compress, dict) else {}
        opts.setdefault("max_ah", MAX_SOC_STEP * float(getattr(model, "capacity_ah", 0.0) or 0.0) or None)
        if segs.count == 1:
            comp = compress_profile(profile, **opts)
            prof, idx = comp.profile, comp.index
        else:  # each segment on its own: a merged step never spans a boundary
            comps = [compress_profile(profile.slice(a, b), **opts) for a, b in segs.spans()]
            idx = np.concatenate([c.index + a for c, (a, _) in zip(comps, segs.spans())])
            prof = _joined(profile, [c.profile for c in comps])
    else:
        prof, idx = profile, np.arange(profile.n)
    restarts = [(int(np.searchsorted(idx, a)), float(restart_soc(profile, a, model)))
                for a in segs.starts[1:]] or None
    jumps = None
    if soc_jumps is not None:
        cum = np.concatenate([[0.0], np.cumsum(np.asarray(soc_jumps, dtype=float))])
        jumps = np.diff(cum[idx + 1], prepend=0.0)
        jumps[0] = 0.0
    if gap_steps is not None and jumps is not None:
        filled = fill_gaps(prof, jumps, float(model.capacity_ah), gap_steps, gap_steps.on(idx))
        if filled.added:
            pos = np.flatnonzero(filled.measured)  # each old sample's place in the filled view
            src = np.cumsum(filled.measured) - 1  # an added sample belongs to the step into the sample after it
            idx = idx[np.minimum(src + ~filled.measured, idx.size - 1)]
            restarts = [(int(pos[k]), z) for k, z in restarts] if restarts else restarts
            return FittingView(filled.profile, idx, filled.jumps, restarts, filled.measured)
    return FittingView(prof, idx, jumps, restarts)


def _joined(profile: Profile, parts: list) -> Profile:
    """The compressed segments of ``profile`` back on one time axis (a plain profile)."""
    def cat(name):
        vals = [getattr(p, name) for p in parts]
        return None if vals[0] is None else np.concatenate(vals, axis=-1)

    return profile.with_(time_s=cat("time_s"), current_a=cat("current_a"), voltage_v=cat("voltage_v"),
                         temperature_c=cat("temperature_c"), soc_ref=cat("soc_ref"))


def _domain(build, theta, t, cur, temp, start_state, jumps, restarts, kept=None) -> dict:
    """The domain report (socbench.domain) of the fitted model along the fitted (compressed) record, on its samples
    ``kept`` (default all; a sample of weight 0 is not fitted, and where the model stands there is not the fit's
    concern)."""
    from ..domain import domain_report
    from ..models.blocks import GuardLog

    try:
        model = build(theta)
        log = GuardLog()
        with np.errstate(all="ignore"):
            states, volts = open_loop_segments(model, t, cur, temp, start_state(model, 0), jumps, restarts, log)
    except (ModelError, ConfigError, FloatingPointError) as exc:
        return {"error": str(exc)}
    log.samples = int(t.size)
    if kept is not None:
        states, volts = states[..., kept, :], volts[..., kept]
    return domain_report(model, states=states, voltage=volts, guards=log)
