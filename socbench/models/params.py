"""Parameter sets are data: SOC functions, the parameter container, and the JSON file format.

Every model parameter is a function of SOC with its derivative (the Jacobians need ``dp/dz``):

* :class:`Constant`     ``p(z) = c``                          (the paper's models 7–14)
* :class:`Polynomial`   ``p(z) = Σ c_j z_p^j``, ``z_p = clip(z, 0, 1)``, Horner form, ``p' = 0`` when clipped
                        (the paper's 6th-degree fits for models 1–6; coefficients stored highest degree first,
                        as Table 3 prints them)
* :class:`Lookup`       piecewise linear in SOC between breakpoints, held flat outside (``p' = 0`` there)
* :class:`TemperatureTable`  one of the above per measured temperature ``T_1 < … < T_K`` (a table over SOC ×
                        temperature), interpolated in temperature (see its docstring); every SOC function takes the
                        cell temperature ``temp`` [°C] and the others ignore it

Parameter batches (for fitting: one simulation runs many parameter variants at once). ``Constant.value`` may be an
array of shape ``P``, ``Polynomial.coeffs`` an array ``P + (degree + 1,)`` and ``Lookup.value`` an array ``P + (K,)``
on shared breakpoints. ``value_and_deriv(z)`` then returns the numpy broadcast of ``P`` and ``z.shape`` (trailing axes
aligned), so a state batch ``(P,)`` gives row ``p`` the parameter variant ``p``; for a state batch ``(P, R)`` use
``P = (P, 1)``. Scalar sets behave exactly as without batching.

A parameter file (``PARAMS.json``) is self-contained: model name, capacity, OCV curve, the parameter functions, the
coulombic efficiency and model options, plus provenance notes::

    {"model": "thevenin", "capacity_ah": 22.0, "eta_charge": 1.0,
     "ocv": {"soc": [...], "voltage": [...], "source": "..."},
     "params": {"R0": {"poly": [c6, ..., c0]}, "R1": {"const": 0.006},
                "C1": {"lookup": {"soc": [...], "value": [...]}},
                "R1": {"by_temperature": {"temps": [-10, 25], "scale": "log", "nodes": [{...}, {...}]}}},
     "options": {"mode": "robust"}, "source": "...", "notes": ["..."]}

A set fitted at several temperatures (``socbench fit --data HPPC1 HPPC2 …``) counts charge on *one* SOC axis: its
``capacity_ah`` is the reference capacity ``Q_ref`` of that axis (the largest capacity measured), and the charge each
temperature delivered is kept as data in the optional key ``"capacity_by_temperature": {"temps": [...],
"capacity_ah": [...], "source": "..."}`` (:class:`CapacityTable`). A set without that key is a single-temperature set,
read and written exactly as before.

A set may carry effects of :mod:`socbench.models.effects` that were fitted with it (the charge-transfer term of a
temperature-aware fit): the optional key ``"effects": [{"name": "butler_volmer", "values": {"I0": 5.1, "dR": 0.0,
"Ea": 48000.0, "t_ref": 25.0}}]`` (each effect's parameters and settings, numbers only).
:func:`~socbench.models.registry.make_model` adds them to the model it builds, so every command that loads the file
runs the model the fit produced. A set without the key has no effects, read and written exactly as before.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import numpy as np

from ..errors import ConfigError, DataError
from ..ocv import T_REF_C, OCVCurve, ocv_from_dict


class SocFunction:
    """A parameter as a function of SOC (and of the cell temperature ``temp`` [°C], which only
    :class:`TemperatureTable` uses): ``value_and_deriv(z, temp=None) -> (p, dp/dz)``."""

    def value_and_deriv(self, z, temp=None):  # pragma: no cover - interface
        raise NotImplementedError

    def __call__(self, z, temp=None):
        return self.value_and_deriv(z, temp)[0]

    @property
    def temperatures(self) -> tuple:
        """The temperatures [°C] the function was measured at (empty: it does not depend on temperature)."""
        return ()

    def to_dict(self) -> dict:  # pragma: no cover - interface
        raise NotImplementedError

    @property
    def is_constant(self) -> bool:
        return False

    def scaled(self, factor) -> SocFunction:
        """A copy multiplied by ``factor`` (a number, or a parameter batch of factors on the leading axes)."""
        raise NotImplementedError(f"{type(self).__name__} cannot be scaled")

    def range_on_unit(self, n: int = 2001) -> tuple[float, float]:
        """(min, max) of the function on z ∈ [0, 1]."""
        v = self(np.linspace(0.0, 1.0, n))
        v = np.broadcast_to(v, (n,))
        return float(v.min()), float(v.max())


@dataclass(frozen=True)
class Constant(SocFunction):
    """``p(z) = value``. ``value`` may be an array of a parameter batch (shape ``P``): the result then has the
    numpy broadcast of ``P`` and ``z``'s shape (one parameter variant per state row; see the module docstring)."""

    value: float

    def value_and_deriv(self, z, temp=None):
        z = np.asarray(z, dtype=float)
        if np.ndim(self.value) == 0:
            return np.full(z.shape, self.value), np.zeros(z.shape)
        value = np.asarray(self.value, dtype=float)
        if value.shape == z.shape:  # the fitting hot path: one parameter variant per state row
            return value.copy(), np.zeros(z.shape)
        shape = np.broadcast_shapes(z.shape, value.shape)
        return np.broadcast_to(value, shape).copy(), np.zeros(shape)

    def scaled(self, factor):
        return Constant(np.asarray(self.value, dtype=float) * np.asarray(factor, dtype=float))

    def to_dict(self):
        return {"const": float(self.value)}

    @property
    def is_constant(self):
        return True


@dataclass(frozen=True, eq=False)
class Polynomial(SocFunction):
    """``Σ c_j z^j`` with ``coeffs`` highest degree first (Table 3 order), on ``z_p = clip(z, 0, 1)``."""

    coeffs: tuple

    def __post_init__(self):
        if np.ndim(self.coeffs) > 1:  # a parameter batch: (..., degree + 1), coefficients on the last axis
            c = np.asarray(self.coeffs, dtype=float)
            object.__setattr__(self, "coeffs", c)
            object.__setattr__(self, "_columns", tuple(np.ascontiguousarray(c[..., j]) for j in range(c.shape[-1])))
        else:
            object.__setattr__(self, "coeffs", tuple(float(c) for c in self.coeffs))

    @property
    def batched(self) -> bool:
        return isinstance(self.coeffs, np.ndarray)

    def value_and_deriv(self, z, temp=None):
        z = np.asarray(z, dtype=float)
        zp = np.clip(z, 0.0, 1.0)
        if self.batched:
            c = self._columns  # c[j] has the batch shape P and broadcasts against z
            shape = z.shape if c[0].shape == z.shape else np.broadcast_shapes(z.shape, c[0].shape)
        else:
            c = self.coeffs
            shape = z.shape
        if not self.batched:
            v = np.full(shape, c[0])
        else:
            v = c[0].copy() if c[0].shape == shape else np.broadcast_to(c[0], shape).copy()
        d = np.zeros(shape)
        for cj in c[1:]:  # Horner for the value and the derivative together
            d = d * zp + v
            v = v * zp + cj
        d = np.where((z < 0.0) | (z > 1.0), 0.0, d)
        return v, d

    def scaled(self, factor):
        return Polynomial(np.asarray(self.coeffs, dtype=float) * np.asarray(factor, dtype=float)[..., None])

    def to_dict(self):
        if self.batched:
            raise ConfigError("a batched polynomial (parameter batch) cannot be saved")
        return {"poly": list(self.coeffs)}


@dataclass(frozen=True, eq=False)
class Lookup(SocFunction):
    """Piecewise-linear table in SOC; flat (zero derivative) outside the breakpoints."""

    soc: tuple
    value: tuple

    def __post_init__(self):
        z = np.asarray(self.soc, dtype=float)
        v = np.asarray(self.value, dtype=float)
        if z.ndim != 1 or v.shape[-1:] != z.shape or z.size < 2 or np.any(np.diff(z) <= 0):
            raise ConfigError("a lookup parameter needs >= 2 strictly increasing SOC breakpoints and as many values")
        object.__setattr__(self, "soc", z)
        object.__setattr__(self, "value", v)  # (K,) or a parameter batch (..., K) on shared breakpoints
        object.__setattr__(self, "_slopes", np.diff(v, axis=-1) / np.diff(z))

    @property
    def batched(self) -> bool:
        return self.value.ndim > 1

    def value_and_deriv(self, z, temp=None):
        z = np.asarray(z, dtype=float)
        j = np.clip(np.searchsorted(self.soc, z, side="right") - 1, 0, self.soc.size - 2)
        outside = (z < self.soc[0]) | (z > self.soc[-1])
        if not self.batched:
            v = np.interp(z, self.soc, self.value)
            d = np.where(outside, 0.0, self._slopes[j])
            return v, d
        shape = np.broadcast_shapes(z.shape, self.value.shape[:-1])
        jb = np.broadcast_to(j, shape)[..., None]
        v0 = np.take_along_axis(np.broadcast_to(self.value, shape + self.value.shape[-1:]), jb, -1)[..., 0]
        s = np.take_along_axis(np.broadcast_to(self._slopes, shape + self._slopes.shape[-1:]), jb, -1)[..., 0]
        zc = np.clip(z, self.soc[0], self.soc[-1])
        v = v0 + s * (zc - self.soc[j])
        d = np.where(outside, 0.0, s)
        return v, d

    def scaled(self, factor):
        return Lookup(self.soc, np.asarray(self.value, dtype=float) * np.asarray(factor, dtype=float)[..., None])

    def to_dict(self):
        if self.batched:
            raise ConfigError("a batched lookup (parameter batch) cannot be saved")
        return {"lookup": {"soc": self.soc.tolist(), "value": self.value.tolist()}}


def temperature_weights(temps, temp):
    """``(k, w)``: ``temp`` lies in ``[temps[k], temps[k+1]]`` at fraction ``w`` (clamped to [0, 1] outside the nodes;
    ``temp=None`` means :data:`T_REF_C`). A single node gives ``k = 0, w = 0``. Shared by every temperature table (the
    parameters here and the OCV curves of :class:`~socbench.ocv.TemperatureOCV`)."""
    nodes = np.asarray(temps, dtype=float)
    t = np.asarray(T_REF_C if temp is None else temp, dtype=float)
    if nodes.size == 1:
        return np.zeros(t.shape, dtype=np.intp), np.zeros(t.shape)
    k = np.clip(np.searchsorted(nodes, t, side="right") - 1, 0, nodes.size - 2)
    lo = nodes[k]
    w = np.clip((t - lo) / (nodes[k + 1] - lo), 0.0, 1.0)
    return k, w


@dataclass(frozen=True, eq=False)
class TemperatureTable(SocFunction):
    """A parameter measured at several temperatures: ``nodes[j]`` is its SOC function at ``temps[j]`` [°C].

    Between two measured temperatures ``T_k ≤ T ≤ T_{k+1}``, ``w = (T − T_k)/(T_{k+1} − T_k)``::

        "linear"   p(z, T) = (1 − w) p_k(z) + w p_{k+1}(z)       dp/dz = (1 − w) p_k' + w p_{k+1}'
        "log"      p(z, T) = p_k(z)^(1 − w) · p_{k+1}(z)^w        dp/dz = p·((1 − w) p_k'/p_k + w p_{k+1}'/p_{k+1})

    "log" (for resistances, capacitances, time constants: positive quantities with an Arrhenius-like temperature
    dependence, exact for ``p ∝ e^{aT}`` between nodes) needs every node positive on [0, 1]. Outside ``[T_1, T_K]`` the
    end node is held (no extrapolation); ``temp=None`` means :data:`T_REF_C` (held likewise).

    Why piecewise (C⁰) and not a smooth spline: an interpolant that is linear in the node values and never leaves the
    range of its two neighbouring nodes (monotone between them, exact at every measured temperature, no overshoot when
    the nodes are few and far apart) is piecewise linear; a C¹ monotone interpolant (PCHIP) is nonlinear in the node
    values, which would make ``dp/dz`` depend on every node's derivative through the PCHIP slopes.
    """

    temps: tuple
    nodes: tuple
    scale: str = "linear"

    def __post_init__(self):
        t = np.asarray(self.temps, dtype=float)
        nodes = tuple(soc_function(n) for n in self.nodes)
        if t.ndim != 1 or t.size < 1 or t.size != len(nodes) or not np.all(np.isfinite(t)) \
                or np.any(np.diff(t) <= 0):
            raise ConfigError("a temperature table needs >= 1 strictly increasing temperatures and one SOC function "
                              f"per temperature (got temps {list(np.atleast_1d(t))} and {len(nodes)} functions)")
        if any(isinstance(n, TemperatureTable) for n in nodes):
            raise ConfigError("a temperature table's nodes must be SOC functions, not temperature tables")
        if self.scale not in ("linear", "log"):
            raise ConfigError(f"a temperature table's scale must be 'linear' or 'log', got {self.scale!r}")
        if self.scale == "log":
            for tk, n in zip(t, nodes):
                lo = n.range_on_unit()[0]
                if not lo > 0:
                    raise ConfigError(f"a 'log' temperature table needs positive values: at {tk:g} °C the minimum on "
                                      f"[0, 1] is {lo:.4g}")
        object.__setattr__(self, "temps", tuple(float(x) for x in t))
        object.__setattr__(self, "nodes", nodes)

    @property
    def temperatures(self) -> tuple:
        return self.temps

    def value_and_deriv(self, z, temp=None):
        z = np.asarray(z, dtype=float)
        if len(self.nodes) == 1:
            return self.nodes[0].value_and_deriv(z)
        k, w = temperature_weights(self.temps, temp)
        shape = np.broadcast_shapes(z.shape, w.shape)
        k, zb = np.broadcast_to(k, shape).ravel(), np.broadcast_to(z, shape).ravel()
        w = np.broadcast_to(w, shape)
        lo_v, lo_d, hi_v, hi_d = (np.empty(zb.size) for _ in range(4))
        for j in np.unique(k):  # each node pair evaluated only where the temperature needs it
            m = k == j
            lo_v[m], lo_d[m] = self.nodes[j].value_and_deriv(zb[m])
            hi_v[m], hi_d[m] = self.nodes[j + 1].value_and_deriv(zb[m])
        lo_v, lo_d, hi_v, hi_d = (a.reshape(shape) for a in (lo_v, lo_d, hi_v, hi_d))
        if self.scale == "linear":
            v, d = (1.0 - w) * lo_v + w * hi_v, (1.0 - w) * lo_d + w * hi_d
        else:
            v = np.exp((1.0 - w) * np.log(lo_v) + w * np.log(hi_v))
            d = v * ((1.0 - w) * lo_d / lo_v + w * hi_d / hi_v)
        # at (and beyond) a measured temperature: that node's own numbers, bit for bit
        at_lo, at_hi = w == 0.0, w == 1.0
        return (np.where(at_lo, lo_v, np.where(at_hi, hi_v, v)),
                np.where(at_lo, lo_d, np.where(at_hi, hi_d, d)))

    def at(self, temp: float) -> SocFunction:
        """The SOC function at a measured temperature (a node), for reports."""
        j = int(np.argmin(np.abs(np.asarray(self.temps) - float(temp))))
        return self.nodes[j]

    def range_on_unit(self, n: int = 2001) -> tuple[float, float]:
        lows, highs = zip(*(f.range_on_unit(n) for f in self.nodes))
        return float(min(lows)), float(max(highs))

    def to_dict(self):
        return {"by_temperature": {"temps": list(self.temps), "scale": self.scale,
                                   "nodes": [n.to_dict() for n in self.nodes]}}


def soc_function(spec) -> SocFunction:
    """Build a :class:`SocFunction` from its JSON form (a bare number is a constant)."""
    if isinstance(spec, SocFunction):
        return spec
    if isinstance(spec, (int, float)):
        return Constant(float(spec))
    if not isinstance(spec, Mapping) or len(spec) == 0:
        raise ConfigError(f"a parameter must be a number or one of {{const, poly, lookup}}, got {spec!r}")
    if "const" in spec:
        return Constant(float(spec["const"]))
    if "poly" in spec:
        return Polynomial(tuple(spec["poly"]))
    if "lookup" in spec:
        lk = spec["lookup"]
        return Lookup(tuple(lk["soc"]), tuple(lk["value"]))
    if "by_temperature" in spec:
        bt = spec["by_temperature"]
        if not isinstance(bt, Mapping) or "temps" not in bt or "nodes" not in bt:
            raise ConfigError("a 'by_temperature' parameter needs keys 'temps' and 'nodes'")
        return TemperatureTable(tuple(bt["temps"]), tuple(bt["nodes"]), bt.get("scale", "linear"))
    raise ConfigError(f"unknown parameter form {sorted(spec)}; expected const, poly, lookup or by_temperature")


@dataclass(frozen=True, eq=False)
class CapacityTable:
    """The charge [Ah] the cell delivered at each measured temperature [°C] (data, not a model parameter).

    ``at(temp)`` interpolates linearly between the measured temperatures and holds the end values outside (the rule
    of :func:`temperature_weights`). A set's own SOC axis is counted with ``ModelParams.capacity_ah``; this table says
    how much of that axis each temperature reached (:mod:`socbench.socaxis` converts between the two definitions).
    """

    temps: tuple
    capacity_ah: tuple
    source: str = ""

    def __post_init__(self):
        t = np.asarray(self.temps, dtype=float).ravel()
        q = np.asarray(self.capacity_ah, dtype=float).ravel()
        if t.size < 1 or t.size != q.size or not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise ConfigError("a capacity table needs >= 1 strictly increasing temperatures and one capacity per "
                              f"temperature (got temps {t.tolist()} and {q.size} capacities)")
        if not np.all(np.isfinite(q) & (q > 0)):
            raise ConfigError(f"a capacity table needs positive capacities, got {q.tolist()}")
        object.__setattr__(self, "temps", tuple(float(x) for x in t))
        object.__setattr__(self, "capacity_ah", tuple(float(x) for x in q))

    def at(self, temp=None):
        """Capacity [Ah] at ``temp`` [°C] (None: :data:`T_REF_C`), linear between nodes, held outside."""
        if len(self.temps) == 1:
            return np.full(np.shape(T_REF_C if temp is None else temp), self.capacity_ah[0])[()]
        k, w = temperature_weights(self.temps, temp)
        q = np.asarray(self.capacity_ah)
        return ((1.0 - w) * q[k] + w * q[k + 1])[()]

    def to_dict(self) -> dict:
        return {"temps": list(self.temps), "capacity_ah": list(self.capacity_ah), "source": self.source}

    @classmethod
    def from_dict(cls, d) -> CapacityTable:
        if not isinstance(d, Mapping) or "temps" not in d or "capacity_ah" not in d:
            raise ConfigError("'capacity_by_temperature' needs keys 'temps' and 'capacity_ah'")
        return cls(tuple(d["temps"]), tuple(d["capacity_ah"]), str(d.get("source", "")))


@dataclass(frozen=True, eq=False)
class ModelParams:
    """Everything a model needs besides its structure: capacity, OCV curve, parameter functions, options.

    ``capacity_ah`` is the capacity the model counts charge with (its SOC axis); ``capacity_by_temperature`` (None
    for a single-temperature set) the charge measured at each temperature, as data (:class:`CapacityTable`).
    """

    capacity_ah: float
    ocv: OCVCurve
    values: Mapping[str, SocFunction]
    eta_charge: float = 1.0
    options: Mapping = field(default_factory=dict)
    source: str = ""
    notes: tuple = ()
    capacity_by_temperature: CapacityTable | None = None
    #: effects fitted with the set: ``({"name": effect name, "values": {parameter or setting: number}}, …)``
    effects: tuple = ()

    def __post_init__(self):
        if not (np.isfinite(self.capacity_ah) and self.capacity_ah > 0):
            raise ConfigError(f"capacity_ah must be positive, got {self.capacity_ah}")
        if not (0 < self.eta_charge <= 1):
            raise ConfigError(f"eta_charge must be in (0, 1], got {self.eta_charge}")
        vals = {k: soc_function(v) for k, v in self.values.items()}
        object.__setattr__(self, "values", MappingProxyType(vals))
        object.__setattr__(self, "options", MappingProxyType(dict(self.options)))
        object.__setattr__(self, "notes", tuple(self.notes))
        object.__setattr__(self, "effects", _effect_specs(self.effects))

    def __getitem__(self, name: str) -> SocFunction:
        try:
            return self.values[name]
        except KeyError:
            raise ConfigError(f"parameter '{name}' is missing (have {sorted(self.values)})") from None

    def replace(self, **changes) -> ModelParams:
        d = {
            "capacity_ah": self.capacity_ah,
            "ocv": self.ocv,
            "values": dict(self.values),
            "eta_charge": self.eta_charge,
            "options": dict(self.options),
            "source": self.source,
            "notes": self.notes,
            "capacity_by_temperature": self.capacity_by_temperature,
            "effects": self.effects,
        }
        d.update(changes)
        return ModelParams(**d)

    @property
    def temperatures(self) -> tuple:
        """Every temperature [°C] a parameter or the OCV curve was measured at, sorted (empty: no temperature
        dependence; the set is then valid at whatever temperature it was fitted at)."""
        ts = set(getattr(self.ocv, "temperatures", ()))
        for f in self.values.values():
            ts.update(f.temperatures)
        return tuple(sorted(ts))

    def with_values(self, **values) -> ModelParams:
        new = dict(self.values)
        new.update({k: soc_function(v) for k, v in values.items()})
        return self.replace(values=new)


def _effect_specs(specs) -> tuple:
    """The ``effects`` of a set, checked (a known effect, its own parameter and setting names, finite numbers) and
    frozen as ``({"name", "values"}, …)`` with float values."""
    from .effects import EFFECTS  # effects import this module

    out = []
    for spec in specs:
        if not isinstance(spec, Mapping) or set(spec) != {"name", "values"} or not isinstance(spec["values"], Mapping):
            raise ConfigError(f"an effect must be {{\"name\": ..., \"values\": {{...}}}}, got {spec!r}")
        cls = EFFECTS.get(spec["name"])
        if cls is None:
            raise ConfigError(f"unknown effect '{spec['name']}'; known: {', '.join(EFFECTS)}")
        allowed = set(cls.param_names) | set(cls.settings)
        values = {}
        for k, v in spec["values"].items():
            if k not in allowed:
                raise ConfigError(f"effect '{cls.name}' has no parameter '{k}' (have {sorted(allowed)})")
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) or not np.isfinite(v):
                raise ConfigError(f"effect '{cls.name}': '{k}' must be a finite number, got {v!r}")
            values[k] = float(v)
        out.append(MappingProxyType({"name": cls.name, "values": MappingProxyType(values)}))
    if len({e["name"] for e in out}) != len(out):
        raise ConfigError(f"an effect appears twice: {[e['name'] for e in out]}")
    return tuple(out)


def params_to_dict(model_name: str, params: ModelParams, **extra) -> dict:
    return {
        "model": model_name,
        "capacity_ah": params.capacity_ah,
        "eta_charge": params.eta_charge,
        "ocv": params.ocv.to_dict(),
        "params": {k: v.to_dict() for k, v in params.values.items()},
        "options": dict(params.options),
        "source": params.source,
        "notes": list(params.notes),
        **({"capacity_by_temperature": params.capacity_by_temperature.to_dict()}
           if params.capacity_by_temperature is not None else {}),
        **({"effects": [{"name": e["name"], "values": dict(e["values"])} for e in params.effects]}
           if params.effects else {}),
        **extra,
    }


#: the SOC grid a parameter file's values are checked on (:func:`check_values`)
CHECK_SOC = np.linspace(0.0, 1.0, 101)


def _must_be(name: str) -> tuple | None:
    """``(test, words)`` a parameter's values must pass by what its name says it is: a resistance ``R…`` at least
    zero, a capacitance ``C<digit>`` or a time constant ``tau…`` above zero; None for any other name (the
    phenomenological ``K…``, ``A``, ``B``, … of the 14 models take either sign)."""
    if name.startswith("R"):
        return (lambda v: v >= 0.0), "a resistance, at least 0"
    if (name.startswith("C") and name[1:].isdigit()) or name.startswith("tau"):
        return (lambda v: v > 0.0), "above 0"
    return None


def _data_points(f) -> np.ndarray | None:
    """The values a parameter is given at (a constant's, a lookup's, a temperature table's of those), or None for a
    polynomial, whose sign between and beyond its nodes is the models' to guard (ECM_SPEC: the paper's own R0(z)
    polynomials dip below zero near full)."""
    if isinstance(f, Constant):
        return np.atleast_1d(np.asarray(f.value, dtype=float))
    if isinstance(f, Lookup):
        return np.asarray(f.value, dtype=float)
    if isinstance(f, TemperatureTable):
        nodes = [_data_points(n) for n in f.nodes]
        return None if any(n is None for n in nodes) else np.concatenate(nodes)
    return None


def check_values(values: Mapping) -> None:
    """A parameter file's values: finite on :data:`CHECK_SOC` (where the models evaluate them: SOC is clipped to
    0…1) at each temperature they tabulate, and, where they are given as data points (:func:`_data_points`), within
    the sign their name implies (:func:`_must_be`). Raises :class:`ConfigError` naming the parameter."""
    for name, f in values.items():
        for temp in f.temperatures or (None,):
            v = np.asarray(f.value_and_deriv(CHECK_SOC, temp)[0], dtype=float)
            if not np.isfinite(v).all():
                k = int(np.argmax(~np.isfinite(v)))
                at = f" at {temp:g} °C" if temp is not None else ""
                raise ConfigError(f"parameter '{name}' must be finite: {v[k]:g} at SOC {CHECK_SOC[k]:g}{at}")
        must, points = _must_be(name), _data_points(f)
        if must is not None and points is not None and not must[0](points).all():
            bad = points[~must[0](points)][0]
            raise ConfigError(f"parameter '{name}' must be {must[1]}, got {bad:g}")


def params_from_dict(d: Mapping, *, ocv: OCVCurve | None = None, file: str = "") -> tuple[str, ModelParams]:
    """``(model_name, ModelParams)`` from the JSON form. ``ocv`` fills in a file that carries none. Every value is
    checked (:func:`check_values`) and every malformed entry is a :class:`ConfigError` naming the file."""
    known = {"model", "capacity_ah", "eta_charge", "ocv", "params", "options", "source", "notes", "fit", "paper",
             "capacity_by_temperature", "model_error", "effects"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ConfigError(f"{file or 'parameters'}: unknown key '{unknown[0]}'")
    for key in ("model", "params"):
        if key not in d:
            raise ConfigError(f"{file or 'parameters'}: missing key '{key}'")
    try:
        curve = ocv_from_dict(d["ocv"]) if "ocv" in d else ocv
    except DataError as exc:
        raise exc.with_file(file) if file else exc from None
    except ConfigError as exc:
        raise ConfigError(f"{file or 'parameters'}: 'ocv': {exc}") from None
    except (TypeError, ValueError, KeyError, AttributeError) as exc:
        raise ConfigError(f"{file or 'parameters'}: 'ocv' malformed ({type(exc).__name__}: {exc})") from None
    if curve is None:
        raise ConfigError(f"{file or 'parameters'}: no OCV curve (key 'ocv')")
    if "capacity_ah" not in d:
        raise ConfigError(f"{file or 'parameters'}: missing key 'capacity_ah'")
    try:
        p = ModelParams(
            capacity_ah=_number(d["capacity_ah"], "capacity_ah"),
            ocv=curve,
            values={k: soc_function(v) for k, v in d["params"].items()},
            eta_charge=_number(d.get("eta_charge", 1.0), "eta_charge"),
            options=d.get("options", {}),
            source=d.get("source", ""),
            notes=tuple(d.get("notes", ())),
            capacity_by_temperature=(CapacityTable.from_dict(d["capacity_by_temperature"])
                                     if d.get("capacity_by_temperature") is not None else None),
            effects=tuple(d.get("effects", ())),
        )
        check_values(p.values)
    except ConfigError as exc:
        raise ConfigError(f"{file or 'parameters'}: {exc}") from None
    except (TypeError, ValueError, KeyError, AttributeError) as exc:  # a value of the wrong type or shape
        raise ConfigError(f"{file or 'parameters'}: malformed entry ({type(exc).__name__}: {exc})") from None
    return str(d["model"]), p


def _number(v, key: str) -> float:
    """A JSON number of a parameter file (``key`` names it in the error): not a string, a list or a boolean."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"'{key}' must be a number, got {v!r}")
    return float(v)


def load_params(path) -> tuple[str, ModelParams]:
    """Read a ``PARAMS.json`` file; errors name the file."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise DataError("file not found", file=str(path)) from None
    except IsADirectoryError:
        raise DataError("is a directory, not a parameter file", file=str(path)) from None
    except (PermissionError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot be read ({type(exc).__name__})", file=str(path)) from None
    except json.JSONDecodeError as exc:
        raise DataError(f"not valid JSON ({exc.msg} at line {exc.lineno})", file=str(path)) from None
    if not isinstance(d, Mapping):
        raise ConfigError(f"{path}: expected a JSON object")
    return params_from_dict(d, file=str(path))


def save_params(path, model_name: str, params: ModelParams, **extra) -> None:
    from ..io import atomic_write_text

    atomic_write_text(path, json.dumps(params_to_dict(model_name, params, **extra), indent=2))
