"""Which parameters a model has, what kind each one is, and how a fit represents it.

Kinds are read from the parameter *name* (models declare only names through ``required_params()``), so a model added
later is fitted without touching this file as long as it follows the naming convention of ECM_SPEC §5:

=========  ======  ========  =============================================================
prefix     kind    unit      parametrisation (θ)
=========  ======  ========  =============================================================
R*         R       Ω         log (positive)
C*         C       F         log (positive)
tau*, t_c  tau     s         log (positive)
gamma      gamma   1         log (positive)
K*, A, M*  volt    V         linear, symmetric bounds
B          B       1/Ah      linear
other      other   ?         log if the reference value is positive, else linear
=========  ======  ========  =============================================================

A unit the model declares in ``param_units`` takes precedence over the name (Fang's ``tau1``, ``tau2`` are
dimensionless offsets, not time constants).

Initial guesses and bounds come from :class:`Guess`: the instantaneous pulse resistance ``r_inst`` (ΔV/ΔI at pulse
edges), the pulse resistance at the end of a pulse ``r_pulse`` and a relaxation time constant ``tau`` from the rests
(see :mod:`socbench.identify.hppc`), plus the capacity and the OCV slope.

Forms (how a parameter depends on SOC in the fit):

* ``constant``  one θ;
* ``poly``      a 6th-degree polynomial represented by its values at 7 Chebyshev nodes on [0, 1] (well conditioned,
                unlike the monomial coefficients; positivity at the nodes through the log); stored as the monomial
                :class:`~socbench.models.params.Polynomial` the paper prints. A record that covers only part of the
                SOC axis (a cold HPPC counted with the warm capacity: ``[1 − Q_T/Q_ref, 1]``) puts the nodes on that
                *domain*; such a polynomial would blow up outside it, so it is stored clamped: a
                :class:`~socbench.models.params.Lookup` sampled every 0.01 on the domain, which holds its end values;
* ``lookup``    values at SOC knots, linear in between (:class:`~socbench.models.params.Lookup`), flat outside them.
                On a partial domain the knots outside it move onto its edge
                (:func:`socbench.identify.fit.knots_within`): a knot no sample reaches is not identified.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ..models.params import Constant, Lookup, Polynomial

#: degree of the paper's SOC polynomials (models 1–6)
POLY_DEGREE = 6


@dataclass(frozen=True)
class Guess:
    """Scales measured from the identification data (all positive)."""

    r_inst: float = 0.02
    r_pulse: float = 0.04
    tau: float = 30.0  # fast relaxation time constant [s]
    tau_slow: float = 300.0  # slow relaxation time constant [s]
    capacity_ah: float = 1.0
    ocv_slope: float = 1.0  # mean dU_oc/dz [V per unit SOC]


@dataclass(frozen=True)
class ParamSpec:
    """One model parameter: name, kind, unit, log-parametrised or not, physical start value and bounds."""

    name: str
    kind: str
    unit: str
    log: bool
    init: float
    lower: float
    upper: float

    def to_theta(self, p):
        p = np.asarray(p, dtype=float)
        return np.log(p) if self.log else p

    def from_theta(self, th):
        th = np.asarray(th, dtype=float)
        return np.exp(th) if self.log else th

    @property
    def theta_bounds(self) -> tuple[float, float]:
        return (float(np.log(self.lower)), float(np.log(self.upper))) if self.log else (self.lower, self.upper)


_UNIT_KINDS = (("Ω", "R"), ("F", "C"), ("s", "tau"), ("1/Ah", "B"), ("V", "volt"))


def param_kind(name: str, unit: str | None = None) -> tuple[str, str]:
    """``(kind, unit)`` of a parameter: from the unit the model declares (``param_units``) when it has one, else from
    the name (see the module table). A dimensionless parameter other than ``gamma`` is of kind ``other``."""
    if unit:
        u = unit.strip()
        if u in ("-", "1", ""):
            return ("gamma", "1") if name in ("gamma", "g") else ("other", "1")
        for prefix, kind in _UNIT_KINDS:
            if u == prefix or u.startswith(prefix + " "):
                return kind, prefix
    if name in ("t_c", "tc") or re.fullmatch(r"tau\w*", name):
        return "tau", "s"
    if name in ("gamma", "g"):
        return "gamma", "1"
    if name == "B":
        return "B", "1/Ah"
    if re.fullmatch(r"R\w*", name):
        return "R", "Ω"
    if re.fullmatch(r"C\w*", name):
        return "C", "F"
    if re.fullmatch(r"(K\w*|A|M\w*)", name):
        return "volt", "V"
    return "other", "?"


def _branch_index(name: str) -> int | None:
    m = re.fullmatch(r"[A-Za-z_]+?(\d+)", name)
    return int(m.group(1)) if m else None


def branch_tau(guess: Guess, j: int | None, n: int) -> float:
    """Start time constant of RC branch ``j`` (1-based) of ``n``: spread geometrically from the fast to the slow
    relaxation time constant (their geometric mean for a single branch)."""
    fast = max(guess.tau, 1e-2)
    slow = max(guess.tau_slow, fast)
    if not j or j < 1 or n <= 1:
        return float(np.sqrt(fast * slow))
    return float(fast * (slow / fast) ** ((min(j, n) - 1) / (n - 1)))


def param_spec(name: str, guess: Guess, n_branches: int = 1, reference: float | None = None,
               unit: str | None = None) -> ParamSpec:
    """Start value and bounds of parameter ``name`` (``n_branches`` RC branches share the polarisation resistance;
    branch ``j`` of ``n`` gets a time constant from :func:`branch_tau`)."""
    kind, unit = param_kind(name, unit)
    r0 = max(guess.r_inst, 1e-6)
    r_pol = max(guess.r_pulse - guess.r_inst, 0.25 * r0)
    n = max(n_branches, 1)
    j = _branch_index(name)
    if kind == "R":
        if j is None or j == 0:
            return ParamSpec(name, kind, unit, True, r0, r0 * 1e-3, r0 * 50.0)
        init = r_pol / n
        return ParamSpec(name, kind, unit, True, init, r0 * 1e-4, 100.0 * max(guess.r_pulse, r0))
    if kind == "C":
        if j == 0:  # PNGV/GNL bulk capacitor: the OCV capacitance 3600 Q / U'
            init = 3600.0 * guess.capacity_ah / max(guess.ocv_slope, 1e-3)
            return ParamSpec(name, kind, unit, True, init, init * 1e-3, init * 1e3)
        init = branch_tau(guess, j, n) / (r_pol / n)
        return ParamSpec(name, kind, unit, True, init, init * 1e-4, init * 1e4)
    if kind == "tau":
        if name in ("t_c", "tc"):
            return ParamSpec(name, kind, unit, True, guess.tau, 1e-2, 1e5)
        return ParamSpec(name, kind, unit, True, branch_tau(guess, j, n), 1e-2, 1e5)
    if kind == "gamma":
        init = reference if (reference is not None and reference > 0) else 1.0
        return ParamSpec(name, kind, unit, True, init, 1e-4, 1e5)
    if kind == "volt":
        init = reference if reference is not None and abs(reference) < 0.5 else 0.0
        if name == "A" and init == 0.0:
            init = 1e-3  # so that B has a gradient from the first iteration
        return ParamSpec(name, kind, unit, False, init, -1.0, 1.0)
    if kind == "B":
        q = max(guess.capacity_ah, 1e-6)
        return ParamSpec(name, kind, unit, False, 3.0 / q, -10.0 / q, 100.0 / q)
    ref = 1.0 if reference is None else float(reference)
    if ref > 0:
        return ParamSpec(name, kind, unit, True, ref, ref * 1e-3, ref * 1e3)
    width = 10.0 * abs(ref) + 1e-3
    return ParamSpec(name, kind, unit, False, ref, ref - width, ref + width)


# --------------------------------------------------------------------------------------------------- forms
def chebyshev_nodes(n: int) -> np.ndarray:
    """``n`` Chebyshev–Lobatto nodes on [0, 1] (ends included, so the end values are parameters)."""
    return 0.5 - 0.5 * np.cos(np.pi * np.arange(n) / (n - 1))


class Form:
    """How one parameter's SOC dependence is represented by θ entries."""

    kind = ""
    size = 1

    def labels(self, name: str) -> list[str]:
        return [name]

    def theta0(self, spec: ParamSpec) -> np.ndarray:
        return np.full(self.size, spec.to_theta(spec.init))

    def function(self, spec: ParamSpec, theta):
        raise NotImplementedError

    def node_soc(self) -> np.ndarray:
        return np.array([0.5])


class ConstantForm(Form):
    kind = "constant"
    size = 1

    def function(self, spec, theta):
        v = spec.from_theta(np.asarray(theta)[..., 0])
        return Constant(float(v) if np.ndim(v) == 0 else v)


class PolyForm(Form):
    """Values at Chebyshev nodes → monomial coefficients, highest degree first (Table 3 order)."""

    kind = "poly"
    #: SOC spacing of the lookup that stores a polynomial fitted on a partial domain (clamped outside it)
    CLAMP_STEP = 0.01
    #: points of the grid on which a positive parameter's polynomial is held above its floor between its nodes
    GRID_POINTS = 401

    def __init__(self, degree: int = POLY_DEGREE, domain: tuple = (0.0, 1.0)):
        self.degree = degree
        self.size = degree + 1
        self.domain = (float(domain[0]), float(domain[1]))
        lo, hi = self.domain
        self.nodes = lo + (hi - lo) * chebyshev_nodes(self.size)
        vander = np.vander(self.nodes, self.size)  # columns z^d … z^0
        self._to_coeffs = np.linalg.inv(vander)  # coeffs = inv(V) @ values
        #: ``(size, G)``: node values ``(…, size)`` @ this = the polynomial on :data:`GRID_POINTS` SOC points spread
        #: evenly over the domain, ends included (built once: the positivity residuals use it at every evaluation)
        self.grid_matrix = (np.vander(np.linspace(lo, hi, self.GRID_POINTS), self.size) @ self._to_coeffs).T

    @property
    def partial(self) -> bool:
        """Whether the nodes cover less than [0, 1] (the stored function is then clamped to the domain)."""
        return self.domain != (0.0, 1.0)

    def clamped(self, spec, theta):
        """The fitted function as stored: the polynomial itself on [0, 1], else a lookup on the domain that holds its
        end values outside (no extrapolation of a 6th-degree polynomial)."""
        poly = self.function(spec, theta)
        if not self.partial:
            return poly
        lo, hi = self.domain
        grid = np.unique(np.r_[np.arange(lo, hi, self.CLAMP_STEP), hi])
        return Lookup(tuple(grid), tuple(poly(grid)))

    def labels(self, name):
        return [f"{name}@z={z:.3f}" for z in self.nodes]

    def node_soc(self):
        return self.nodes

    def function(self, spec, theta):
        vals = spec.from_theta(np.asarray(theta, dtype=float))
        coeffs = vals @ self._to_coeffs.T
        return Polynomial(tuple(coeffs) if coeffs.ndim == 1 else coeffs)


class LookupForm(Form):
    kind = "lookup"

    def __init__(self, knots):
        self.knots = np.asarray(sorted(set(float(k) for k in knots)))
        self.size = self.knots.size

    def labels(self, name):
        return [f"{name}@z={z:.3f}" for z in self.knots]

    def node_soc(self):
        return self.knots

    def function(self, spec, theta):
        vals = spec.from_theta(np.asarray(theta, dtype=float))
        return Lookup(tuple(self.knots), tuple(vals) if vals.ndim == 1 else vals)
