"""Lowering: a model (with its parameter set, OCV curve and effects) as two plain arrays a compiled kernel reads.

``lower(model) -> Lowered(im, fm)``: ``im`` (int64) holds the structure — the family code, state layout, options and
*records* (offsets into ``fm``); ``fm`` (float64, one row per parameter variant) holds the numbers. One compiled
interpreter (:mod:`socbench.kernels.evaluate`) evaluates ``step``/``output`` and their Jacobians for any lowered
model, so sixteen models, their options and any combination of the eight effects share one compiled code.

Layout of ``im`` (``H_*`` header slots, then records)::

    header   [family, n_states, n_base_states, sub, flags, ocv record, n_params, params list, n_effects,
              effects table, bias state (−1: none), step's parameter range (2), output's (2), 0]
    params   one function-record offset per parameter, in the order the family's kernel_spec() lists them
    function [kind, fm offset, size, extra, (node records of a temperature table)]
               CONST   fm: value
               POLY    fm: coefficients, highest degree first (size of them)
               LOOKUP  fm: breakpoints (K), values (K), slopes (K − 1); extra 1 = the parameter-batch formula
               TABLE   fm: temperatures (K); extra 0 linear / 1 log; then K node records (plain functions)
    ocv      [kind, fm offset, size, 0, (curve records of a temperature OCV)]
               PCHIP   fm: rest-point SOCs (m), cubic coefficients ((m − 1) × 4), U(z_lo), U(z_hi), U'(z_lo), U'(z_hi),
                       extension limit (the linear extension beyond the rest points; inf = unlimited)
               TABLE   fm: temperatures (K); then K PCHIP records
    effects  per effect [code, first state, n states, fm offset of its values]

``fm[0]`` is the capacity [Ah], ``fm[1]`` the charge efficiency. A parameter batch (fitting: ``Constant`` values
``(V,)``, ``Polynomial`` coefficients ``(V, d + 1)``, ``Lookup`` values ``(V, K)``, effect values ``(V,)``) lowers to
``V`` rows of ``fm`` over one ``im``: every variant has the same structure.

A model lowers when its class names a compiled family (:meth:`~socbench.models.base.Model.kernel_spec`), its mode is
``robust`` (strict mode raises on guards; the compiled code does not) and every parameter is one of the forms above;
otherwise :class:`NotLowerable` says why and the caller runs the numpy engine.

How to add a compiled model family, effect or SOC-function form: DOCS in :mod:`socbench.kernels`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..models.effects import AugmentedModel
from ..models.params import Constant, Lookup, Polynomial, TemperatureTable
from ..ocv import EXCURSION_FLAG, OCVCurve, TemperatureOCV

# ---------------------------------------------------------------------------------------------- codes (shared)
#: model families: the family of Model.kernel_spec() -> code (one compiled step/output pair each in evaluate.py)
FAMILIES = {"rc_network": 1, "improved_rc": 2, "static_terms": 3, "tremblay": 4, "esc": 5}
#: effects: Effect.name -> code (one compiled hook set each in evaluate.py)
EFFECT_CODES = {"temperature": 1, "hysteresis": 2, "capacity": 3, "current_bias": 4, "extra_rc": 5,
                "butler_volmer": 6, "coulombic_efficiency": 7, "self_discharge": 8, "r0_offset": 9, "model_error": 10}
#: static-term models: sub code of the static_terms family
STATIC_TERMS = {"shepherd": 1, "unnewehr": 2, "nernst": 3, "fang": 4, "tremblay1": 5, "plett": 6}

FN_CONST, FN_POLY, FN_LOOKUP, FN_TABLE = 0, 1, 2, 3
OCV_PCHIP, OCV_TABLE = 10, 11

H_FAMILY, H_N, H_NB, H_SUB, H_FLAGS, H_OCV, H_NPAR, H_PARAMS, H_NEFF, H_EFFECTS, H_BIAS = range(11)
H_STEP0, H_STEP1, H_OUT0, H_OUT1 = range(11, 15)
HEADER = 16
F_CAP, F_ETA = 0, 1
#: rc_network flags
RC_INTEGRATOR, RC_C0_PRINTED = 1, 2
#: ints per effect in the effects table
EFFECT_WIDTH = 4
#: most parameters a lowered model may have (the compiled scratch holds them)
MAX_PARAMS = 48


class NotLowerable(Exception):
    """The model (or one of its parameters or options) has no compiled form; the message says which."""


@dataclass(frozen=True, eq=False)
class Lowered:
    """A lowered model: structure ``im`` (int64) and numbers ``fm`` (float64, ``(n_variants, L)``)."""

    im: np.ndarray
    fm: np.ndarray
    name: str

    @property
    def n_states(self) -> int:
        return int(self.im[H_N])

    @property
    def n_variants(self) -> int:
        return int(self.fm.shape[0])


class _Builder:
    """Appends ints and float slots. A float slot is a scalar or a ``(V,)`` array (one value per variant); a block of
    consecutive slots is a ``(k,)`` array (the same for every variant) or ``(V, k)`` (one row per variant), appended
    whole: a model is lowered on every residual of a fit, and one Python call per OCV coefficient was most of it."""

    def __init__(self):
        self.ints: list = [0] * HEADER
        self.blocks: list = []  # (first slot, array (1 or V, k))
        self.size = 0
        self.variants = 1

    def _append(self, rows: np.ndarray) -> int:
        if rows.shape[0] != 1:
            if self.variants not in (1, rows.shape[0]):
                raise NotLowerable(f"parameter batches of sizes {self.variants} and {rows.shape[0]}")
            self.variants = rows.shape[0]
        off = self.size
        self.blocks.append((off, rows))
        self.size += rows.shape[1]
        return off

    def slot(self, value) -> int:
        v = np.asarray(value, dtype=float)
        if v.ndim > 1:
            raise NotLowerable(f"a parameter batch of shape {v.shape} (only one batch axis lowers)")
        return self._append(v.reshape(-1, 1))

    def block(self, values) -> int:
        """Consecutive slots from ``(k,)`` or ``(V, k)`` values; returns the offset of the first."""
        v = np.asarray(values, dtype=float)
        if v.ndim > 2:
            raise NotLowerable(f"a parameter batch of shape {v.shape} (only one batch axis lowers)")
        return self._append(np.atleast_2d(v))

    def slots(self, values) -> int:
        """Consecutive slots, one per value (each a scalar or ``(V,)``); returns the offset of the first."""
        off = self.size
        for v in values:
            self.slot(v)
        return off

    def record(self, *ints) -> int:
        off = len(self.ints)
        self.ints.extend(int(v) for v in ints)
        return off

    def finish(self, name: str) -> Lowered:
        fm = np.empty((self.variants, self.size))
        for off, rows in self.blocks:
            fm[:, off:off + rows.shape[1]] = rows
        return Lowered(np.asarray(self.ints, dtype=np.int64), fm, name)


# ---------------------------------------------------------------------------------------------- SOC functions
def _plain_function(b: _Builder, f) -> int:
    if isinstance(f, Constant):
        return b.record(FN_CONST, b.slot(f.value), 1, 0)
    if isinstance(f, Polynomial):
        c = np.asarray(f.coeffs, dtype=float)
        return b.record(FN_POLY, b.block(c), c.shape[-1], 0)
    if isinstance(f, Lookup):
        K = f.soc.size
        off = b.block(f.soc)
        b.block(f.value)
        b.block(f._slopes)
        return b.record(FN_LOOKUP, off, K, 1 if f.batched else 0)
    raise NotLowerable(f"parameter form {type(f).__name__} has no compiled evaluator")


def _function(b: _Builder, f) -> int:
    if not isinstance(f, TemperatureTable):
        return _plain_function(b, f)
    nodes = [_plain_function(b, n) for n in f.nodes]
    off = b.block(f.temps)
    return b.record(FN_TABLE, off, len(nodes), 1 if f.scale == "log" else 0, *nodes)


# ---------------------------------------------------------------------------------------------- OCV curves
def _extension_limit(curve) -> float:
    """How far beyond its rest points an OCVCurve extends linearly before it is held (socbench.ocv)."""
    return float(EXCURSION_FLAG)


def _pchip(b: _Builder, c) -> int:
    m = c.soc.size
    off = b.block(c.soc)
    b.block(np.asarray(c._coef, dtype=float).ravel())
    b.block([c.voltage[0], c.voltage[-1], c._slope_lo, c._slope_hi, _extension_limit(c)])
    return b.record(OCV_PCHIP, off, m, 0)


def _ocv(b: _Builder, curve) -> int:
    if isinstance(curve, TemperatureOCV):
        recs = [_pchip(b, c) for c in curve.curves]
        off = b.block(curve.temps)
        return b.record(OCV_TABLE, off, len(recs), 0, *recs)
    if type(curve) is not OCVCurve:
        raise NotLowerable(f"OCV curve type {type(curve).__name__} has no compiled evaluator")
    return _pchip(b, curve)


# ---------------------------------------------------------------------------------------------- models
def lower(model) -> Lowered:
    """Lower ``model`` (see the module docstring); :class:`NotLowerable` if it has no compiled form."""
    base, effects = (model.base, model.effects) if isinstance(model, AugmentedModel) else (model, ())
    if getattr(model, "mode", "robust") != "robust":
        raise NotLowerable(f"mode '{model.mode}' (strict mode raises on its guards; only robust mode is compiled)")
    spec_of = getattr(base, "kernel_spec", None)
    spec = spec_of() if spec_of is not None else None
    if spec is None:
        raise NotLowerable(f"model '{getattr(base, 'name', type(base).__name__)}' names no compiled family")
    if spec.family not in FAMILIES:
        raise NotLowerable(f"unknown compiled family '{spec.family}'")
    b = _Builder()
    b.slot(float(base.capacity_ah))
    b.slot(float(base.eta_charge))
    ocv = _ocv(b, base.ocv)
    if len(spec.params) > MAX_PARAMS:
        raise NotLowerable(f"{len(spec.params)} parameters (the compiled evaluator holds at most {MAX_PARAMS})")
    params = [_function(b, base.params[p]) for p in spec.params]
    plist = b.record(*params) if params else len(b.ints)
    table, bias = [], -1
    start = base.n_states
    for e in effects:
        code = EFFECT_CODES.get(e.name)
        values_of = getattr(e, "kernel_values", None)
        if code is None or values_of is None:
            raise NotLowerable(f"effect '{e.name}' has no compiled form")
        values = values_of(base)
        if values is None:
            raise NotLowerable(f"effect '{e.name}' with these settings has no compiled form")
        values = tuple(values)
        off = b.slots(values) if values else b.size
        if e.name == "current_bias" and bias < 0:
            bias = start
        table.append((code, start, e.n_states, off))
        start += e.n_states
    etab = b.record(*(v for row in table for v in row)) if table else len(b.ints)
    header = {H_FAMILY: FAMILIES[spec.family], H_N: start, H_NB: base.n_states, H_SUB: spec.sub,
              H_FLAGS: spec.flags, H_OCV: ocv, H_NPAR: len(params), H_PARAMS: plist, H_NEFF: len(table),
              H_EFFECTS: etab, H_BIAS: bias, H_STEP0: spec.step[0], H_STEP1: spec.step[1],
              H_OUT0: spec.output[0], H_OUT1: spec.output[1]}
    for k, v in header.items():
        b.ints[k] = int(v)
    if start != model.n_states:  # pragma: no cover - a layout bug, not a user error
        raise NotLowerable(f"state count mismatch: lowered {start}, model {model.n_states}")
    return b.finish(getattr(model, "name", type(model).__name__))


def try_lower(model) -> tuple[Lowered | None, str]:
    """``(lowered, "")`` or ``(None, why not)``."""
    try:
        return lower(model), ""
    except NotLowerable as exc:
        return None, str(exc)
