"""The Estimator protocol and the plumbing every filter shares: inputs, initial conditions, output recording.

``Estimator(model, noise=None, **options)`` — configuration only (scikit-learn style); ``run(profile, soc0=None,
P0=None, seed=None) -> Estimate`` does the work, batched over the profile's Monte Carlo runs. A filter subclass writes
its time loop in ``_run(inputs, x0, P0, seed)`` with the equations next to the code; this module holds what is not
specific to one filter:

* :class:`Inputs`   the profile as ``(R, T)`` arrays (current, voltage, temperature), the step lengths, and the
                    current variance the zero-order hold misses over each step (``hold_var``: nonzero across a
                    logger pause, :func:`socbench.segments.hold_var`; every filter widens each state by it
                    there, :func:`socbench.estimators.noise.hold_cov`);
* initial state     ``x0 = model.x0(soc0)``; ``soc0`` scalar or ``(R,)`` (default: the SOC the model reads off the
                    first voltage with the first current flowing, ``Model.soc_from_voltage``);
                    ``P0`` scalar (SOC variance), ``(n,)`` diagonal, ``(n, n)`` or ``(R, n, n)``; by default
                    ``diag(model.initial_sd(soc0_sd, state0_sd)²)`` (``soc0_sd²``, ``state0_sd²``, …; an augmented
                    model's effect states declare their own); a filter that reads the SOC through the
                    output's slope (the EKF family, ``linearises_output``) whose prior mean lies where the OCV curve
                    is held flat (beyond its extrapolation band, :mod:`socbench.ocv`) has it moved to the band's edge
                    when that lies within one prior SD (:func:`out_of_held_ocv`);
* :class:`Recorder` preallocated outputs, with the freeze of failed runs (outputs repeat their last finite values).

Options common to all filters (all keyword): ``Q``, ``R`` (overrides, see :class:`~.noise.NoiseModel`),
``gate_alpha`` (χ² gate tail probability, None = off), ``gate_release``, ``var_max``, ``nis_max``, ``psd_floor``,
``psd_rel_floor``, ``soc0_sd``, ``state0_sd``, ``store_states``, ``engine``, ``hold`` (False: the filter ignores
the current the hold misses across a logger pause, ``Inputs.hold_var`` all zero, as every filter did before it).

Engines. ``engine="numpy"`` runs the filter's numpy loop (``_run``: batched over runs, the reference every other
engine is tested against); ``engine="compiled"`` its compiled kernel (``_run_compiled``: numba, the time loop of every
run compiled, runs in parallel; :mod:`socbench.kernels`), raising :class:`ConfigError` if it has none for this model;
``engine="auto"`` (default) the compiled kernel when numba is installed and the model, its parameters and the noise
have a compiled form, else numpy. ``Estimate.info["engine"]`` says which ran, ``info["engine_note"]`` why numpy ran
under ``auto`` (e.g. a strict-mode model). Both give the same numbers to 1e-9 (tests/test_kernels.py).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from ..errors import ConfigError, DataError
from ..profile import Profile
from .estimate import Estimate
from .noise import NoiseModel, SensorNoise
from .safety import Gate, diverged, project_soc, repair_psd, symmetrise

COMMON_OPTIONS: dict = {
    "Q": None,
    "R": None,
    "gate_alpha": 1e-6,
    "gate_release": 10,
    "var_max": 1.0,
    "nis_max": 1e10,
    "psd_floor": 1e-15,
    "psd_rel_floor": 1e-12,
    "soc0_sd": 0.1,
    "state0_sd": 0.01,
    "store_states": False,
    "engine": "auto",
    "hold": True,
}
ENGINES = ("auto", "numpy", "compiled")


@dataclass(frozen=True, eq=False)
class Inputs:
    """A profile as the filters consume it: every signal ``(R, T)``; ``temp`` None when the profile has none."""

    time_s: np.ndarray
    dt: np.ndarray  # (T-1,)
    current: np.ndarray
    voltage: np.ndarray
    temp: np.ndarray | None
    name: str
    capacity_ah: float | None = None  # the record's declared capacity (the coulomb counter's default)
    hold_var: np.ndarray | None = None  # (T-1,) A²: the current the hold misses over each step (None: zeros)

    def __post_init__(self):
        if self.hold_var is None:
            object.__setattr__(self, "hold_var", np.zeros(self.dt.size))

    @property
    def n_runs(self) -> int:
        return int(self.current.shape[0])

    @property
    def n(self) -> int:
        return int(self.time_s.size)

    def temp_at(self, k: int):
        return None if self.temp is None else self.temp[:, k]

    @classmethod
    def from_profile(cls, profile: Profile, hold: bool = True) -> Inputs:
        if not isinstance(profile, Profile):
            raise ConfigError(f"expected a Profile, got {type(profile).__name__}")
        profile.require("voltage_v")
        R = profile.n_runs
        T = profile.n

        def full(a):
            return None if a is None else np.ascontiguousarray(np.broadcast_to(a, (R, T)), dtype=float)

        from ..segments import hold_var

        return cls(profile.time_s, profile.dt, full(profile.current_a), full(profile.voltage_v),
                   full(profile.temperature_c), profile.name, profile.meta.capacity_ah,
                   hold_var(profile) if hold else None)

    def slice(self, start: int, stop: int) -> Inputs:
        """Samples ``start:stop`` (a segment of the record)."""
        def cut(a):
            return None if a is None else np.ascontiguousarray(a[:, start:stop])

        steps = slice(start, max(stop - 1, start))
        return Inputs(self.time_s[start:stop], self.dt[steps], cut(self.current), cut(self.voltage), cut(self.temp),
                      self.name, self.capacity_ah, np.ascontiguousarray(self.hold_var[steps]))


class Estimator:
    """Base class: configuration in ``__init__``, work in :meth:`run`."""

    name: ClassVar[str] = ""
    #: filter-specific options and their defaults (the common ones are in COMMON_OPTIONS)
    defaults: ClassVar[dict] = {}
    #: how the noise recipe's model error enters this filter (:func:`socbench.estimators.model_error.apply`):
    #: "states" (coloured-noise states in the model) or "inflated" (one white R)
    model_error_form: ClassVar[str] = "states"
    #: the filter reads the SOC through the linearised output (∂h/∂z): a prior mean where the OCV curve is held flat
    #: gets no gain there and never leaves (:func:`out_of_held_ocv`)
    linearises_output: ClassVar[bool] = False

    def __init__(self, model, noise: SensorNoise | None = None, **options):
        for attr in ("step", "output", "n_states", "x0"):
            if not hasattr(model, attr):
                raise ConfigError(f"{type(model).__name__} is not a Model (no '{attr}')")
        known = {**COMMON_OPTIONS, **self.defaults}
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise ConfigError(f"{self.name}: unknown option '{unknown[0]}'; known: {', '.join(sorted(known))}")
        self.model = model
        self.options = {**known, **options}
        self.n = int(model.n_states)
        walk = model.walk_var() if hasattr(model, "walk_var") else None
        self.noise = NoiseModel(noise, self.n, self.options["Q"], self.options["R"], walk)
        for key in ("var_max", "nis_max", "soc0_sd", "state0_sd"):
            if not self.options[key] > 0:
                raise ConfigError(f"{self.name}: option {key} must be > 0, got {self.options[key]!r}")
        if self.options["gate_alpha"] is not None and not 0 < self.options["gate_alpha"] < 1:
            raise ConfigError(f"{self.name}: gate_alpha must be in (0, 1) or None")
        if self.options["engine"] not in ENGINES:
            raise ConfigError(f"{self.name}: engine must be one of {', '.join(ENGINES)}, "
                              f"got {self.options['engine']!r}")

    def __repr__(self) -> str:
        return f"{type(self).__name__}(model={getattr(self.model, 'name', '?')!r})"

    # ------------------------------------------------------------------ the one verb
    def run(self, profile: Profile, soc0=None, P0=None, seed=None, segments=None, x0=None) -> Estimate:
        """Estimate SOC over every run of ``profile`` (see the module docstring for ``soc0`` and ``P0``).

        A record of several discharges (battery swaps, recharges: :mod:`socbench.segments`) is filtered segment by
        segment: ``segments=None`` finds them, ``False`` filters the record as one piece, or pass a
        :class:`~socbench.segments.Segments`. ``soc0`` (or ``x0``, a full initial state ``(R, n)`` that replaces
        ``model.x0(soc0)``) starts the first segment; every later one restarts the
        filter as at a record's start — SOC read off its first voltage (an estimator never reads
        the reference it is scored against), the other states at rest, covariance ``P0`` — and the current across
        a boundary is never used. ``Estimate.domain`` is :func:`socbench.domain.estimate_domain` of the result.
        """
        from ..domain import estimate_domain
        from ..segments import resolve

        inputs = Inputs.from_profile(profile, self.options["hold"])
        segs = resolve(segments, profile, self.model.ocv, self.model.capacity_ah)
        P0 = self.initial_cov(inputs.n_runs, P0)
        if x0 is not None:
            x0 = np.ascontiguousarray(np.broadcast_to(np.asarray(x0, dtype=float), (inputs.n_runs, self.n)))
        moved = None
        if x0 is None:
            start = self.initial_state(inputs, soc0)
            if self.linearises_output:
                start, moved = out_of_held_ocv(self.model, start, np.sqrt(P0[:, 0, 0]), inputs.temp_at(0))
        else:
            start = x0
        if segs.count == 1:
            est = self._run_engine(inputs, start, P0, seed)
        else:
            parts = []
            for s, (a, b) in enumerate(segs.spans()):
                part = inputs.slice(a, b)  # a later segment starts where its first voltage reads: never held
                first = self.initial_state(part, None) if s else start
                parts.append(self._run_engine(part, first, P0, segment_seed(seed, s)))
            est = Estimate.join(parts, inputs.time_s, segs)
        if moved is not None:
            est.info["soc0_moved_out_of_held_ocv"] = moved
        t0 = time.perf_counter()
        domain = estimate_domain(self.model, est, profile)
        domain["segments"] = segs.count
        domain["seconds"] = time.perf_counter() - t0  # not filter time: timings of the filter subtract it
        return replace(est, domain=domain, segments=segs)

    def _run(self, inputs: Inputs, x0: np.ndarray, P0: np.ndarray, seed) -> Estimate:  # pragma: no cover
        raise NotImplementedError

    def _run_compiled(self, job) -> Estimate | None:
        """The compiled form of :meth:`_run` on a :class:`socbench.kernels.engine.Job` (None: not available here,
        or a run met a condition only the numpy engine reports). Subclasses with a kernel override this."""
        return None

    def engine_plan(self):
        """``(lowered model or None, why not compiled)`` under this estimator's ``engine`` option."""
        if self.options["engine"] == "numpy":
            return None, "engine='numpy'"
        cached = self.__dict__.get("_engine_plan")
        if cached is None:  # the model and options are fixed at construction: lower once
            from ..kernels.engine import plan

            cached = self._engine_plan = plan(self)
        lowered, why = cached
        if lowered is None and self.options["engine"] == "compiled":
            raise ConfigError(f"{self.name}: engine='compiled' is not available: {why}")
        return lowered, why

    def _run_engine(self, inputs: Inputs, x0: np.ndarray, P0: np.ndarray, seed, **extra) -> Estimate:
        """Run the compiled kernel when the engine plan allows, else (or when it hands back) the numpy loop."""
        lowered, why = self.engine_plan()
        if lowered is not None:
            from ..kernels.engine import Job

            est = self._run_compiled(Job(self, lowered, inputs, x0, P0), seed=seed, **extra)
            if est is not None:
                est.info["engine"] = "compiled"
                return est
            why = "the compiled kernel handed the batch back (a model condition only numpy reports)"
        est = self._run(inputs, x0, P0, seed, **extra)
        est.info["engine"] = "numpy"
        if self.options["engine"] == "auto":
            est.info["engine_note"] = why
        return est

    # ------------------------------------------------------------------ per-run bookkeeping
    def recorder(self, inputs: Inputs, x0: np.ndarray, P0: np.ndarray) -> Recorder:
        """The output buffers of a run batch ``x0 (R, n)``, ``P0 (R, n, n)``: initial SOC and its SD from them."""
        return Recorder(inputs, self.n, self.options["store_states"], x0[:, 0], np.sqrt(P0[:, 0, 0]))

    def gate(self, n_runs: int) -> Gate:
        """The innovation gate with this estimator's ``gate_alpha`` and ``gate_release``."""
        return Gate(n_runs, self.options["gate_alpha"], self.options["gate_release"])

    # ------------------------------------------------------------------ initial conditions
    def initial_state(self, inputs: Inputs, soc0) -> np.ndarray:
        R = inputs.n_runs
        if soc0 is None:
            soc0 = self.model.soc_from_voltage(inputs.voltage[:, 0], inputs.current[:, 0], inputs.temp_at(0))
        soc0 = np.asarray(soc0, dtype=float)
        if soc0.ndim > 1 or (soc0.ndim == 1 and soc0.size not in (1, R)):
            raise ConfigError(f"soc0 must be a scalar or have one value per run ({R}), got shape {soc0.shape}")
        if not np.all(np.isfinite(soc0)) or np.any((soc0 < 0) | (soc0 > 1)):
            raise DataError(f"initial SOC must be a fraction in [0, 1], got {soc0.ravel()[0]:g}", column="soc0")
        return self.model.x0(np.broadcast_to(soc0, (R,)), (R,))

    def initial_cov(self, R: int, P0) -> np.ndarray:
        if hasattr(self.model, "initial_sd"):
            sd = np.asarray(self.model.initial_sd(self.options["soc0_sd"], self.options["state0_sd"]), dtype=float)
        else:
            sd = np.full(self.n, self.options["state0_sd"])
            sd[0] = self.options["soc0_sd"]
        return initial_cov(R, P0, self.n, sd)


def out_of_held_ocv(model, x0: np.ndarray, sd: np.ndarray, temp) -> tuple[np.ndarray, dict | None]:
    """``(x0, moved)``: the initial states ``x0 (R, n)`` with each SOC mean that lies where ``model``'s OCV curve is
    held flat (more than :data:`~socbench.ocv.EXCURSION_FLAG` beyond its rest points at the temperature ``temp``)
    moved to the edge of the extrapolation band, where the curve still slopes, when that is at most the run's prior
    SD ``sd (R,)`` away; ``moved`` says how many runs and how far (None: none).

    Why: there ``∂h/∂z = 0``, so a filter linearised at the mean (the EKF family) gets no gain on the SOC, gates every
    innovation and counts coulombs from the guess for the whole record however wide its prior (``--soc0 0 --soc0-sd
    0.5`` on a fitted curve whose lowest rest point is at 9.4 %: an EKF held at 0 through a drive from ~80 %, SOC RMSE
    70.8 %, while the UKF's sigma points, spread into the curve, found the SOC: 0.15 %). Within one SD the prior
    allows the edge as well as the guess; a prior surer than that of an SOC the model cannot read is the user's and is
    kept."""
    from ..ocv import EXCURSION_FLAG

    z = x0[:, 0]
    exc = np.asarray(model.ocv.excursion(z, temp), dtype=float)
    move = exc - EXCURSION_FLAG
    held = (move > 0.0) & (move <= sd)
    if not held.any():
        return x0, None
    below = np.asarray(model.ocv.excursion(z + exc, temp)) < exc  # stepping up by the excursion reaches the curve
    x0 = x0.copy()
    x0[:, 0] = np.where(held, np.where(below, z + move, z - move), z)
    return x0, {"runs": int(held.sum()), "from": float(z[held][0]), "to": float(x0[held, 0][0])}


def initial_cov(R: int, P0, n: int, default_sd) -> np.ndarray:
    """``(R, n, n)`` initial covariances from ``P0``: None (``diag(default_sd²)``), a scalar (the SOC variance, the
    rest from ``default_sd``), ``(n,)`` variances, ``(n, n)`` or ``(R, n, n)``; symmetric positive definite."""
    base = np.diag(np.asarray(default_sd, dtype=float) ** 2)
    if P0 is None:
        P = base
    else:
        P = np.asarray(P0, dtype=float)
        if P.ndim == 0:
            P = base.copy()
            P[0, 0] = float(P0)
        elif P.shape == (n,):
            P = np.diag(P)
        elif P.shape not in ((n, n), (R, n, n)):
            raise ConfigError(f"P0 must be a scalar, ({n},), ({n}, {n}) or ({R}, {n}, {n}); got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise ConfigError("P0 must be finite")
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    if np.min(np.linalg.eigvalsh(P)) <= 0:
        raise ConfigError("P0 must be positive definite")
    return np.ascontiguousarray(np.broadcast_to(P, (R, n, n)))


def segment_seed(seed, s: int):
    """The random seed of segment ``s``: ``seed`` itself for the first (a record in one piece is unchanged), an
    independent stream derived from ``(seed, s)`` for the others; None stays None (fresh entropy)."""
    if seed is None or s == 0:
        return seed
    return int(np.random.SeedSequence([int(seed), int(s)]).generate_state(1, np.uint64)[0] >> np.uint64(1))


class Recorder:
    """Preallocated ``(R, T)`` outputs; rows of failed runs repeat their last recorded values from failure on."""

    def __init__(self, inputs: Inputs, n_states: int, store_states: bool, soc0, std0):
        R, T = inputs.n_runs, inputs.n
        self.inputs = inputs
        self.soc = np.empty((R, T))
        self.soc_std = np.empty((R, T))
        self.v_pred = np.empty((R, T))
        self.innovation = np.empty((R, T))
        self.innovation_var = np.empty((R, T))
        self.clamped = np.zeros((R, T), dtype=bool)
        self.gated = np.zeros((R, T), dtype=bool)
        self.x = np.empty((R, T, n_states)) if store_states else None
        self.P_diag = np.empty((R, T, n_states)) if store_states else None
        self.failed = np.zeros(R, dtype=bool)
        self.failed_at = np.full(R, -1)
        self.failed_reason = np.zeros(R, dtype=np.int8)  # safety.DIVERGENCE_REASONS
        self.psd_repairs = np.zeros(R, dtype=int)  # updates whose covariance needed the PSD repair, per run
        self._soc0 = np.asarray(soc0, dtype=float)
        self._std0 = np.asarray(std0, dtype=float)
        self._x0 = None

    def fail(self, k: int, bad: np.ndarray) -> np.ndarray:
        """Mark runs ``bad`` failed at sample ``k``; returns the (R,) mask of all failed runs.

        ``bad`` is a reason code per run (:func:`~.safety.diverged`, nonzero = failed) or a bool mask (reason 1,
        non-finite state)."""
        bad = np.asarray(bad)
        new = (bad != 0) & ~self.failed
        if new.any():
            self.failed_at[new] = k
            self.failed_reason[new] = bad[new] if bad.dtype != bool else 1
            self.failed |= new
        return self.failed

    def record(self, k, soc, soc_std, v_pred, innovation, innovation_var, clamped, gated, x=None, P_diag=None):
        self.soc[:, k] = soc
        self.soc_std[:, k] = soc_std
        self.v_pred[:, k] = v_pred
        self.innovation[:, k] = innovation
        self.innovation_var[:, k] = innovation_var
        self.clamped[:, k] = clamped
        self.gated[:, k] = gated
        if self.x is not None:
            self.x[:, k] = x
            self.P_diag[:, k] = P_diag
        dead = self.failed
        if dead.any():
            self._freeze(k, dead)

    def _freeze(self, k: int, dead: np.ndarray) -> None:
        if k > 0:
            for a in (self.soc, self.soc_std, self.v_pred, self.innovation, self.innovation_var):
                a[dead, k] = a[dead, k - 1]
            if self.x is not None:
                self.x[dead, k] = self.x[dead, k - 1]
                self.P_diag[dead, k] = self.P_diag[dead, k - 1]
        else:  # failed on the very first sample: the initial guess, a zero innovation
            self.soc[dead, 0] = np.broadcast_to(self._soc0, dead.shape)[dead]
            self.soc_std[dead, 0] = np.broadcast_to(self._std0, dead.shape)[dead]
            self.v_pred[dead, 0] = self.inputs.voltage[dead, 0]
            self.innovation[dead, 0] = 0.0
            self.innovation_var[dead, 0] = 1.0
            if self.x is not None:
                self.x[dead, 0] = 0.0
                self.x[dead, 0, 0] = self.soc[dead, 0]
                self.P_diag[dead, 0] = 0.0
                self.P_diag[dead, 0, 0] = self.soc_std[dead, 0] ** 2
        self.clamped[dead, k] = False
        self.gated[dead, k] = False

    def finish(self, estimator: str, model, info: dict | None = None) -> Estimate:
        return Estimate(
            time_s=self.inputs.time_s, soc=self.soc, soc_std=self.soc_std, v_pred=self.v_pred,
            innovation=self.innovation, innovation_var=self.innovation_var, failed=self.failed.copy(),
            failed_at=self.failed_at.copy(), clamped=self.clamped, gated=self.gated, x=self.x, P_diag=self.P_diag,
            estimator=estimator, model=getattr(model, "name", type(model).__name__),
            state_names=tuple(model.state_names), info={"psd_repairs": self.psd_repairs.copy(), **(info or {})},
            failed_reason=self.failed_reason.copy(),
        )


def restore(values: np.ndarray, good: np.ndarray, failed: np.ndarray) -> None:
    """In place: rows of failed runs take their last good (finite) values, so the batch keeps computing cleanly."""
    if failed.any():
        values[failed] = good[failed]


def settle_update(rec: Recorder, k: int, x, P, x_good, P_good, v_pred, e, S, nis, gated, opt: dict, factor=False):
    """The safety tail every Kalman update shares, in order: symmetrise and PSD-repair ``P``, bring the SOC back into
    [0, 1] by projecting the state onto the bound (:func:`~.safety.project_soc`, flagged),
    detect divergence, put failed runs back on their last good state, record sample ``k``. Returns ``(x, P)``.

    ``factor=True``: ``P`` is a lower-triangular square root ``L`` of the covariance (``L Lᵀ``, the square-root
    filters); it is PSD by construction, so nothing is symmetrised or repaired, and the recorded variances are the
    row sums ``Σ_j L_ij²``."""
    if factor:  # clamping the SOC cannot change what is finite: check first
        var = np.einsum("rij,rij->ri", P, P)
        bad = diverged(x, var[:, 0], nis, opt["var_max"], opt["nis_max"]) | ~np.all(np.isfinite(var), axis=-1)
    else:
        P, repaired = repair_psd(symmetrise(P), opt["psd_floor"], opt["psd_rel_floor"])
        rec.psd_repairs += repaired & ~rec.failed  # a failed run is frozen: it counts nothing more
        bad = None
    clamped = project_soc(x, P, factor)
    if bad is None:
        bad = diverged(x, P, nis, opt["var_max"], opt["nis_max"])
    failed = rec.fail(k, bad)
    restore(x, x_good, failed)
    restore(P, P_good, failed)
    if factor:
        var = np.einsum("rij,rij->ri", P, P)
    else:
        var = np.diagonal(P, 0, -2, -1)
    rec.record(k, x[:, 0], np.sqrt(var[:, 0]), v_pred, e, S, clamped, gated, x, var)
    return x, P


def scheduled_jacobian(model, F):
    """``F`` with ``∂x_j⁺/∂z = 0`` for every state ``j`` but the SOC when ``model.schedule_soc`` (else ``F``).

    Parameter scheduling: the parameters of the dynamics (R1(z), C1(z), …) are looked up at the estimated SOC, but
    their SOC *slope* is not SOC information. A table fitted point by point on HPPC pulses has slopes the cell does not
    have; differentiated, they let a filter read the SOC off the polarisation's shape to a precision the model does not
    have (``docs/real_data.md`` §4b measures it on the Panasonic US06)."""
    if not getattr(model, "schedule_soc", False):
        return F
    F = np.array(F, dtype=float, copy=True)
    F[..., 1:, 0] = 0.0
    return F


def equilibrium(model, z, temp=None, jac: bool = False):
    """The model's equilibrium voltage ``E(z, T) = h([z, 0, …, 0], I = 0, T)`` and, with ``jac``, ``∂E/∂z``.

    Every state but the SOC at zero and no current: the OCV of an RC model, ``U(z) + g(z)`` of a static-term model,
    the augmented states' terms gone (their rest values are zero). What of the output a filter may read the SOC off
    under parameter scheduling (:func:`scheduled_output`)."""
    z = np.asarray(z, dtype=float)
    xe = np.zeros(z.shape + (model.n_states,))
    xe[..., 0] = z
    y, H, _ = model.output(xe, np.zeros(z.shape), temp, jac=jac)
    return (y, H[..., 0]) if jac else (y, None)


def scheduled_output(model, x, i, temp, jac: bool = True):
    """``model.output`` of the means ``x (R, n)`` for the EKF family; with ``model.schedule_soc`` the output's SOC
    column is the equilibrium slope, ``H_z = ∂E/∂z`` (:func:`equilibrium`).

    The output counterpart of :func:`scheduled_jacobian`: the SOC tables of the output's parameters (``R0(z)``, the
    recipe's error scales σ(z)…) are looked up at the estimated SOC but their slopes are not SOC information; the
    SOC is read off the voltage through the equilibrium curve alone."""
    y, H, D = model.output(x, i, temp, jac=jac)
    if jac and getattr(model, "schedule_soc", False):
        H = np.array(H, dtype=float, copy=True)
        H[..., 0] = equilibrium(model, x[..., 0], temp, jac=True)[1]
    return y, H, D


def scheduled_points_output(model, X, i, temp, jac: bool):
    """``model.output`` of sigma points ``X (R, S, n)`` whose point 0 is the mean; with ``model.schedule_soc`` the
    sigma-point form of :func:`scheduled_output`: every point's output is taken at the mean SOC and its own SOC
    deviation enters through the equilibrium curve alone, ``y_s = h(X_s|z=z̄) + E(z_s) − E(z̄)``."""
    if not getattr(model, "schedule_soc", False):
        return model.output(X, i, temp, jac=jac)
    zs = X[..., 0]
    zbar = np.broadcast_to(X[:, :1, 0], zs.shape)
    Xs = np.array(X, dtype=float, copy=True)
    Xs[..., 0] = zbar
    Y, H, D = model.output(Xs, i, temp, jac=jac)
    return Y + equilibrium(model, zs, temp)[0] - equilibrium(model, zbar, temp)[0], H, D


def scheduled_step(model, X, x, i, dt, temp, jac):
    """``model.step`` of sigma points ``X (R, S, n)`` around the mean ``x (R, n)``; with ``model.schedule_soc`` the
    sigma-point form of :func:`scheduled_jacobian`: every point steps at the mean SOC (so its other states see the
    mean's parameters) and keeps its own SOC deviation (the counter's ``∂z⁺/∂z = 1``)."""
    if not getattr(model, "schedule_soc", False):
        return model.step(X, i, dt, temp, jac=jac)
    dz = X[..., 0] - x[:, None, 0]
    Xs = np.array(X, dtype=float, copy=True)
    Xs[..., 0] = x[:, None, 0]
    Xf, F, B = model.step(Xs, i, dt, temp, jac=jac)
    Xf = np.array(Xf, copy=True)
    Xf[..., 0] += dz
    return Xf, F, B


def settle_predict(rec: Recorder, k: int, x, P, x_good, P_good) -> None:
    """The safety tail every prediction shares (in place): runs whose predicted state or covariance (or its square
    root) is not finite fail at sample ``k``; failed runs go back to their last good values; the others become the
    new last good values."""
    failed = rec.fail(k, diverged(x, P, None, np.inf, np.inf))
    restore(x, x_good, failed)
    restore(P, P_good, failed)
    np.copyto(x_good, x, where=~failed[:, None])
    np.copyto(P_good, P, where=~failed[:, None, None])
