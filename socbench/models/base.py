"""The Model protocol: a discrete-time state-space ECM with analytic Jacobians, batched over leading axes.

Conventions (DESIGN.md, ECM_SPEC §2):

* state ``x`` has shape ``(..., n)`` with ``x[..., 0] = z`` (SOC) for every model; input ``I`` (A, positive =
  discharge) and temperature ``T`` (°C) broadcast to ``x.shape[:-1]``; ``dt`` may vary per step;
* ``x_{k+1} = f(x_k, I_k, dt_k, T_k)`` with zero-order hold on ``I``; ``y_k = h(x_k, I_k, T_k)`` with direct
  feed-through of the same-sample current;
* ``F = ∂f/∂x`` ``(..., n, n)``, ``B = ∂f/∂I`` ``(..., n)``, ``H = ∂h/∂x`` ``(..., n)``, ``D = ∂h/∂I`` ``(...)``;
* temperature: every parameter and the OCV curve are looked up at the cell temperature ``T`` (:meth:`Model.p`,
  :meth:`Model.params_at`, ``self.ocv.value_and_slope(z, temp)``); a parameter set measured at one temperature ignores
  it, a set with temperature tables (:class:`~socbench.models.params.TemperatureTable`,
  :class:`~socbench.ocv.TemperatureOCV`) interpolates in it. ``T`` is an input like ``I``: no Jacobian w.r.t. it.

A model implements two methods, each returning the value and, on request, its Jacobians from the same intermediate
quantities (one evaluation per filter step):

* ``step(x, i, dt, temp, jac, guards) -> (x⁺, F, B)``
* ``output(x, i, temp, jac, guards) -> (y, H, D)``

``f, h, F, H, B, D`` are thin views of these. Models are pure: parameters are fixed at construction
(:class:`~socbench.models.params.ModelParams`), nothing mutates afterwards.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ..errors import ConfigError
from ..ocv import T_REF_C
from ..profile import Profile
from .blocks import ROBUST, STRICT, GuardLog, soc_step
from .params import ModelParams, Polynomial
from .recurrence import running_sum

# T_REF_C: the reference temperature when a profile carries none
__all__ = ["KernelSpec", "Model", "Simulation", "T_REF_C"]


@dataclass(frozen=True, eq=False)
class Simulation:
    """Result of :meth:`Model.simulate`: voltage ``(…, T)``, states ``(…, T, n)``, guard activity (share of samples
    each guard acted on), the segments simulated (:mod:`socbench.segments`) and the domain report
    (:func:`socbench.domain.domain_report`; ``domain_fractions`` is it as shares of samples, guards included)."""

    time_s: np.ndarray
    voltage_v: np.ndarray
    states: np.ndarray
    state_names: tuple
    guard_fractions: dict = field(default_factory=dict)
    segments: object = None
    domain: dict = field(default_factory=dict)
    domain_fractions: dict = field(default_factory=dict)

    @property
    def soc(self) -> np.ndarray:
        return self.states[..., 0]


@dataclass(frozen=True)
class KernelSpec:
    """How a model lowers to the compiled interpreter (:mod:`socbench.kernels`): its ``family`` (a key of
    ``socbench.kernels.lowering.FAMILIES``), its parameters in the order the family's compiled code reads them, the
    index ranges ``[j0, j1)`` of them that ``step`` and ``output`` read (evaluated once per call, before the family's
    code runs), and two small integers the family interprets (``sub``: e.g. the number of RC branches; ``flags``:
    options)."""

    family: str
    params: tuple
    step: tuple
    output: tuple
    sub: int = 0
    flags: int = 0


class Model(ABC):
    """Base class of every ECM. Subclasses set the class attributes and implement ``step`` and ``output``."""

    #: registry name
    name: ClassVar[str] = ""
    #: human title, e.g. "Thevenin (1 RC)"
    title: ClassVar[str] = ""
    #: literature source of the structure
    source: ClassVar[str] = ""
    #: ECM_SPEC section / paper number
    paper_number: ClassVar[int | None] = None
    #: parameters the model needs (units in ``param_units``)
    param_names: ClassVar[tuple] = ()
    param_units: ClassVar[dict] = {}
    #: one line on what was corrected against the paper
    corrections: ClassVar[str] = ""
    #: for the Kalman-type filters: look the SOC-dependent parameters of the dynamics up at the estimated SOC without
    #: differentiating them (``∂x_j⁺/∂z = 0`` for every state but the SOC; see
    #: :func:`socbench.estimators.base.scheduled_jacobian`). Set on a model by the noise recipe
    #: (:func:`socbench.estimators.model_error.apply`); False: the full Jacobian
    schedule_soc: ClassVar[bool] = False

    def __init__(self, params: ModelParams, mode: str | None = None):
        self.params = params
        self.mode = mode or params.options.get("mode", ROBUST)
        if self.mode not in (ROBUST, STRICT):
            raise ConfigError(f"mode must be '{ROBUST}' or '{STRICT}', got {self.mode!r}")
        missing = [p for p in self.required_params() if p not in params.values]
        if missing:
            raise ConfigError(f"model '{self.name}' needs parameter '{missing[0]}' (have {sorted(params.values)})")
        self._plans = {}  # names -> _ParamPlan (a cache of the stacked polynomial coefficients; not model state)
        self.capacity_ah = float(params.capacity_ah)
        self.eta_charge = float(params.eta_charge)
        self.ocv = params.ocv

    # ------------------------------------------------------------------ description
    def required_params(self) -> tuple:
        return tuple(self.param_names)

    @property
    def state_names(self) -> tuple:
        return ("z",)

    @property
    def n_states(self) -> int:
        return len(self.state_names)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(states={self.state_names}, mode={self.mode!r})"

    # ------------------------------------------------------------------ the two methods a model implements
    @abstractmethod
    def step(self, x, i, dt, temp=None, jac: bool = False, guards: GuardLog | None = None):
        """``(x⁺, F, B)``; ``F`` and ``B`` are None unless ``jac``."""

    @abstractmethod
    def output(self, x, i, temp=None, jac: bool = False, guards: GuardLog | None = None):
        """``(y, H, D)``; ``H`` and ``D`` are None unless ``jac``."""

    def dxdt(self, x, i, temp=None, z_params=None):
        """Continuous-time dynamics ``ẋ`` with every SOC-dependent parameter frozen at ``z_params`` (default: x's z).

        ``step`` must be the exact zero-order-hold discretisation of this (tests integrate it with RK4 and compare).
        States that only exist in discrete time (a sign memory) return 0 here and are listed in ``discrete_states``.
        """
        raise NotImplementedError(f"{type(self).__name__} does not expose its continuous dynamics")

    #: states with no continuous-time counterpart (excluded from the discretisation check)
    discrete_states: ClassVar[tuple] = ()

    # ------------------------------------------------------------------ compiled form
    def kernel_spec(self) -> KernelSpec | None:
        """The compiled family this model lowers to, or None (numpy only). See :mod:`socbench.kernels`."""
        return None

    def lower(self):
        """This model as plain arrays for the compiled kernels (:func:`socbench.kernels.lowering.lower`); raises
        :class:`~socbench.kernels.lowering.NotLowerable` when it has no compiled form."""
        from ..kernels.lowering import lower

        return lower(self)

    # ------------------------------------------------------------------ protocol views
    def x0(self, soc, batch=()) -> np.ndarray:
        """Initial state at SOC ``soc`` from rest: every dynamic state 0. ``soc`` broadcasts against ``batch``."""
        soc = np.asarray(soc, dtype=float)
        shape = np.broadcast_shapes(tuple(batch) if np.ndim(batch) else (int(batch),) if batch else (), soc.shape)
        x = np.zeros(shape + (self.n_states,))
        x[..., 0] = soc
        return x

    def soc_from_voltage(self, v, i=0.0, temp=None, iterations: int = 40) -> np.ndarray:
        """The SOC at which this model, at rest (every dynamic state 0, :meth:`x0`) and with the current ``i``
        flowing, reads the voltage ``v`` (shape of ``v``), clipped to [0, 1]: the root in z of::

            g(z) = U(z, T) − ΔV(z) − v,   ΔV(z) = h(x0(z), 0, T) − h(x0(z), I, T)

        ``U`` the OCV at the cell temperature ``T``, ``ΔV`` the load's instantaneous drop (``R0·I`` for an RC model,
        the static terms' change for the others), found by bisection on [0, 1] (``iterations`` halvings; an end when
        ``g`` keeps one sign there). At ``I = 0`` exactly it is the OCV inverse. A record that starts under load (a
        UAV's take-off) would otherwise start ``R0·I`` of OCV away from its SOC."""
        v = np.asarray(v, dtype=float)
        i = np.broadcast_to(np.asarray(i, dtype=float), v.shape)
        if not np.any(i != 0.0):
            return np.clip(self.ocv.inverse(v, temp=temp), 0.0, 1.0)
        rest = np.zeros(v.shape)

        def g(z):
            x = self.x0(z, v.shape)
            drop = self.output(x, rest, temp)[0] - self.output(x, i, temp)[0]
            return self.ocv.value(z, temp) - drop - v

        lo, hi = np.zeros(v.shape), np.ones(v.shape)
        g_lo = g(lo)
        rising = g(hi) >= g_lo  # the voltage rises with SOC (every model here); the other sign is searched alike
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            below = (g(mid) < 0.0) == rising
            lo = np.where(below, mid, lo)
            hi = np.where(below, hi, mid)
        return 0.5 * (lo + hi)

    def initial_sd(self, soc0_sd: float, state0_sd: float) -> np.ndarray:
        """SD of every state's initial value for a filter ``(n,)``: ``soc0_sd`` for the SOC, ``state0_sd`` for the
        others (a model with states of other kinds overrides this)."""
        sd = np.full(self.n_states, float(state0_sd))
        sd[0] = soc0_sd
        return sd

    def walk_var(self) -> np.ndarray:
        """Random-walk variance of every state per second ``(n,)`` the filters add to Q (0: none)."""
        return np.zeros(self.n_states)

    def f(self, x, i, dt, temp=None):
        return self.step(x, i, dt, temp)[0]

    def F(self, x, i, dt, temp=None):
        return self.step(x, i, dt, temp, jac=True)[1]

    def B(self, x, i, dt, temp=None):
        return self.step(x, i, dt, temp, jac=True)[2]

    def h(self, x, i, temp=None):
        return self.output(x, i, temp)[0]

    def H(self, x, i, temp=None):
        return self.output(x, i, temp, jac=True)[1]

    def D(self, x, i, temp=None):
        return self.output(x, i, temp, jac=True)[2]

    # ------------------------------------------------------------------ helpers for subclasses
    def p(self, name: str, z, temp=None):
        """Parameter ``name`` and its z-derivative at SOC ``z`` and cell temperature ``temp`` [°C]."""
        return self.params[name].value_and_deriv(z, temp)

    def params_at(self, names: tuple, z, deriv: bool = True, temp=None):
        """``(values (m, …), derivatives (m, …) or None)``: the parameters ``names`` at SOC ``z`` (and cell
        temperature ``temp``), stacked first.

        One call per filter step instead of one per parameter: the plain polynomials (the paper's 6th-degree fits)
        go through one Horner pass over an ``(m, …)`` array, bit-for-bit the values of :meth:`p`; other forms (and
        parameter batches, temperature tables) are evaluated one by one. ``deriv=False`` skips the derivatives (steps
        without Jacobians). The parameter axis comes first so that every inner loop runs over the contiguous batch.
        """
        plan = self._plans.get(names)
        if plan is None:
            plan = self._plans[names] = _ParamPlan([self.params[n] for n in names])
        return plan(np.asarray(z, dtype=float), deriv, temp)

    @staticmethod
    def _broadcast(x, *args):
        x = np.asarray(x, dtype=float)
        batch = x.shape[:-1]
        return x, [np.broadcast_to(np.asarray(a, dtype=float), batch) if a is not None else None for a in args]

    # ------------------------------------------------------------------ simulation
    def simulate(self, profile: Profile, soc0=None, x0=None, guards: GuardLog | None = None,
                 segments=None, soc_jumps=None) -> Simulation:
        """Open-loop simulation on a profile's current (and temperature): ``y_k = h(x_k, I_k)``, ``x_{k+1} = f(...)``.

        ``soc0`` defaults to the profile's reference SOC at the first sample, else the SOC read off the first
        voltage, else 1. Batched profiles simulate all runs in one pass.

        A record of several discharges (battery swaps, recharges: :mod:`socbench.segments`) is simulated segment by
        segment: ``segments=None`` finds them, ``False`` runs the record as one piece (the zero-order hold then
        carries the current across every gap), or pass a :class:`~socbench.segments.Segments`. Each segment after
        the first restarts from rest at the reference SOC of its first sample (else the SOC read off its first
        voltage); no current is integrated across a boundary. ``soc_jumps`` (optional, ``(T,)``): SOC added after the
        step into each sample, charge the current column does not carry (:meth:`open_loop`;
        :func:`socbench.identify.hppc.gap_soc_jumps`), none at a segment's first sample (it restarts).
        ``Simulation.domain`` counts the samples outside the model's domain (:func:`socbench.domain.domain_report`).
        """
        from ..domain import domain_report, guard_fractions
        from ..segments import REFERENCE, resolve, restart_soc

        i = profile.current_a
        segs = resolve(segments, profile, self.ocv, self.capacity_ah)
        if x0 is None:
            if soc0 is None:
                soc0 = restart_soc(profile, 0, self, REFERENCE)
            x0 = self.x0(soc0, i.shape[:-1])
        log = guards if guards is not None else GuardLog()
        temp = profile.temperature_c
        parts = []
        for s, (a, b) in enumerate(segs.spans()):
            xs = x0
            if s:  # a restart: from rest, at the SOC the segment starts from
                z = restart_soc(profile, a, self, REFERENCE)
                xs = self.x0(np.broadcast_to(z, np.broadcast_shapes(np.shape(z), np.shape(x0)[:-1])))
            jumps = None
            if soc_jumps is not None:
                jumps = np.array(soc_jumps[a:b], dtype=float)
                jumps[0] = 0.0
            parts.append(self.open_loop(xs, profile.time_s[a:b], i[..., a:b], None if temp is None else temp[..., a:b],
                                        jumps, guards=log))
        states = parts[0][0] if len(parts) == 1 else np.concatenate([p[0] for p in parts], axis=-2)
        volts = parts[0][1] if len(parts) == 1 else np.concatenate([p[1] for p in parts], axis=-1)
        log.samples += int(np.prod(volts.shape[:-1], dtype=int)) * profile.n
        domain = domain_report(self, states=states, temp=temp, voltage=volts, guards=log)
        domain["segments"] = segs.count
        return Simulation(profile.time_s, volts, states, self.state_names, log.fractions(), segs, domain,
                          guard_fractions(domain))

    def open_loop(self, x0, time_s, current_a, temp_c=None, soc_jumps=None, guards: GuardLog | None = None):
        """States ``(…, T, n)`` and voltage ``(…, T)``: ``y_k = h(x_k, I_k, T_k)``, ``x_{k+1} = f(x_k, I_k, dt_k, …)``.

        ``time_s`` is ``(T,)``; ``current_a``, ``temp_c`` are ``(…, T)`` and broadcast with ``x0 (…, n)``.
        ``soc_jumps[k]`` (optional, ``(T,)``) is added to the SOC *after* the step into sample ``k``: charge the
        current column does not carry (a gap in a record whose amp-hours a reference knows).

        Models whose other states follow a linear recurrence once the SOC path is known implement
        :meth:`_states_given_soc`: the whole record is then evaluated at once (the SOC path as a running sum, the
        recurrence by a prefix scan, :mod:`socbench.models.recurrence`), which equals the step loop to rounding.
        Every other model runs the step loop.
        """
        if np.size(time_s) < 2 or type(self)._states_given_soc is Model._states_given_soc:
            return self.open_loop_stepwise(x0, time_s, current_a, temp_c, soc_jumps, guards)
        x, i_t, temp_t, dt, jumps = self._record_time_first(x0, time_s, current_a, temp_c, soc_jumps)
        xs = np.empty(i_t.shape[:1] + x.shape)
        dz = soc_step(0.0, i_t[:-1], dt, self.capacity_ah, self.eta_charge)[0]
        xs[..., 0] = running_sum(x[..., 0], dz, jumps)  # B1 over the record: the loop's additions, in order
        self._states_given_soc(xs, x, i_t[:-1], dt, None if temp_t is None else temp_t[:-1], guards)
        return self._time_first_result(xs, i_t, temp_t, guards)

    def open_loop_stepwise(self, x0, time_s, current_a, temp_c=None, soc_jumps=None,
                           guards: GuardLog | None = None):
        """:meth:`open_loop` by the step loop, one ``output`` and one ``step`` call per sample (the reference the
        whole-record evaluation is tested against)."""
        x, i, temp, dts, T = self._record(x0, time_s, current_a, temp_c)
        states = np.empty(x.shape[:-1] + (T, self.n_states))
        volts = np.empty(x.shape[:-1] + (T,))
        for k in range(T):
            tk = None if temp is None else temp[..., k]
            states[..., k, :] = x
            volts[..., k] = self.output(x, i[..., k], tk, guards=guards)[0]
            if k + 1 < T:
                x = self.step(x, i[..., k], dts[k], tk, guards=guards)[0]
                if soc_jumps is not None and soc_jumps[k + 1] != 0.0:
                    x[..., 0] += soc_jumps[k + 1]
        return states, volts

    def _states_given_soc(self, xs, x0, i, dt, temp, guards):
        """Fill ``xs[..., 1:]`` (time first, ``(T, …, n)``) from the SOC path ``xs[..., 0]``, the initial state
        ``x0 (…, n)``, the step currents ``i (T − 1, …)``, steps ``dt (T − 1, 1, …)`` and cell temperatures ``temp
        (T − 1, …)`` or None. Not implemented: the step loop runs instead (see :meth:`open_loop`)."""
        raise NotImplementedError

    def _record(self, x0, time_s, current_a, temp_c):
        """``(x0, I, T_cell, dt, n_samples)`` broadcast to one batch shape (current and temperature ``(…, T)``)."""
        time_s = np.asarray(time_s, dtype=float)
        T = time_s.size
        i = np.asarray(current_a, dtype=float)
        x = np.asarray(x0, dtype=float)
        batch = np.broadcast_shapes(x.shape[:-1], i.shape[:-1],
                                    () if temp_c is None else np.shape(temp_c)[:-1])
        x = np.broadcast_to(x, batch + (self.n_states,)).copy()
        i = np.broadcast_to(i, batch + (T,))
        temp = None if temp_c is None else np.broadcast_to(np.asarray(temp_c, dtype=float), batch + (T,))
        return x, i, temp, np.diff(time_s), T


    def _record_time_first(self, x0, time_s, current_a, temp_c, soc_jumps):
        """:meth:`_record` with time on the *first* axis, the layout of the whole-record evaluation (SOC functions
        broadcast a parameter batch against the trailing axes): ``(x0 (…, n), I (T, …), T_cell (T, …) or None,
        dt (T − 1, 1, …), SOC jumps (T, 1, …) or None)``."""
        x, i, temp, dts, T = self._record(x0, time_s, current_a, temp_c)
        ones = (1,) * (x.ndim - 1)
        temp_t = None if temp is None else np.moveaxis(temp, -1, 0)
        jumps = None if soc_jumps is None else np.reshape(soc_jumps, (T,) + ones)
        return x, np.moveaxis(i, -1, 0), temp_t, dts.reshape((T - 1,) + ones), jumps

    def _time_first_result(self, xs, i_t, temp_t, guards):
        """``(states (…, T, n), voltage (…, T))`` of time-first states ``xs (T, …, n)``: one ``output`` call."""
        y = self.output(xs, i_t, temp_t, guards=guards)[0]
        return np.moveaxis(xs, 0, -2), np.moveaxis(y, 0, -1)

class _ParamPlan:
    """Stacked evaluation of SOC functions: polynomials of one degree (and one parameter-batch shape) share one
    Horner pass; other forms are evaluated one by one.

    Horner for the value and the derivative together on ``z_p = clip(z, 0, 1)``, derivative 0 outside [0, 1]: the
    same floating-point operations, in the same order, as :meth:`~socbench.models.params.Polynomial.value_and_deriv`
    (done in place: on particle clouds the temporaries are large and allocating them costs more than the arithmetic).
    """

    def __init__(self, funcs):
        self.funcs = funcs
        self.m = len(funcs)
        groups: dict = {}
        for k, f in enumerate(funcs):
            if isinstance(f, Polynomial):
                batch = f.coeffs.shape[:-1] if f.batched else ()
                groups.setdefault((len(f._columns if f.batched else f.coeffs), batch), []).append(k)
        # (member indices, batch shape P, coefficients (degree + 1, members, *P))
        self.groups = [(ks, batch, np.stack([np.moveaxis(np.asarray(funcs[k].coeffs, dtype=float), -1, 0)
                                             for k in ks], axis=1)) for (_, batch), ks in groups.items()]
        self.other = [k for k in range(self.m) if not any(k in g[0] for g in self.groups)]

    @staticmethod
    def _horner(z, batch, coef, deriv):
        shape = np.broadcast_shapes(z.shape, batch)
        c = coef.reshape(coef.shape[:2] + (1,) * (len(shape) - len(batch)) + batch)  # c[j] broadcasts to (m, *shape)
        zp = np.clip(z, 0.0, 1.0)
        v = np.empty(coef.shape[1:2] + shape)
        v[...] = c[0]
        if not deriv:
            for cj in c[1:]:
                v *= zp
                v += cj
            return v, None
        d = np.zeros(v.shape)
        for cj in c[1:]:
            d *= zp
            d += v
            v *= zp
            v += cj
        outside = (z < 0.0) | (z > 1.0)
        if outside.any():
            d[:, np.broadcast_to(outside, shape)] = 0.0
        return v, d

    def __call__(self, z, deriv: bool, temp=None):
        if len(self.groups) == 1 and not self.other:
            _, batch, coef = self.groups[0]
            return self._horner(z, batch, coef, deriv)
        parts = [None] * self.m
        for ks, batch, coef in self.groups:
            v, d = self._horner(z, batch, coef, deriv)
            for j, k in enumerate(ks):
                parts[k] = (v[j], None if d is None else d[j])
        for k in self.other:
            parts[k] = self.funcs[k].value_and_deriv(z, temp)
        shape = np.broadcast_shapes(*(p[0].shape for p in parts))
        out_v = np.empty((self.m,) + shape)
        out_d = np.empty((self.m,) + shape) if deriv else None
        for k, (v, d) in enumerate(parts):
            out_v[k] = v
            if deriv:
                out_d[k] = d
        return out_v, out_d
