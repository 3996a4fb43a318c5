"""One effect set fitted once per fold, and its cross-validated residual.

With the blocked folds of :mod:`socbench.diagnose.data`, an effect set's parameters are fitted ``G`` times (fold ``j``
on every sample outside block ``j``; the all-data fit is one more group with no sample left out)::

    θ_g = argmin ‖m_g ⊙ e(θ)‖²      (e the model-minus-measured voltage on every record, m_g group g's training mask)

Each group is its own :func:`scipy.optimize.least_squares` problem (trust-region reflective, bounds): fold ``j``'s
optimiser never evaluates a residual that contains block ``j``, so its parameters are independent of that block's
voltage bit for bit (one joint problem over all folds would couple them through its shared trust region and
stopping rule). Every residual evaluation simulates the records once (:func:`~socbench.identify.lsq.simulate_voltage`:
the compiled step loop where the model lowers, else the whole-record open loop,
:meth:`~socbench.models.base.Model.open_loop`; its cost grows with the parameter batch, so nothing is gained by
batching the folds), every Jacobian the ``P`` forward differences as one parameter batch. This is
:func:`socbench.identify.fit_parameters` for several records and several masks at once; it fits on the same compressed
records (:func:`~socbench.identify.compress.compress_profile`).

:func:`cv_residual` then scores: every sample of block ``j`` by fold ``j``'s parameters (measured − model, on every
sample of the binned records, not the compressed ones).
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..errors import ConfigError, ModelError
from ..identify.compress import compress_profile
from ..identify.lsq import MAX_SOC_STEP, NONFINITE_RESIDUAL, one_blas_thread, simulate_voltage
from .data import Folds


@dataclass(frozen=True, eq=False)
class FoldFit:
    """Fitted parameters, one row per group (``groups[g]`` is a fold index, or None for the all-data fit)."""

    thetas: np.ndarray
    groups: tuple
    names: tuple
    nfev: int
    njev: int
    seconds: float

    def row(self, group) -> np.ndarray:
        return self.thetas[self.groups.index(group)]

    def folds(self) -> np.ndarray:
        """``(k, P)``: the rows of the folds ``0 … k − 1`` in order."""
        return np.stack([self.row(j) for j in sorted(g for g in self.groups if g is not None)])


def simulate_records(build, thetas, records, soc0s) -> list:
    """Open-loop voltage ``(B, n_r)`` of ``build(thetas)`` (``thetas (B, P)``) on every record; NaN where the model
    rejects the parameters. ``build`` returns a model, or ``(model, offsets (B, records) or None)``: a voltage offset
    added to each record's output."""
    thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
    B = thetas.shape[0]
    try:
        built = build(thetas)
    except (ModelError, ConfigError, FloatingPointError):
        return [np.full((B, p.n), np.nan) for p in records]
    model, offsets = built if isinstance(built, tuple) else (built, None)
    out = []
    with np.errstate(all="ignore"):
        for r, (p, z0) in enumerate(zip(records, soc0s)):
            try:
                y = simulate_voltage(model, p.time_s, p.current_a, p.temperature_c, model.x0(z0, (B,)))
            except (ModelError, ConfigError, FloatingPointError):
                y = np.full((B, p.n), np.nan)
            if offsets is not None:
                y = y + np.broadcast_to(offsets, (B, len(records)))[:, r:r + 1]
            out.append(np.broadcast_to(y, (B, p.n)))
    return out


def fit_folds(build, folds: Folds, theta0, lower, upper, soc0s, *, groups=None, names=None, compress=None,
              max_nfev: int = 15, diff_step: float = 1e-6) -> FoldFit:
    """Fit θ for every group of ``groups`` (default: the folds ``0 … k − 1``; ``None`` in it = all data) at once.

    ``build(θ (B, P)) -> model`` with the parameter batch on the leading axis; ``theta0`` is ``(P,)`` (one start for
    every group) or ``(G, P)``; ``soc0s`` the initial SOC of each record; ``compress`` the options of
    :func:`~socbench.identify.compress.compress_profile` (None: fit every binned sample).
    """
    t0 = _time.perf_counter()
    groups = tuple(range(folds.k)) if groups is None else tuple(groups)
    G = len(groups)
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    P = lower.size
    th0 = np.broadcast_to(np.asarray(theta0, dtype=float), (G, P))
    inner = 1e-9 * (upper - lower)
    th0 = np.clip(th0, lower + inner, upper - inner)
    names = tuple(names) if names is not None else tuple(f"theta{j}" for j in range(P))
    # the fitting view of every record: compressed, with each group's training mask on the kept samples
    recs, masks = [], []
    built = build(th0[:1])
    cap = float(getattr(built[0] if isinstance(built, tuple) else built, "capacity_ah", 0.0) or 0.0)
    for r, p in enumerate(folds.records):
        if compress:
            opts = dict(compress)
            opts.setdefault("max_ah", MAX_SOC_STEP * cap or None)
            c = compress_profile(p, **opts)
            prof, idx = c.profile, c.index
        else:
            prof, idx = p, np.arange(p.n)
        recs.append(prof)
        masks.append(np.stack([folds.train_mask(r, g)[idx] for g in groups]).astype(float))
    v_meas = [p.voltage_v for p in recs]

    def residuals(thetas, rows):
        """``(len(rows), N)``: masked model − measured of the variants ``thetas`` on every record, row ``b`` with the
        mask of group ``rows[b]``."""
        parts = []
        for y, v, m in zip(simulate_records(build, thetas, recs, soc0s), v_meas, masks):
            e = y - v
            e = np.where(np.isfinite(e), e, NONFINITE_RESIDUAL)
            parts.append(e * m[rows])
        return np.concatenate(parts, axis=1)

    counts = {"nfev": 0, "njev": 0}
    out = np.empty((G, P))
    for g in range(G):
        cache = {}

        def fun(theta, g=g, cache=cache):
            key = theta.tobytes()
            if key not in cache:
                counts["nfev"] += 1
                cache.clear()
                cache[key] = residuals(theta[None], [g])[0]
            return cache[key]

        def jac(theta, g=g):
            counts["njev"] += 1
            r0 = fun(theta)
            h = diff_step * np.maximum(1.0, np.abs(theta))
            h = np.where(theta + h > upper, -h, h)
            rv = residuals(theta[None] + np.diag(h), [g] * P)
            return ((rv - r0[None]) / h[:, None]).T

        with one_blas_thread():  # the optimiser's SVD of a (samples × P) Jacobian every iteration
            sol = least_squares(fun, th0[g], jac=jac, bounds=(lower, upper), method="trf", x_scale="jac",
                                ftol=1e-6, xtol=1e-6, gtol=1e-8, max_nfev=max_nfev)
        out[g] = sol.x
    return FoldFit(out, groups, names, counts["nfev"], counts["njev"], _time.perf_counter() - t0)


def cv_residual(model_or_build, folds: Folds, soc0s, thetas=None):
    """``(residual, per-fold sse, per-fold n)``: measured − model on every sample of every record, block ``j`` by
    fold ``j``. With ``thetas (k, P)`` the model is ``build(thetas)`` (one variant per fold); without, one model
    scores every block (a base model: nothing fitted on the evaluation data)."""
    if thetas is None:
        ys = simulate_records(lambda th: model_or_build, np.zeros((1, 0)), folds.records, soc0s)
    else:
        ys = simulate_records(model_or_build, thetas, folds.records, soc0s)
    res, sse, n = [], np.zeros(folds.k), np.zeros(folds.k)
    for p, b, y in zip(folds.records, folds.blocks, ys):
        pred = y[b, np.arange(p.n)] if y.shape[0] > 1 else y[0]
        e = p.voltage_v - pred
        e = np.where(np.isfinite(e), e, NONFINITE_RESIDUAL)
        res.append(e)
        sse += np.bincount(b, weights=e * e, minlength=folds.k)
        n += np.bincount(b, minlength=folds.k)
    return np.concatenate(res), sse, n
