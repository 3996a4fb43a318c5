"""Effects the 14 ECMs lack (ECM_SPEC §9), as augmentations of any model: ``augment(model, [effects]) -> Model``.

An :class:`Effect` adds states, parameters (each with a physically bounded range, :meth:`Effect.bounds`) and terms,
with their Jacobian blocks. :class:`AugmentedModel` is a real :class:`~socbench.models.base.Model`: every estimator and
the generic Jacobian / ZOH / batch tests run it unchanged. State ``x = [base states, effect 1 states, ...]``.

How the pieces compose in one step (``i`` the measured current, ``T`` the measured temperature)::

    i_e = i − b                                         current_bias: base model and effects see the true current
    x_b⁺ = f_base(x_b, i_e)                              the base model's own step (its F_b, B_b = ∂f_b/∂I)
    z⁺  = z + G·(z_b⁺ − z) − Σ leak                      capacity (G ∋ c), coulombic_efficiency (G ∋ η_c on charge),
                                                         self_discharge (leak)
    e⁺  = f_e(e, z, i_e)                                 the effects' own states (hysteresis h, s; extra RC U_x; c; b)
    y   = U(z) + K·(h_base(x_b, i_e) − U(z)) + Σ terms(e, z, i_e, T)
    K   = Π over-potential factors = k(T)·(1 + g)           temperature's Arrhenius k(T) (its entropic ΔS·(T − T_ref)
                                                         is one of the terms), capacity's resistance growth g

and for the bias state (``b`` enters only through ``i_e``): ``∂x⁺/∂b = −∂x⁺/∂i_e``, ``∂y/∂b = −∂y/∂i_e``, which needs
the base model's ``B = ∂f/∂I`` and ``D = ∂h/∂I``. The over-potential factors multiply, so they compose in any order:
``H = K·H_base + (1 − K)·U'(z)·e_z``, ``D = K·D_base``.

Effects (ECM_SPEC §9 numbering in brackets):

* :class:`Temperature` [2] — Arrhenius scaling of the over-potential plus an entropic OCV term.
* :class:`Hysteresis` [1] — Plett's one-state dynamic + instantaneous hysteresis (states ``h``, ``s``).
* :class:`Capacity` [3] — capacity fade / wrong declared capacity: a random-walk state ``cap`` = Q_model/Q_true, and
  the resistance growth ``g`` of ageing that comes with a fade (the over-potential scaled by ``1 + g``).
* :class:`CurrentBias` [4] — current-sensor offset ``b`` as a random-walk state.
* :class:`ExtraRC` [7] — a further RC branch ``U_x`` (diffusion), built with ``blocks.rc_coefficients``.
* :class:`ButlerVolmer` [6] — asinh charge-transfer over-potential (no state).
* :class:`CoulombicEfficiency` [5] — η_c < 1 on charge.
* :class:`SelfDischarge` [8] — a leak ``ż = −r_sd·U_oc(z)/U_oc(1)/3600``.
* :class:`ModelError` — not a physical effect: the model's own voltage error as four coloured (Gauss–Markov)
  states (slow, fast, resistive, and the slow scale at a mid period), for the filters' noise recipe
  (:mod:`socbench.estimators.model_error`).
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np

from ..errors import ConfigError
from .base import T_REF_C, Model
from .blocks import rc_coefficients, soc_step
from .recurrence import affine_scan, hysteresis_path, running_sum

#: gas constant [J/(mol K)] and Faraday constant [C/mol]
R_GAS = 8.314462618
FARADAY = 96485.33212
KELVIN = 273.15


def n_cells(model) -> int:
    """Cells in series, from the OCV level at full charge (≈ 3.4–4.2 V per cell): scales the voltage bounds."""
    return max(1, int(round(float(model.ocv(1.0)) / 4.0)))


def resistance_scale(model) -> float:
    """A generous upper bound for an added resistance [Ω]: 0.5 Ω·Ah per cell divided by the capacity."""
    return 0.5 * n_cells(model) / model.capacity_ah


class Effect:
    """An augmentation: states, bounded parameters, and hooks that the :class:`AugmentedModel` composes.

    Subclasses set ``name``, ``state_names``, ``param_names``, ``defaults`` and implement :meth:`bounds` and the hooks
    they need. Parameters are fixed at construction (``Effect(**values)``); :meth:`with_values` returns a copy.
    Every hook is batched over the leading axes; ``e`` is the effect's own slice of the state, shape ``(..., ne)``.
    """

    name: ClassVar[str] = ""
    state_names: ClassVar[tuple] = ()
    discrete_states: ClassVar[tuple] = ()
    param_names: ClassVar[tuple] = ()
    defaults: ClassVar[dict] = {}
    #: settings that are not fitted (e.g. the reference temperature)
    settings: ClassVar[dict] = {}
    #: for a filter, per state: the SD of its initial value (None: the estimator's default for a dynamic state) and
    #: of its random walk per √hour (a constant's is 0: capacity and a sensor offset do not move within a record)
    state_sd: ClassVar[tuple] = ()
    walk_sd: ClassVar[tuple] = ()
    #: state -> the parameter that is its initial value (a fitted initial value's spread is its filter uncertainty)
    initial_params: ClassVar[dict] = {}
    #: the parameters a fit together with the base model estimates (:func:`socbench.identify.fit.fit_model`'s
    #: ``effects``): those no base parameter can stand in for (None: every parameter)
    joint_params: ClassVar[tuple | None] = None

    def __init__(self, *, initial_sd=None, **values):
        unknown = sorted(set(values) - set(self.param_names) - set(self.settings))
        if unknown:
            raise ConfigError(f"effect '{self.name}' has no parameter '{unknown[0]}' (have {list(self.param_names)})")
        # a value may carry a leading batch axis (one parameter variant per run): the fits simulate variants together
        self.values = {k: np.asarray(v, dtype=float) for k, v in {**self.defaults, **self.settings, **values}.items()}
        if initial_sd is not None and len(initial_sd) != self.n_states:
            raise ConfigError(f"effect '{self.name}': initial_sd needs one entry per state {self.state_names}")
        self._initial_sd = None if initial_sd is None else tuple(initial_sd)

    def __getitem__(self, key):
        return self.values[key]

    def with_values(self, **values) -> Effect:
        return type(self)(initial_sd=self._initial_sd, **{**self.values, **values})

    def initial_sd(self, base) -> tuple:
        """SD of each state's initial value for a filter (None: the estimator's default): the one given at
        construction (e.g. the spread of a fitted initial value), else the class's declaration."""
        return self._initial_sd if self._initial_sd is not None else self.state_sd

    def __repr__(self) -> str:
        vals = ", ".join(f"{k}={np.array2string(v, precision=4)}" for k, v in self.values.items())
        return f"{type(self).__name__}({vals})"

    @property
    def n_states(self) -> int:
        return len(self.state_names)

    def bounds(self, model) -> dict:
        """``{param: (low, high)}``: the physically admissible range on base ``model`` (used by every fit)."""
        raise NotImplementedError

    def initial(self) -> np.ndarray:
        """Initial values of the effect's states."""
        return np.zeros(self.n_states)

    # ------------------------------------------------------------------ hooks (defaults: no contribution)
    def current_offset(self, e):
        """Offset subtracted from the measured current (current_bias), or None."""
        return None

    def soc_gain(self, e, i, base):
        """``(g, ∂g/∂e)``: factor on the base SOC increment, or None."""
        return None

    def soc_leak(self, z, e, dt, base):
        """``(Δz, ∂Δz/∂z)``: SOC removed per step in addition to the current, or None."""
        return None

    def advance(self, e, z, i, dt, temp, base, jac):
        """``(e⁺, ∂e⁺/∂e (…, ne, ne), ∂e⁺/∂z (…, ne), ∂e⁺/∂I (…, ne))`` of the effect's states."""
        return e, None, None, None

    def record_states(self, e0, i, dt, base):
        """The effect's states over a whole record at once, time first ``(T, …, ne)``, from ``e0 (…, ne)``, the
        (effective) step currents ``i (T − 1, …)`` and steps ``dt (T − 1, 1, …)``: what :meth:`advance` gives step by
        step, for effects whose states do not depend on the SOC. Not implemented: the augmented model runs the step
        loop (see :meth:`AugmentedModel.open_loop`)."""
        raise NotImplementedError

    def rate(self, e, z, i, temp, base):
        """Continuous-time ``ė`` (0 for discrete states); SOC-dependent quantities frozen at ``z``."""
        return np.zeros_like(e)

    def soc_rate(self, z_params, e, base):
        """Continuous-time leak ``ż`` (self_discharge), or None."""
        return None

    def overpotential_factor(self, temp, shape):
        """The factor ``K_e`` on the base model's over-potential ``h_base − U(z)`` (temperature, resistance growth),
        broadcast to ``shape``, or None (no factor). The model scales by the product of every effect's."""
        return None

    def output_term(self, e, z, i, temp, base, jac):
        """``(Δy, ∂Δy/∂e (…, ne), ∂Δy/∂z, ∂Δy/∂I)`` added to the output, or None."""
        return None

    #: ``kernel_values(base) -> tuple``: the numbers the effect's compiled hooks read (socbench.kernels.evaluate),
    #: each a scalar or a ``(V,)`` parameter batch; None: the effect has no compiled form (numpy engine only)
    kernel_values = None


def _constant_states(self, e0, i, dt, base):
    """A random-walk state without process noise stays at its initial value over the record (open loop)."""
    return np.broadcast_to(e0, (i.shape[0] + 1,) + np.shape(e0))


def _temp_k(temp, t_ref_c, shape):
    t = np.full(shape, t_ref_c) if temp is None else np.broadcast_to(np.asarray(temp, dtype=float), shape)
    return t + KELVIN


# ======================================================================================================= effects
class Temperature(Effect):
    """Arrhenius scaling of the over-potential and an entropic OCV term (ECM_SPEC §9.2).

    ``y = U(z) + ΔS·(T − T_ref) − k(T)·(U(z) − h_base(x, I))``,  ``k(T) = exp[(E_a/R_g)(1/T − 1/T_ref)]`` (kelvin).

    This is **exact for a constant temperature** when every resistance of the base model scales with ``k(T)`` and every
    time constant stays fixed (each C scales with 1/k): the RC states then scale with ``k`` too, so the whole
    over-potential ``U − h_base`` does. With a time-varying ``T`` it is the quasi-static approximation (the RC
    states are not re-weighted by the temperature history). ``T`` is the profile's measured temperature; no temperature
    input means ``T = T_ref`` (``k = 1``). Parameters: ``Ea`` [J/mol], ``dUdT`` [V/K] (pack: cells × per-cell),
    setting ``t_ref`` [°C] (the temperature the base model was fitted at).

    Jacobians: ``H = (1 − k)U'(z)·e_z + k·H_base``, ``D = k·D_base``. ``k`` is the effect's over-potential factor
    (:meth:`overpotential_factor`, composed with any other by :class:`AugmentedModel`); the entropic term is its
    output term.
    """

    name = "temperature"
    param_names = ("Ea", "dUdT")
    defaults = {"Ea": 20e3, "dUdT": 0.0}
    settings = {"t_ref": T_REF_C}

    def bounds(self, model):
        n = n_cells(model)
        return {"Ea": (0.0, 100e3), "dUdT": (-1e-3 * n, 1e-3 * n)}

    def kernel_values(self, base):
        return (self["Ea"], self["dUdT"], self["t_ref"])

    def factor(self, temp, shape):
        tk = _temp_k(temp, self["t_ref"], shape)
        return np.exp(self["Ea"] / R_GAS * (1.0 / tk - 1.0 / (self["t_ref"] + KELVIN))), tk

    def overpotential_factor(self, temp, shape):
        return self.factor(temp, shape)[0]

    def output_term(self, e, z, i, temp, base, jac):
        dy = self["dUdT"] * (_temp_k(temp, self["t_ref"], np.shape(z)) - KELVIN - self["t_ref"])
        if not jac:
            return dy, None, None, None
        return dy, np.zeros(dy.shape + (0,)), np.zeros(dy.shape), np.zeros(dy.shape)


class Hysteresis(Effect):
    """Plett's one-state dynamic plus instantaneous hysteresis (ESC, ECM_SPEC §9.1).

    ``A_h = exp(−|η(I)·I·γ·dt/(3600 Q)|)``, ``h⁺ = A_h h − (1 − A_h) sgn(I)``; ``s_k = sgn(I_k)`` if ``|I_k| > Q/100``
    else ``s_{k−1}``; ``y += M h_k + M0 s_k``. State ``s`` stores ``s_{k−1}`` (discrete: no derivative, no ``ṡ``).
    Continuous form: ``ḣ = −γ|η I|/(3600 Q)·(h + sgn I)`` (exact under ZOH).
    Jacobians: ``∂h⁺/∂h = A_h``, ``∂h⁺/∂I = ∂A_h/∂I·(h + sgn I)`` with ``∂A_h/∂I = −A_h γ η dt sgn(I)/(3600 Q)``;
    ``∂y/∂h = M``, ``∂y/∂s = M0`` where the current is below Q/100 (else 0). Parameter ``h0`` is the initial ``h``
    (+1: the cell comes from a charge).

    The base model's OCV curve was measured on some branch, so the term is taken relative to it:
    ``y += M (h − h_ref) + M0 (s − s_ref)`` with the setting ``h_ref`` and ``s_ref = −h_ref``: −1 for rest points taken
    after discharge steps (HPPC: ``h = −1``, ``s = +1`` there), 0 for the mean of a slow test's two branches.
    Plett's form is ``h_ref = 0``.
    """

    name = "hysteresis"
    state_names = ("h", "s")
    discrete_states = ("s",)
    param_names = ("M", "M0", "gamma", "h0")
    defaults = {"M": 0.01, "M0": 0.0, "gamma": 50.0, "h0": 0.0}
    settings = {"h_ref": 0.0}
    #: h ∈ [−1, 1] starts at the fitted h0; the sign memory s is a bookkeeping state (no uncertainty of its own)
    state_sd = (0.1, 1e-6)
    walk_sd = (0.0, 0.0)
    initial_params = {"h": "h0"}

    def bounds(self, model):
        n = n_cells(model)
        return {"M": (0.0, 0.1 * n), "M0": (-0.05 * n, 0.05 * n), "gamma": (1.0, 500.0), "h0": (-1.0, 1.0)}

    def initial(self):
        return np.stack([self["h0"], np.zeros_like(self["h0"])], axis=-1)

    def kernel_values(self, base):
        return (self["M"], self["M0"], self["gamma"], self["h_ref"])

    def _decay(self, i, dt, base):
        eta = np.where(i >= 0.0, 1.0, base.eta_charge)
        c = self["gamma"] * eta / (3600.0 * base.capacity_ah)
        return np.exp(-np.abs(i * c * dt)), c

    def advance(self, e, z, i, dt, temp, base, jac):
        h, s = e[..., 0], e[..., 1]
        a, c = self._decay(i, dt, base)
        sg = np.sign(i)
        moving = np.abs(i) > base.capacity_ah / 100.0
        en = np.stack([a * h - (1.0 - a) * sg, np.where(moving, sg, s)], axis=-1)
        if not jac:
            return en, None, None, None
        Fe = np.zeros(e.shape + (2,))
        Fe[..., 0, 0] = a
        Fe[..., 1, 1] = np.where(moving, 0.0, 1.0)
        Be = np.zeros(e.shape)
        Be[..., 0] = -a * c * dt * sg * (h + sg)
        return en, Fe, np.zeros(e.shape), Be

    def record_states(self, e0, i, dt, base):
        """Both states over the record by :func:`~socbench.models.recurrence.hysteresis_path`."""
        moving = np.abs(i) > base.capacity_ah / 100.0
        return np.stack(hysteresis_path(self._decay(i, dt, base)[0], i, moving, e0[..., 0], e0[..., 1]), axis=-1)

    def rate(self, e, z, i, temp, base):
        eta = np.where(i >= 0.0, 1.0, base.eta_charge)
        r = np.zeros_like(e)
        r[..., 0] = -self["gamma"] * np.abs(eta * i) / (3600.0 * base.capacity_ah) * (e[..., 0] + np.sign(i))
        return r

    def output_term(self, e, z, i, temp, base, jac):
        moving = np.abs(i) > base.capacity_ah / 100.0
        s = np.where(moving, np.sign(i), e[..., 1])
        dy = self["M"] * (e[..., 0] - self["h_ref"]) + self["M0"] * (s + self["h_ref"])
        if not jac:
            return dy, None, None, None
        He = np.stack([np.broadcast_to(self["M"], dy.shape), np.where(moving, 0.0, self["M0"])], axis=-1)
        return dy, He, np.zeros(dy.shape), np.zeros(dy.shape)


class Capacity(Effect):
    """Capacity fade or a wrong declared capacity (ECM_SPEC §9.3): state ``cap = Q_model/Q_true`` (random walk), and
    the resistance growth that comes with ageing.

    ``z⁺ = z + cap·(z_base⁺ − z)`` — the base SOC increment (computed with the declared Q) is scaled.
    ``∂z⁺/∂cap = z_base⁺ − z``; ``∂z⁺/∂I = cap·B_base[z]``; ``cap⁺ = cap``. Parameter ``cap0`` is its initial value.

    Ageing (SEI growth) fades the capacity and raises the resistances together. With every resistance grown by
    ``1 + g`` and every capacitance shrunk by it (time constants unchanged), every RC state grows by ``1 + g`` too, so
    the whole over-potential does — exactly, the mechanism of :class:`Temperature`'s ``k(T)``:
    ``y = U(z) + (1 + g)·(h_base(x, I) − U(z))``, the over-potential factor ``1 + g`` (:meth:`overpotential_factor`).
    Jacobians ``H = (1 + g)·H_base − g·U'(z)·e_z``, ``D = (1 + g)·D_base``. Parameter ``r_growth = g ≥ 0`` (default 0:
    a fade alone, or a wrong declared capacity).
    """

    name = "capacity"
    state_names = ("cap",)
    param_names = ("cap0", "r_growth")
    defaults = {"cap0": 1.0, "r_growth": 0.0}
    state_sd = (0.01,)
    walk_sd = (0.0,)
    initial_params = {"cap": "cap0"}
    #: a fit of the base model's own parameters scales every resistance itself: the growth is not told from it
    joint_params = ("cap0",)

    def bounds(self, model):
        # up to doubled resistances: end of life (20 % fade) comes with some tens of percent growth
        return {"cap0": (0.6, 1.6), "r_growth": (0.0, 1.0)}

    def initial(self):
        return self["cap0"][..., None]

    def kernel_values(self, base):
        return (self["r_growth"],)

    def overpotential_factor(self, temp, shape):
        g = self["r_growth"]
        # a fade alone (g = 0 in every variant) leaves the output untouched, bit for bit
        return None if not np.any(g) else np.broadcast_to(1.0 + g, shape)

    def soc_gain(self, e, i, base):
        return e[..., 0], np.ones(e.shape)

    def advance(self, e, z, i, dt, temp, base, jac):
        if not jac:
            return e, None, None, None
        return e, np.ones(e.shape + (1,)), np.zeros(e.shape), np.zeros(e.shape)

    record_states = _constant_states


class CurrentBias(Effect):
    """Current-sensor offset (ECM_SPEC §9.4): ``I_meas = I + b``, ``b`` a random-walk state (``b⁺ = b``).

    The base model and every other effect run on ``I − b``; so ``∂x⁺/∂b = −∂x⁺/∂I`` (the base model's ``B``, e.g.
    ``∂z⁺/∂b = ηκ``) and ``∂y/∂b = −∂y/∂I`` (e.g. ``+R0``; the RC paths act through their states). Parameter ``b0``.
    """

    name = "current_bias"
    state_names = ("b",)
    param_names = ("b0",)
    defaults = {"b0": 0.0}
    walk_sd = (0.0,)
    initial_params = {"b": "b0"}

    def initial_sd(self, base):
        """0.1 % of 1C unless given (a fitted offset is known to about a sensor's resolution)."""
        return self._initial_sd if self._initial_sd is not None else (1e-3 * base.capacity_ah,)

    def bounds(self, model):
        return {"b0": (-0.05 * model.capacity_ah, 0.05 * model.capacity_ah)}

    def initial(self):
        return self["b0"][..., None]

    def kernel_values(self, base):
        return ()

    def current_offset(self, e):
        return e[..., 0]

    def advance(self, e, z, i, dt, temp, base, jac):
        if not jac:
            return e, None, None, None
        return e, np.ones(e.shape + (1,)), np.zeros(e.shape), np.zeros(e.shape)

    record_states = _constant_states


class ResistanceOffset(Effect):
    """An offset on the ohmic resistance, ``ΔR0`` (a random-walk state, ``ΔR0⁺ = ΔR0``): ``y −= ΔR0·I``.

    Not one of the missing physical effects (the base model already has its R0), so it is not in :data:`EFFECTS` and
    the diagnosis never proposes it: it is the state through which a joint estimator tracks resistance growth
    (``estimators.dual``). ``∂y/∂ΔR0 = −I``, ``∂y/∂I = −ΔR0``. Parameter ``dR0`` is its initial value [Ω].
    """

    name = "r0_offset"
    state_names = ("dR0",)
    param_names = ("dR0",)
    defaults = {"dR0": 0.0}

    def bounds(self, model):
        return {"dR0": (-resistance_scale(model), resistance_scale(model))}

    def initial(self):
        return self["dR0"][..., None]

    def kernel_values(self, base):
        return ()

    def advance(self, e, z, i, dt, temp, base, jac):
        if not jac:
            return e, None, None, None
        return e, np.ones(e.shape + (1,)), np.zeros(e.shape), np.zeros(e.shape)

    record_states = _constant_states

    def output_term(self, e, z, i, temp, base, jac):
        dy = -e[..., 0] * i
        if not jac:
            return dy, None, None, None
        return dy, -np.broadcast_to(i, dy.shape)[..., None], np.zeros(dy.shape), -e[..., 0] * np.ones(dy.shape)


class ExtraRC(Effect):
    """A further RC branch (diffusion, ECM_SPEC §9.7): ``U_x⁺ = a U_x + b I``, ``y −= U_x`` (block B2).

    ``a = e^{−dt/τ}``, ``b = R(1 − a)`` from :func:`~socbench.models.blocks.rc_coefficients` with ``C = τ/R``;
    ``F = a``, ``B = b``, ``H = −1``. Parameters ``R`` [Ω] and ``log10_tau`` (τ in s), constant in SOC.
    """

    name = "extra_rc"
    state_names = ("Ux",)
    param_names = ("R", "log10_tau")
    defaults = {"R": 1e-3, "log10_tau": 2.5}
    state_sd = (None,)
    walk_sd = (0.0,)

    def bounds(self, model):
        return {"R": (1e-6, resistance_scale(model)), "log10_tau": (0.5, 4.0)}

    def _rc(self):
        """``(R, C)`` of the branch: ``R ≥ 1e-9`` Ω, ``C = τ/R``."""
        R = np.maximum(self["R"], 1e-9)
        return R, 10.0 ** self["log10_tau"] / R

    def _coef(self, dt, base):
        R, C = self._rc()
        a, b, _, _ = rc_coefficients(R, 0.0, C, 0.0, dt, base.mode, name="RCx")
        return a, b

    def kernel_values(self, base):
        return self._rc()

    def advance(self, e, z, i, dt, temp, base, jac):
        a, b = self._coef(dt, base)
        en = (a * e[..., 0] + b * i)[..., None]
        if not jac:
            return en, None, None, None
        return en, a[..., None, None], np.zeros(e.shape), b[..., None]

    def record_states(self, e0, i, dt, base):
        """``U_x⁺ = a U_x + b I`` over the record by :func:`~socbench.models.recurrence.affine_scan`."""
        a, b = self._coef(dt, base)
        return affine_scan(a, b * i, e0[..., 0])[..., None]

    def rate(self, e, z, i, temp, base):
        tau = 10.0 ** self["log10_tau"]
        return ((-e[..., 0] + self["R"] * i) / tau)[..., None]

    def output_term(self, e, z, i, temp, base, jac):
        dy = -e[..., 0]
        if not jac:
            return dy, None, None, None
        return dy, -np.ones(e.shape), np.zeros(dy.shape), np.zeros(dy.shape)


class ButlerVolmer(Effect):
    """Current-dependent charge-transfer over-potential (ECM_SPEC §9.6), no state.

    ``y += −U_ct(I, T) + ΔR·I``, ``U_ct = N_s·(2 R_g T/F)·asinh(I/(2 I_0(T)))`` (symmetric α = 0.5, ``N_s`` cells in
    series, ``T`` the measured temperature in kelvin, else 25 °C), with the exchange current following Arrhenius::

        I_0(T) = I0 · exp[−(E_a/R_g)(1/T − 1/T_ref)]

    (``E_a = 0``, the default: one ``I0`` at every temperature). ``ΔR`` hands back the part of the base model's linear
    ``R0·I`` that the asinh term now carries (``y = … − R_Ω I − U_ct``).
    ``D = −N_s(2R_gT/F)/(2 I_0(T) √(1 + (I/2I_0(T))²)) + ΔR``; no state and no SOC dependence (``H`` gets nothing).
    Parameters ``I0`` [A] (at ``t_ref``) and ``dR`` [Ω]; settings ``Ea`` [J/mol] and ``t_ref`` [°C]: not fitted by the
    generic effect fits (a single-temperature record cannot tell ``E_a``), set by the temperature-aware fit
    (:func:`socbench.identify.temperature.fit_temperatures` with ``charge_transfer=True``).
    """

    name = "butler_volmer"
    param_names = ("I0", "dR")
    defaults = {"I0": 1.0, "dR": 0.0}
    settings = {"Ea": 0.0, "t_ref": T_REF_C}
    #: fitted with a base model, ΔR is the base's R0 over again (both multiply I): only I0
    joint_params = ("I0",)

    def bounds(self, model):
        q = model.capacity_ah
        return {"I0": (0.01 * q, 10.0 * q), "dR": (-resistance_scale(model), resistance_scale(model))}

    def kernel_values(self, base):
        return (self["I0"], self["dR"], float(n_cells(base)), self["Ea"], self["t_ref"])

    def exchange_current(self, tk):
        """``I_0(T)`` [A] at the cell temperature ``tk`` [K] (the Arrhenius law of the class docstring)."""
        return self["I0"] * np.exp(-self["Ea"] / R_GAS * (1.0 / tk - 1.0 / (self["t_ref"] + KELVIN)))

    def output_term(self, e, z, i, temp, base, jac):
        tk = _temp_k(temp, T_REF_C, np.shape(i))
        g = n_cells(base) * 2.0 * R_GAS * tk / FARADAY
        i0 = self.exchange_current(tk)
        x = i / (2.0 * i0)
        dy = -g * np.arcsinh(x) + self["dR"] * i
        if not jac:
            return dy, None, None, None
        return dy, np.zeros(e.shape), np.zeros(dy.shape), -g / (2.0 * i0 * np.sqrt(1.0 + x * x)) + self["dR"]


class CoulombicEfficiency(Effect):
    """Coulombic efficiency on charge (ECM_SPEC §9.5): the base SOC increment is scaled by ``η_c`` when ``I < 0``.

    ``z⁺ = z + η(I)·(z_base⁺ − z)``, ``η = η_c`` for ``I < 0`` else 1 (on top of the base model's own ``eta_charge``).
    Parameter ``eta_c`` ∈ [0.9, 1].
    """

    name = "coulombic_efficiency"
    param_names = ("eta_c",)
    defaults = {"eta_c": 1.0}

    def bounds(self, model):
        return {"eta_c": (0.9, 1.0)}

    def soc_gain(self, e, i, base):
        return np.where(i < 0.0, self["eta_c"], 1.0), np.zeros(e.shape)

    def kernel_values(self, base):
        return (self["eta_c"],)


class SelfDischarge(Effect):
    """Self-discharge through a leak (ECM_SPEC §9.8): ``ż = −r_sd·U_oc(z)/U_oc(1)/3600`` (per hour at full charge).

    This is the spec's ``U_oc(z)/(3600 Q R_sd)`` with ``r_sd = U_oc(1)/(Q R_sd)``; ``U_oc`` is the curve at the
    reference temperature (the temperature of a temperature-aware curve is ignored here). With ``U_oc`` frozen at
    ``z_k`` over the step (as every SOC-dependent quantity): ``Δz = −r_sd·U(z_k)·dt/(3600 U(1))``,
    ``∂Δz/∂z = −r_sd U'(z) dt/(3600 U(1))``.
    Parameter ``rate`` [1/h], at most 5 %/h.
    """

    name = "self_discharge"
    param_names = ("rate",)
    defaults = {"rate": 0.0}

    def bounds(self, model):
        return {"rate": (0.0, 0.05)}

    def _c(self, base):
        return self["rate"] / (3600.0 * float(base.ocv(1.0)))

    def kernel_values(self, base):
        return (self._c(base),)

    def soc_leak(self, z, e, dt, base):
        u, du = base.ocv.value_and_slope(z)
        c = self._c(base) * dt
        return c * u, c * du

    def soc_rate(self, z_params, e, base):
        return -self._c(base) * base.ocv(z_params)


class ModelError(Effect):
    """The model's voltage error as four coloured-noise states: Gauss–Markov processes of unit variance (slow
    additive, fast additive, resistive, and the slow error's scale again at a shorter time), each scaled by its
    standard deviation at the SOC and cell temperature.

    For each component ``c``: ``ε_c⁺ = φ_c ε_c + w_c``, ``φ_c = e^{−dt/τ_c}``, ``w_c ~ N(0, 1 − φ_c²)`` (so
    ``Var ε_c = 1`` in steady state), and::

        y += s_slow(z, T)·(ε_slow + ε_mid) + s_fast(z, T)·ε_fast − s_r(z, T)·ε_r·I

    ``ε_mid`` (``τ_mid``, :attr:`socbench.estimators.model_error.ModelErrorStats.tau_mid_s`) says that an error of
    the slow part's size may also come and go within minutes: the slow part's integral time is set by its most
    persistent component, and a filter told only that would read a slow error that changes faster as SOC.

    ``s_c(z, T)`` bilinear on a grid: piecewise linear in SOC over ``soc`` and in temperature over ``temps`` (both
    held outside, the rule of every temperature table); a model's error is largest near the ends of the SOC range
    (the knee, the hysteresis left by a charge), and the scale says so. ``s_r`` is a resistance [Ω]: the part of the
    error that scales with the current (a resistance the model has wrong), which must not be read as SOC information
    wherever a parameter varies with SOC. Jacobians: ``∂ε_c⁺/∂ε_c = φ_c``; ``∂y/∂ε_slow = ∂y/∂ε_mid = s_slow``,
    ``∂y/∂ε_fast = s_fast``, ``∂y/∂ε_r = −s_r I``, ``∂y/∂z += s_slow' (ε_slow + ε_mid) + s_fast' ε_fast − s_r' ε_r I``,
    ``∂y/∂I += −s_r ε_r``.

    The process noise ``w`` is not part of the effect (a model is deterministic): a filter gets it through its
    covariance ``Q`` as these states' walk variances :meth:`walk_var` (``(1 − φ_c(dt₀)²)·dt/dt₀``, first order in
    dt). In open loop (no noise) ε stays at its initial value 0. Settings (not fitted): ``temps`` [°C], ``soc``,
    ``sd_slow``, ``sd_fast`` [V], ``sd_r`` [Ω] (each ``(len(temps), len(soc))``), ``tau_slow``, ``tau_fast``,
    ``tau_r``, ``tau_mid`` [s]. Estimated from residuals by :func:`socbench.estimators.model_error.estimate`.
    """

    name = "model_error"
    state_names = ("eps_slow", "eps_fast", "eps_r", "eps_mid")
    #: a record may start anywhere: the error starts at its stationary spread; its walk is not declared here (it
    #: depends on the step: :meth:`walk_var`, which the noise recipe puts in ``SensorNoise.walk_sd``)
    state_sd = (1.0, 1.0, 1.0, 1.0)
    settings = {"temps": (25.0,), "soc": (0.0, 1.0), "sd_slow": ((0.01, 0.01),), "sd_fast": ((0.0, 0.0),),
                "sd_r": ((0.0, 0.0),), "tau_slow": 600.0, "tau_fast": 5.0, "tau_r": 600.0, "tau_mid": 80.0}
    KEYS = ("sd_slow", "sd_fast", "sd_r")

    def bounds(self, model):
        return {}

    def kernel_values(self, base):
        """``τ_slow, τ_fast, τ_r, τ_mid, K_T, K_z``, the temperatures, the SOC grid, then the three scale grids
        (row-major ``(K_T, K_z)``; ε_mid reads the slow grid) — the layout
        socbench.kernels.evaluate.model_error_scale reads."""
        temps = np.atleast_1d(np.asarray(self["temps"], dtype=float))
        soc = np.atleast_1d(np.asarray(self["soc"], dtype=float))
        grids = [np.asarray(self[k], dtype=float) for k in self.KEYS]
        if temps.ndim != 1 or soc.ndim != 1 or any(g.size != temps.size * soc.size for g in grids):
            return None  # a batch of settings: no compiled form (the lowering says so)
        return (*self.taus, float(temps.size), float(soc.size), *temps, *soc, *(v for g in grids for v in g.ravel()))

    @property
    def taus(self) -> np.ndarray:
        return np.array([float(self[k]) for k in ("tau_slow", "tau_fast", "tau_r", "tau_mid")])

    def _phi(self, dt):
        return np.exp(-np.asarray(dt, dtype=float)[..., None] / self.taus)

    def walk_var(self, dt0: float) -> np.ndarray:
        """Variances of ``(w_slow, w_fast, w_r, w_mid)`` per step ``dt0`` (unit stationary variances)."""
        return 1.0 - np.exp(-2.0 * float(dt0) / self.taus)

    def scale(self, z, temp, shape):
        """``(s, ds/dz)``, each ``shape + (3,)``: the three scales at SOC ``z`` and temperature ``temp``."""
        from .params import temperature_weights

        zg = np.atleast_1d(np.asarray(self["soc"], dtype=float))
        z = np.broadcast_to(np.asarray(z, dtype=float), shape)
        kz = np.clip(np.searchsorted(zg, z, side="right") - 1, 0, max(zg.size - 2, 0))
        if zg.size > 1:
            width = zg[kz + 1] - zg[kz]
            wz = np.clip((z - zg[kz]) / width, 0.0, 1.0)
            inside = (z >= zg[0]) & (z <= zg[-1])
        else:
            width, wz, inside = np.ones(shape), np.zeros(shape), np.zeros(shape, dtype=bool)
        temps = np.atleast_1d(np.asarray(self["temps"], dtype=float))
        kt, wt = temperature_weights(temps, np.full(shape, T_REF_C) if temp is None
                                     else np.broadcast_to(np.asarray(temp, dtype=float), shape))
        kt1 = np.minimum(kt + 1, temps.size - 1)
        kz1 = np.minimum(kz + 1, zg.size - 1)
        s = np.empty(tuple(shape) + (3,))
        ds = np.empty(tuple(shape) + (3,))
        for j, key in enumerate(self.KEYS):
            g = np.asarray(self[key], dtype=float).reshape(temps.size, zg.size)
            lo = (1.0 - wt) * g[kt, kz] + wt * g[kt1, kz]
            hi = (1.0 - wt) * g[kt, kz1] + wt * g[kt1, kz1]
            s[..., j] = (1.0 - wz) * lo + wz * hi
            ds[..., j] = np.where(inside, (hi - lo) / width, 0.0)
        return s, ds

    def advance(self, e, z, i, dt, temp, base, jac):
        phi = np.broadcast_to(self._phi(dt), e.shape)
        en = phi * e
        if not jac:
            return en, None, None, None
        Fe = np.zeros(e.shape + (self.n_states,))
        for j in range(self.n_states):
            Fe[..., j, j] = phi[..., j]
        return en, Fe, np.zeros(e.shape), np.zeros(e.shape)

    def record_states(self, e0, i, dt, base):
        """``ε_k = φ^k ε_0`` over the record (no noise in open loop), by the affine scan."""
        phi = np.broadcast_to(self._phi(dt), i.shape + (self.n_states,))
        return np.stack([affine_scan(phi[..., j], np.zeros(i.shape), e0[..., j]) for j in range(self.n_states)],
                        axis=-1)

    def rate(self, e, z, i, temp, base):
        return -e / self.taus

    def output_term(self, e, z, i, temp, base, jac):
        s, ds = self.scale(z, temp, e.shape[:-1])
        i = np.broadcast_to(i, e.shape[:-1])
        slow = e[..., 0] + e[..., 3]
        dy = s[..., 0] * slow + s[..., 1] * e[..., 1] - s[..., 2] * e[..., 2] * i
        if not jac:
            return dy, None, None, None
        He = np.stack([s[..., 0], s[..., 1], -s[..., 2] * i, s[..., 0]], axis=-1)
        dz = ds[..., 0] * slow + ds[..., 1] * e[..., 1] - ds[..., 2] * e[..., 2] * i
        return dy, He, dz, -s[..., 2] * e[..., 2]


#: effect name -> class
EFFECTS: dict[str, type] = {
    cls.name: cls
    for cls in (Temperature, Hysteresis, Capacity, CurrentBias, ExtraRC, ButlerVolmer, CoulombicEfficiency,
                SelfDischarge)
}  # ModelError is not listed: it is no physical effect a diagnosis could add, only the noise recipe's state


def effect_names() -> list[str]:
    return list(EFFECTS)


def make_effect(name: str, **values) -> Effect:
    try:
        return EFFECTS[name](**values)
    except KeyError:
        raise ConfigError(f"unknown effect '{name}'; known: {', '.join(EFFECTS)}") from None


# ======================================================================================================= the model
class AugmentedModel(Model):
    """A base model with effects: ``x = [x_base, e_1, e_2, …]`` (see the module docstring for the composition)."""

    def __init__(self, base: Model, effects):
        effects = tuple(effects)
        names = [e.name for e in effects]
        if len(set(names)) != len(names):
            raise ConfigError(f"an effect appears twice: {names}")
        states = list(base.state_names)
        for e in effects:
            clash = set(e.state_names) & set(states)
            if clash:
                raise ConfigError(f"effect '{e.name}' state {sorted(clash)[0]!r} already exists in {base.name}")
            states += list(e.state_names)
        self.base = base
        self.effects = effects
        super().__init__(base.params, base.mode)
        self.name = base.name + "".join(f"+{n}" for n in names)
        self.title = base.title + "".join(f" + {n}" for n in names)
        self._states = tuple(states)
        self.discrete_states = tuple(base.discrete_states) + tuple(s for e in effects for s in e.discrete_states)
        nb = base.n_states
        self._nb = nb
        self._slices = []
        for e in effects:
            self._slices.append(slice(nb, nb + e.n_states))
            nb += e.n_states

    def required_params(self):
        return self.base.required_params()

    @property
    def state_names(self):
        return self._states

    def effect(self, name: str) -> Effect:
        for e in self.effects:
            if e.name == name:
                return e
        raise KeyError(name)

    def initial_sd(self, soc0_sd: float, state0_sd: float) -> np.ndarray:
        """SD of every state's initial value for a filter ``(n,)``: the base model's, then each effect's declaration
        (:meth:`Effect.initial_sd`; None takes ``state0_sd``)."""
        sd = list(self.base.initial_sd(soc0_sd, state0_sd))
        for e in self.effects:
            sd += [state0_sd if v is None else float(v) for v in e.initial_sd(self.base)]
        return np.asarray(sd, dtype=float)

    def walk_var(self) -> np.ndarray:
        """Random-walk variance of every state per second ``(n,)``: the base model's, then the effects' declared
        ``walk_sd`` (per √hour)."""
        w = list(self.base.walk_var())
        for e in self.effects:
            w += [(float(v) ** 2 / 3600.0) if v else 0.0 for v in (e.walk_sd or (0.0,) * e.n_states)]
        return np.asarray(w, dtype=float)

    def x0(self, soc, batch=()):
        xb = self.base.x0(soc, batch)
        parts = [xb] + [np.broadcast_to(e.initial(), xb.shape[:-1] + (e.n_states,)) for e in self.effects]
        return np.concatenate(parts, axis=-1)

    # ------------------------------------------------------------------ pieces
    def _effective_current(self, x, i):
        """``(i_e, bias column or None)``."""
        for e, sl in zip(self.effects, self._slices):
            off = e.current_offset(x[..., sl])
            if off is not None:
                return i - off, sl.start
        return i, None

    def step(self, x, i, dt, temp=None, jac=False, guards=None):
        x, (i, dt) = self._broadcast(x, i, dt)
        tmp = None if temp is None else np.broadcast_to(np.asarray(temp, dtype=float), x.shape[:-1])
        nb, n = self._nb, x.shape[-1]
        ie, bcol = self._effective_current(x, i)
        xb = x[..., :nb]
        z = x[..., 0]
        xbn, Fb, Bb = self.base.step(xb, ie, dt, tmp, jac, guards)
        xn = np.empty_like(x)
        xn[..., :nb] = xbn
        dz = xbn[..., 0] - z
        # SOC gain and leak
        gain = np.ones_like(z)
        gains = []
        for e, sl in zip(self.effects, self._slices):
            g = e.soc_gain(x[..., sl], ie, self.base)
            if g is not None:
                gains.append((sl, g))
                gain = gain * g[0]
        xn[..., 0] = z + gain * dz
        leak_dz = np.zeros_like(z)
        for e, sl in zip(self.effects, self._slices):
            lk = e.soc_leak(z, x[..., sl], dt, self.base)
            if lk is not None:
                xn[..., 0] -= lk[0]
                leak_dz = leak_dz + lk[1]
        if jac:
            F = np.zeros(x.shape + (n,))
            B = np.zeros(x.shape)
            F[..., :nb, :nb] = Fb
            B[..., :nb] = Bb
            F[..., 0, :nb] = gain[..., None] * Fb[..., 0, :]
            F[..., 0, 0] += 1.0 - gain - leak_dz
            B[..., 0] = gain * Bb[..., 0]
            for sl, (g, dg) in gains:
                others = np.where(g != 0, gain / np.where(g != 0, g, 1.0), 0.0)
                F[..., 0, sl] += (others * dz)[..., None] * dg
        for e, sl in zip(self.effects, self._slices):
            if not e.n_states:
                continue
            en, Fe, Fez, Be = e.advance(x[..., sl], z, ie, dt, tmp, self.base, jac)
            xn[..., sl] = en
            if jac:
                F[..., sl, sl] = Fe
                F[..., sl, 0] += Fez
                B[..., sl] = Be
        if not jac:
            return xn, None, None
        if bcol is not None:
            F[..., :, bcol] -= B
        return xn, F, B

    # ------------------------------------------------------------------ the whole record at once
    @property
    def whole_record(self) -> bool:
        """Whether :meth:`open_loop` can evaluate a record at once: the base model's non-SOC states are linear given
        the SOC path (:meth:`Model._states_given_soc`) and every effect with states has :meth:`Effect.record_states`."""
        base_ok = type(self.base)._states_given_soc is not Model._states_given_soc
        return base_ok and all(not e.n_states or type(e).record_states is not Effect.record_states
                               for e in self.effects)

    def open_loop(self, x0, time_s, current_a, temp_c=None, soc_jumps=None, guards=None):
        """:meth:`Model.open_loop` for the augmented model, the whole record at once when :attr:`whole_record`.

        In open loop the current offset ``b`` is constant (a random walk without noise), so the effective current
        ``i_e = i − b`` is known for the whole record first. Then, time first:

        1. the effects' states from ``i_e`` (:meth:`Effect.record_states`: prefix scans, or constants);
        2. the SOC path ``z_{k+1} = z_k + g_k·Δz_k − leak(z_k) (+ jump_{k+1})``, ``Δz_k`` the base model's B1
           increment on ``i_e``, ``g_k`` the product of the effects' SOC gains (capacity, coulombic efficiency): a
           running sum (:func:`~socbench.models.recurrence.running_sum`); with a leak (self_discharge, which depends
           on ``U_oc(z_k)``) running sums iterated to the fixed point (:meth:`_leaky_soc_path`);
        3. the base model's other states given that SOC path and ``i_e`` (its :meth:`Model._states_given_soc`);
        4. the output on every sample in one :meth:`output` call.

        Equals :meth:`open_loop_stepwise` to rounding (the SOC increment is not formed as ``(z + Δz) − z``).
        """
        if np.size(time_s) < 2 or not self.whole_record:
            return self.open_loop_stepwise(x0, time_s, current_a, temp_c, soc_jumps, guards)
        x, i_t, temp_t, dt, jumps = self._record_time_first(x0, time_s, current_a, temp_c, soc_jumps)
        T, nb = i_t.shape[0], self._nb
        ie = self._effective_current(x, i_t[:-1])[0]  # (T − 1, …): b is the initial (constant) offset
        xs = np.empty((T,) + x.shape)
        for e, sl in zip(self.effects, self._slices):
            if e.n_states:
                xs[..., sl] = e.record_states(x[..., sl], ie, dt, self.base)
        gain = np.ones(ie.shape)
        for e, sl in zip(self.effects, self._slices):
            g = e.soc_gain(xs[:-1, ..., sl], ie, self.base)
            if g is not None:
                gain = gain * g[0]
        inc = gain * soc_step(0.0, ie, dt, self.base.capacity_ah, self.base.eta_charge)[0]
        leaky = [(e, sl) for e, sl in zip(self.effects, self._slices) if type(e).soc_leak is not Effect.soc_leak]
        xs[..., 0] = running_sum(x[..., 0], inc, jumps)
        if leaky:
            xs[..., 0] = self._leaky_soc_path(xs, x[..., 0], inc, dt, jumps, leaky)
        self.base._states_given_soc(xs[..., :nb], x[..., :nb], ie, dt, None if temp_t is None else temp_t[:-1], guards)
        return self._time_first_result(xs, i_t, temp_t, guards)

    #: the leaky SOC path's fixed-point iteration stops when no sample moves by more than this (SOC fraction)
    LEAK_TOL = 1e-14
    LEAK_MAX_ITER = 200

    def _leaky_soc_path(self, xs, z0, inc, dt, jumps, leaky):
        """The SOC path under a leak that depends on ``U_oc(z_k)`` (self-discharge), time first.

        ``z_{k+1} = z_k + inc_k − leak(z_k) (+ jump_{k+1})`` is a Volterra recurrence: its fixed point is found by
        Picard iteration on the whole path, ``z^{(m+1)} = running_sum(z_0, inc − leak(z^{(m)}))`` from the leak-free
        path ``xs[..., 0]``. The error after ``m`` sweeps is bounded by ``(L·t)^m/m!`` (``L`` the leak's Lipschitz
        constant, ``t`` the record length): a day at the largest admissible rate takes about twenty whole-record
        sweeps instead of a Python step per sample. Should it not settle in ``LEAK_MAX_ITER`` sweeps, the step loop
        runs."""
        z = xs[..., 0]
        for _ in range(self.LEAK_MAX_ITER):
            leak = sum(e.soc_leak(z[:-1], xs[:-1, ..., sl], dt, self.base)[0] for e, sl in leaky)
            z_new = running_sum(z0, inc - leak, jumps)
            done = np.max(np.abs(z_new - z)) <= self.LEAK_TOL
            z = z_new
            if done:
                return z
        z = np.empty_like(xs[..., 0])
        zk = z0
        for k in range(z.shape[0]):
            z[k] = zk
            if k + 1 < z.shape[0]:
                zk = zk + inc[k] - sum(e.soc_leak(z[k], xs[k, ..., sl], dt[k], self.base)[0] for e, sl in leaky)
                if jumps is not None:
                    zk = zk + jumps[k + 1]
        return z

    def output(self, x, i, temp=None, jac=False, guards=None):
        x, (i,) = self._broadcast(x, i)
        tmp = None if temp is None else np.broadcast_to(np.asarray(temp, dtype=float), x.shape[:-1])
        nb = self._nb
        ie, bcol = self._effective_current(x, i)
        z = x[..., 0]
        y, Hb, D = self.base.output(x[..., :nb], ie, tmp, jac, guards)
        if jac:
            H = np.zeros(x.shape)
            H[..., :nb] = Hb
        factors = [k for k in (e.overpotential_factor(tmp, y.shape) for e in self.effects) if k is not None]
        if factors:  # y = U + K·(h_base − U), K the product of the effects' factors
            k = math.prod(factors)
            u, du = self.base.ocv.value_and_slope(z, tmp)
            y = u + k * (y - u)
            D = None if D is None else k * D
            if jac:
                H[..., :nb] *= k[..., None]
                H[..., 0] += (1.0 - k) * du
        for e, sl in zip(self.effects, self._slices):
            out = e.output_term(x[..., sl], z, ie, tmp, self.base, jac)
            if out is not None:
                y = y + out[0]
                if jac:
                    H[..., sl] += out[1]
                    H[..., 0] += out[2]
                    D = D + out[3]
        if not jac:
            return y, None, None
        if bcol is not None:
            H[..., bcol] -= D
        return y, H, D

    def dxdt(self, x, i, temp=None, z_params=None):
        x, (i,) = self._broadcast(x, i)
        nb = self._nb
        ie, _ = self._effective_current(x, i)
        zp = x[..., 0] if z_params is None else np.broadcast_to(z_params, x.shape[:-1])
        d = np.zeros_like(x)
        d[..., :nb] = self.base.dxdt(x[..., :nb], ie, temp, z_params)
        gain = np.ones_like(zp)
        for e, sl in zip(self.effects, self._slices):
            g = e.soc_gain(x[..., sl], ie, self.base)
            if g is not None:
                gain = gain * g[0]
        d[..., 0] *= gain
        for e, sl in zip(self.effects, self._slices):
            r = e.soc_rate(zp, x[..., sl], self.base)
            if r is not None:
                d[..., 0] += r
            d[..., sl] = e.rate(x[..., sl], zp, ie, temp, self.base)
        return d


def augment(model: Model, effects) -> AugmentedModel:
    """``model`` with ``effects`` added (an :class:`AugmentedModel` is flattened: its effects come first)."""
    if isinstance(model, AugmentedModel):
        return AugmentedModel(model.base, model.effects + tuple(effects))
    return AugmentedModel(model, effects)
