"""The compiled interpreter of lowered models: ``model_step`` and ``model_output`` with their Jacobians, one point.

Every function here evaluates one point (one run, sigma point or particle) and mirrors its numpy original operation
for operation, so the two agree to rounding (the tests hold them to 1e-9 on every model and effect):

* SOC functions (:mod:`socbench.models.params`): ``plain_fn`` (Constant, Polynomial — Horner on ``clip(z, 0, 1)``,
  derivative 0 outside —, Lookup — ``np.interp``'s rule, or the parameter-batch formula), ``soc_fn`` (adds
  TemperatureTable: linear or log-linear between the nodes, the node's own numbers at a node, held outside);
* OCV curves (:mod:`socbench.ocv`): ``ocv_eval`` (PCHIP segments and the end rule; TemperatureOCV blending);
* the building blocks of :mod:`socbench.models.blocks`, once each: B1 ``soc_step``, B2 ``rc_coef``, B3 (inline, two
  lines), B4 ``lowpass_coef``, B5 ``coupled_rc`` (with ``phi_functions``), B6 ``guarded_inv/log/log1m``,
  ``clipped_exp``, and the robust floor ``floor0``;
* one step/output pair per model family (the families of ``lowering.FAMILIES``), written with those blocks;
* the :class:`~socbench.models.effects.AugmentedModel` composition with the eight effects (``model_step``,
  ``model_output``), following the module docstring of :mod:`socbench.models.effects`.

Conventions: ``x`` the full state vector of the point (base states first), ``temp`` the cell temperature and
``has_temp`` whether the record has one (``False``: the numpy code's ``temp=None``: parameter tables and OCV curves at
``T_REF_C``, the temperature effect at its ``t_ref``); ``jac`` asks for ``F, B`` / ``H, D``. ``step`` writes ``xn``
(and ``F (n, n)``, ``B (n,)``), ``output`` writes ``H (n,)`` and returns ``(y, D, status)``; both use ``work``
(:data:`WORK_SIZE` floats of scratch: the parameters of the point, B5's matrices). ``status`` is 0, or 1 where
the numpy model would raise (e.g. improved_rc with ``R1 + R2 ≤ 0``): the caller then hands the work back to numpy.
"""

from __future__ import annotations

import math

import numpy as np
from numba.core import types
from numba.extending import intrinsic

from ..models.blocks import C_FLOOR, EPS_SINGULAR, EXP_CLIP, R_FLOOR, TAU_ALGEBRAIC
from ..models.effects import FARADAY, KELVIN, R_GAS
from ..ocv import T_REF_C
from .jit import kernel
from .lowering import (
    EFFECT_WIDTH,
    F_CAP,
    F_ETA,
    FN_CONST,
    FN_POLY,
    FN_TABLE,
    H_BIAS,
    H_EFFECTS,
    H_FAMILY,
    H_FLAGS,
    H_N,
    H_NB,
    H_NEFF,
    H_OCV,
    H_OUT0,
    H_OUT1,
    H_PARAMS,
    H_STEP0,
    H_STEP1,
    H_SUB,
    MAX_PARAMS,
    OCV_PCHIP,
    RC_C0_PRINTED,
    RC_INTEGRATOR,
)

#: scratch of model_step/model_output: B5's 12 numbers, then the parameter values and z-derivatives
W_VAL = 16
W_DER = W_VAL + MAX_PARAMS
WORK_SIZE = W_DER + MAX_PARAMS
#: 1/n!, n = 0 … 12 (the series of the φ functions of B5; the same numbers as blocks._INV_FACT)
INV_FACT = 1.0 / np.cumprod(np.r_[1.0, np.arange(1.0, 13.0)])
PHI_SERIES_BELOW = 0.1
PHI_TERMS = 10


# ================================================================================================ memory
@intrinsic
def ptr(typingctx, arr):
    """The data pointer of a C-contiguous array (the array must outlive every use of the pointer).

    Every compiled function below takes pointers, not arrays: numba passes an array as a struct of 7–9 words and
    reference-counts it on each call LLVM does not inline (~30 ns per call with two arrays), a pointer is one word
    (~4 ns per call). 2-D operands (``F``, covariances) are row-major ``n × n`` behind their pointer.
    """
    def codegen(context, builder, sig, args):
        return context.make_array(sig.args[0])(context, builder, args[0]).data

    return types.CPointer(arr.dtype)(arr), codegen


@intrinsic
def ptr_off(typingctx, p, k):
    """``p + k``: a pointer ``k`` elements further."""
    def codegen(context, builder, sig, args):
        return builder.gep(args[0], [args[1]])

    return p(p, k), codegen


@intrinsic
def keep_alive(typingctx, arrays):
    """Nothing, but a use of every array in the tuple ``arrays``: call it at the end of a kernel with the arrays it
    only reaches through :func:`ptr`. numba frees an array after its variable's last use, and a ``ptr(a)`` call is
    the last use of an array read through its pointer alone, so the array would be freed while the pointer is still
    written through (measured: a 1300-particle cloud's scratch, an ``mmap`` block, unmapped before the first write:
    a segfault; smaller blocks stay mapped in the heap and the writes went to freed memory)."""
    def codegen(context, builder, sig, args):
        return context.get_dummy_value()

    return types.none(arrays), codegen


@intrinsic
def ptr_at(typingctx, arr, k):
    """Pointer to element ``k`` (flat, C order) of a C-contiguous array."""
    def codegen(context, builder, sig, args):
        data = context.make_array(sig.args[0])(context, builder, args[0]).data
        return builder.gep(data, [args[1]])

    return types.CPointer(arr.dtype)(arr, k), codegen


# ================================================================================================ SOC functions
@kernel(inline=True)
def _count_le(fm, off, n, z):
    """``#{q < n : fm[off + q] ≤ z}`` for ascending ``fm[off:off+n]`` (``searchsorted(..., side="right")``)."""
    lo, hi = 0, n
    while lo < hi:
        mid = (lo + hi) >> 1
        if fm[off + mid] <= z:
            lo = mid + 1
        else:
            hi = mid
    return lo


@kernel(inline=True)
def _interp(fm, off, K, z):
    """``np.interp(z, xp, fp)`` with ``xp = fm[off:off+K]``, ``fp`` next, slopes after (numpy's rule, exactly)."""
    if z != z:
        return z
    xv, yv, sv = off, off + K, off + 2 * K
    if z < fm[xv]:
        return fm[yv]
    if z > fm[xv + K - 1]:
        return fm[yv + K - 1]
    j = _count_le(fm, xv, K, z) - 1
    if j == K - 1:
        return fm[yv + K - 1]
    if fm[xv + j] == z:
        return fm[yv + j]
    slope = fm[sv + j]
    v = slope * (z - fm[xv + j]) + fm[yv + j]
    if v != v:
        v = slope * (z - fm[xv + j + 1]) + fm[yv + j + 1]
        if v != v and fm[yv + j] == fm[yv + j + 1]:
            v = fm[yv + j]
    return v


@kernel(inline=True)
def unit_clip(z):
    """``clip(z, 0, 1)`` with NaN kept (a polynomial parameter is evaluated on the clipped SOC)."""
    if z < 0.0:
        return 0.0
    if z > 1.0:
        return 1.0
    return z


@kernel(inline=True)
def horner_step(v, d, z, c):
    """One Horner step of a polynomial's value and derivative together (params.Polynomial): ``(v z + c, d z + v)``.
    The one recurrence of a polynomial parameter, one point at a time (:func:`plain_fn`) or every point of a batch
    together (:func:`load_params`)."""
    return v * z + c, d * z + v


@kernel(inline=True)
def plain_fn(im, fm, rec, z):
    """``(p, dp/dz)`` of a Constant, Polynomial or Lookup record."""
    kind = im[rec]
    off = im[rec + 1]
    n = im[rec + 2]
    if kind == FN_CONST:
        return fm[off], 0.0
    if kind == FN_POLY:
        zp = unit_clip(z)
        v = fm[off]
        d = 0.0
        for j in range(1, n):
            v, d = horner_step(v, d, zp, fm[off + j])
        return v, (0.0 if z < 0.0 or z > 1.0 else d)
    # FN_LOOKUP: piecewise linear, flat outside
    K = n
    j = _count_le(fm, off, K, z) - 1
    if j < 0:
        j = 0
    elif j > K - 2:
        j = K - 2
    outside = z < fm[off] or z > fm[off + K - 1]
    s = fm[off + 2 * K + j]
    if im[rec + 3] == 0:
        v = _interp(fm, off, K, z)
    else:  # a parameter batch: params.Lookup's batched formula on the clipped SOC
        zc = z
        if z < fm[off]:
            zc = fm[off]
        elif z > fm[off + K - 1]:
            zc = fm[off + K - 1]
        v = fm[off + K + j] + s * (zc - fm[off + j])
    return v, (0.0 if outside else s)


@kernel(inline=True)
def temperature_weight(fm, off, K, t):
    """``(k, w)`` of params.temperature_weights for the K temperatures at ``fm[off:]`` (``t`` the cell temperature,
    T_REF_C for a record without one)."""
    k = _count_le(fm, off, K, t) - 1
    if k < 0:
        k = 0
    elif k > K - 2:
        k = K - 2
    lo = fm[off + k]
    w = (t - lo) / (fm[off + k + 1] - lo)
    if w < 0.0:
        w = 0.0
    elif w > 1.0:
        w = 1.0
    return k, w


@kernel(inline=True)
def table_nodes(im, fm, rec, t):
    """The temperature blend of every table (parameter tables and OCV curves alike, as params.temperature_weights
    serves both in numpy): ``(lower node's record, upper node's record, w)`` of the table record ``rec`` at cell
    temperature ``t``; a one-node table gives ``(node, node, 0)``."""
    K = im[rec + 2]
    if K == 1:
        return im[rec + 4], im[rec + 4], 0.0
    k, w = temperature_weight(fm, im[rec + 1], K, t)
    return im[rec + 4 + k], im[rec + 5 + k], w


@kernel(inline=True)
def linear_blend(w, lv, ld, hv, hd):
    """``(1 − w)·lo + w·hi`` of a value and its derivative; at a node (``w`` 0 or 1) that node's own numbers."""
    if w == 0.0:
        return lv, ld
    if w == 1.0:
        return hv, hd
    return (1.0 - w) * lv + w * hv, (1.0 - w) * ld + w * hd


@kernel(inline=True)
def soc_fn(im, fm, rec, z, t):
    """``(p, dp/dz)`` of any function record at SOC ``z`` and cell temperature ``t``."""
    if im[rec] != FN_TABLE:
        return plain_fn(im, fm, rec, z)
    lo, hi, w = table_nodes(im, fm, rec, t)
    lv, ld = plain_fn(im, fm, lo, z)
    if w == 0.0:
        return lv, ld
    hv, hd = plain_fn(im, fm, hi, z)
    if im[rec + 3] == 0 or w == 1.0:
        return linear_blend(w, lv, ld, hv, hd)
    v = math.exp((1.0 - w) * math.log(lv) + w * math.log(hv))  # the log scale (params.TemperatureTable)
    return v, v * ((1.0 - w) * ld / lv + w * hd / hv)


# ================================================================================================ OCV
@kernel(inline=True)
def _pchip(im, fm, rec, z):
    off = im[rec + 1]
    m = im[rec + 2]
    j = _count_le(fm, off + 1, m - 2, z)  # segment: interior breakpoints at or below z
    s = z - fm[off + j]
    c = off + m + 4 * j
    v = ((fm[c] * s + fm[c + 1]) * s + fm[c + 2]) * s + fm[c + 3]
    dv = (3.0 * fm[c] * s + 2.0 * fm[c + 1]) * s + fm[c + 2]
    e = off + m + 4 * (m - 1)  # U(z_lo), U(z_hi), U'(z_lo), U'(z_hi), extension limit
    z_lo = fm[off]
    z_hi = fm[off + m - 1]
    limit = fm[e + 4]
    if z < z_lo:
        d = z - z_lo
        if d < -limit:
            d = -limit
        v = fm[e] + fm[e + 2] * d
        dv = 0.0 if z < z_lo - limit else fm[e + 2]
    elif z > z_hi:
        d = z - z_hi
        if d > limit:
            d = limit
        v = fm[e + 1] + fm[e + 3] * d
        dv = 0.0 if z > z_hi + limit else fm[e + 3]
    return v, dv


@kernel(inline=True)
def ocv_eval(im, fm, z, t):
    """``(U_oc(z, t), dU_oc/dz)`` of the model's OCV record."""
    rec = im[H_OCV]
    if im[rec] == OCV_PCHIP:
        return _pchip(im, fm, rec, z)
    lo, hi, w = table_nodes(im, fm, rec, t)
    v0, d0 = _pchip(im, fm, lo, z)
    if w == 0.0:
        return v0, d0
    v1, d1 = _pchip(im, fm, hi, z)
    return linear_blend(w, v0, d0, v1, d1)


# ================================================================================================ blocks B1–B6
@kernel(inline=True)
def soc_step(z, i, dt, cap, eta_c):
    """B1 ``(z⁺, ∂z⁺/∂I)``."""
    k = (1.0 if i >= 0.0 else eta_c) * dt / (3600.0 * cap)
    return z - k * i, -k


@kernel(inline=True)
def floor0(p, dp, lower):
    """Robust floor ``max(p, lower)``, derivative 0 where floored."""
    if p < lower:
        return lower, 0.0
    return p, dp


@kernel(inline=True)
def rc_coef(R, dR, C, dC, dt, jac):
    """B2 ``(a, b, a_z, b_z)`` of one branch, robust mode (R floored at 0, C at C_FLOOR where τ ≤ 0); ``a_z = b_z = 0``
    unless ``jac``."""
    if R < 0.0 or C <= 0.0:
        if R < 0.0:
            R = R_FLOOR
            dR = 0.0
        if C < C_FLOOR:
            C = C_FLOOR
            dC = 0.0
    tau = R * C
    if tau < TAU_ALGEBRAIC * dt:
        return 0.0, R, 0.0, dR
    em = math.expm1(-dt / tau)
    a = em + 1.0
    if not jac:
        return a, -R * em, 0.0, 0.0
    a_z = a * dt * (dR * C + R * dC) / (tau * tau)
    return a, -R * em, a_z, dR * (1.0 - a) - R * a_z


@kernel(inline=True)
def lowpass_coef(tc, dtc, dt):
    """B4 ``(a_f, ∂a_f/∂z)``."""
    a = math.exp(-dt / tc)
    return a, a * dt * dtc / (tc * tc)


@kernel(inline=True)
def _clip_singular(z):
    zs = z
    if z < EPS_SINGULAR:
        zs = EPS_SINGULAR
    elif z > 1.0 - EPS_SINGULAR:
        zs = 1.0 - EPS_SINGULAR
    return zs, (z > EPS_SINGULAR and z < 1.0 - EPS_SINGULAR)


@kernel(inline=True)
def guarded_inv(z):
    """B6 ``(1/z_s, d/dz)``."""
    zs, inside = _clip_singular(z)
    return 1.0 / zs, (-1.0 / (zs * zs) if inside else 0.0)


@kernel(inline=True)
def guarded_log(z):
    zs, inside = _clip_singular(z)
    return math.log(zs), (1.0 / zs if inside else 0.0)


@kernel(inline=True)
def guarded_log1m(z):
    zs, inside = _clip_singular(z)
    return math.log1p(-zs), (-1.0 / (1.0 - zs) if inside else 0.0)


@kernel(inline=True)
def floored_log(a):
    """B6 ``(ln max(a, ε), d/da)``, derivative 0 where floored (blocks.floored_log; NaN is floored, as there)."""
    if a > EPS_SINGULAR:
        return math.log(a), 1.0 / a
    return math.log(EPS_SINGULAR), 0.0


@kernel(inline=True)
def clipped_exp(arg):
    c = arg
    if arg < -EXP_CLIP:
        c = -EXP_CLIP
    elif arg > EXP_CLIP:
        c = EXP_CLIP
    e = math.exp(c)
    return e, (e if c == arg else 0.0)


@kernel(inline=True)
def sign(v):
    if v > 0.0:
        return 1.0
    if v < 0.0:
        return -1.0
    return v  # 0 (keeps its sign bit, as np.sign) or NaN


@kernel(inline=True)
def phi_functions(x):
    """B5's ``e1, e2, e1', e2'`` (series below |x| = 0.1, closed forms above; blocks._phi_functions)."""
    if abs(x) < PHI_SERIES_BELOW:
        e1 = 0.0
        e2 = 0.0
        d1 = 0.0
        d2 = 0.0
        for k in range(PHI_TERMS, -1, -1):
            e1 = e1 * x + INV_FACT[k + 1]
            e2 = e2 * x + INV_FACT[k + 2]
            if k >= 1:
                d1 = d1 * x + k * INV_FACT[k + 1]
                d2 = d2 * x + k * INV_FACT[k + 2]
        return e1, e2, d1, d2
    em = math.expm1(x)
    x2 = x * x
    return em / x, (em - x) / x2, (x * (em + 1.0) - em) / x2, (x * em - 2.0 * (em - x)) / math.pow(x, 3.0)


@kernel
def coupled_rc(Re, dRe, Rc, dRc, Ce, dCe, Cc, dCc, dt, out):
    """B5: ``out[0:4] = Φ`` (row-major), ``out[4:6] = Γ``, ``out[6:10] = Φ'``, ``out[10:12] = Γ'``; returns λ."""
    Rs = Re + Rc
    dRs = dRe + dRc
    al = 1.0 / Ce
    be = 1.0 / Cc
    lam = -(al + be) / Rs
    A00 = -al / Rs
    A01 = al / Rs
    A10 = be / Rs
    A11 = -be / Rs
    B0 = -(Rc * al) / Rs
    B1 = -(Re * be) / Rs
    e1, e2, d1, d2 = phi_functions(lam * dt)
    phi1 = dt * e1
    phi2 = dt * dt * e2
    out[0] = 1.0 + phi1 * A00
    out[1] = 0.0 + phi1 * A01
    out[2] = 0.0 + phi1 * A10
    out[3] = 1.0 + phi1 * A11
    G00 = dt + phi2 * A00
    G01 = 0.0 + phi2 * A01
    G10 = 0.0 + phi2 * A10
    G11 = dt + phi2 * A11
    out[4] = G00 * B0 + G01 * B1
    out[5] = G10 * B0 + G11 * B1
    dal = -dCe / (Ce * Ce)
    dbe = -dCc / (Cc * Cc)
    dlam = -(dal + dbe) / Rs - lam * dRs / Rs
    r = -(dRs / Rs)
    dA00 = r * A00 + (-dal) / Rs
    dA01 = r * A01 + dal / Rs
    dA10 = r * A10 + dbe / Rs
    dA11 = r * A11 + (-dbe) / Rs
    dB0 = r * B0 - (dRc * al + Rc * dal) / Rs
    dB1 = r * B1 - (dRe * be + Re * dbe) / Rs
    q1 = dt * dt * d1 * dlam
    q2 = math.pow(dt, 3.0) * d2 * dlam
    out[6] = phi1 * dA00 + q1 * A00
    out[7] = phi1 * dA01 + q1 * A01
    out[8] = phi1 * dA10 + q1 * A10
    out[9] = phi1 * dA11 + q1 * A11
    dG00 = phi2 * dA00 + q2 * A00
    dG01 = phi2 * dA01 + q2 * A01
    dG10 = phi2 * dA10 + q2 * A10
    dG11 = phi2 * dA11 + q2 * A11
    out[10] = (G00 * dB0 + G01 * dB1) + (dG00 * B0 + dG01 * B1)
    out[11] = (G10 * dB0 + G11 * dB1) + (dG10 * B0 + dG11 * B1)
    return lam


# ================================================================================================ families
# Each family's step and output read their parameters from ``work``: model_step and model_output evaluate the range
# the family declared (KernelSpec.step / .output) once, in one loop (one call site of soc_fn), before calling it.
@kernel(inline=True)
def load_params(im, fm, z, t, j0, j1, work):
    """Parameters ``j0 … j1 − 1`` of the family's list at ``(z, t)`` for one point: values into ``work[W_VAL + j]``,
    z-derivatives into ``work[W_DER + j]``, where the families read them."""
    pl = im[H_PARAMS]
    for j in range(j0, j1):
        v, d = soc_fn(im, fm, im[pl + j], z, t)
        work[W_VAL + j] = v
        work[W_DER + j] = d


@kernel
def load_params_points(im, fm, X, ld, npts, t, j0, j1, PV, ZP):
    """:func:`load_params` for the SOC ``X[p·ld]`` of each point ``p < npts``: the value of parameter ``j`` at point
    ``p`` into ``PV[j·npts + p]``, its z-derivative into ``PV[(MAX_PARAMS + j)·npts + p]`` (``ZP``: ``npts`` floats of
    scratch).

    Polynomials (the common form) run with the points innermost: one Horner step (:func:`horner_step`) for every
    point, then the next, over contiguous memory (SIMD, and no chain of dependent multiply-adds per point); the
    other forms point by point (:func:`soc_fn`).
    """
    pl = im[H_PARAMS]
    for p in range(npts):
        ZP[p] = unit_clip(X[p * ld])
    for j in range(j0, j1):
        rec = im[pl + j]
        V = j * npts
        Dv = (MAX_PARAMS + j) * npts
        if im[rec] == FN_POLY:
            off = im[rec + 1]
            c0 = fm[off]
            for p in range(npts):
                PV[V + p] = c0
                PV[Dv + p] = 0.0
            for q in range(1, im[rec + 2]):
                c = fm[off + q]
                for p in range(npts):
                    PV[V + p], PV[Dv + p] = horner_step(PV[V + p], PV[Dv + p], ZP[p], c)
            for p in range(npts):
                z = X[p * ld]
                if z < 0.0 or z > 1.0:
                    PV[Dv + p] = 0.0
        else:
            for p in range(npts):
                v, d = soc_fn(im, fm, rec, X[p * ld], t)
                PV[V + p] = v
                PV[Dv + p] = d


# ---------------------------------------------------------------------------------------- rc_network (rc_network.py)
# parameters [R0, R1 … Rn, C1 … Cn, (C0)]: output reads 0, step the rest
@kernel
def _rc_step(im, fm, x, i, dt, t, jac, xn, F, B, work):
    nn = im[H_N]  # row length of F
    n = im[H_SUB]
    flags = im[H_FLAGS]
    first = 1
    if flags & RC_INTEGRATOR:
        first = 2
        g = 0.0
        g_z = 0.0
        if flags & RC_C0_PRINTED:
            c0 = work[W_VAL + 1 + 2 * n]
            g = dt / c0
            g_z = -dt * work[W_DER + 1 + 2 * n] / (c0 * c0)
            if math.isinf(c0):
                g_z = 0.0
        xn[1] = x[1] + g * i
        if jac:
            F[1 * nn + 0] = g_z * i
            F[1 * nn + 1] = 1.0
            B[1] = g
    for j in range(n):
        a, b, a_z, b_z = rc_coef(work[W_VAL + 1 + j], work[W_DER + 1 + j], work[W_VAL + 1 + n + j],
                                 work[W_DER + 1 + n + j], dt, jac)
        c = first + j
        u = x[c]
        xn[c] = a * u + b * i
        if jac:
            F[c * nn + 0] = a_z * u + b_z * i
            F[c * nn + c] = a
            B[c] = b
    return 0


@kernel
def _rc_output(im, fm, x, i, u, du, t, jac, H, work):
    nb = im[H_NB]
    r0, dr0 = floor0(work[W_VAL], work[W_DER], R_FLOOR)
    pol = 0.0
    if nb > 1:
        pol = x[1]
        for c in range(2, nb):
            pol += x[c]
    if jac:
        H[0] = du - dr0 * i
        for c in range(1, nb):
            H[c] = -1.0
    return u - r0 * i - pol, -r0, 0


# ---------------------------------------------------------------------------------------- improved_rc
# parameters [R0, R1 (R_c), R2 (R_e), C1 (C_c), C2 (C_e)]: output reads 0 … 2, step 1 … 4
@kernel
def _irc_step(im, fm, x, i, dt, t, jac, xn, F, B, work):
    nn = im[H_N]  # row length of F
    rc = work[W_VAL + 1]
    re = work[W_VAL + 2]
    if re + rc <= 0.0:
        return 1  # ImprovedRC._network raises
    cc, dcc = floor0(work[W_VAL + 3], work[W_DER + 3], C_FLOOR)
    ce, dce = floor0(work[W_VAL + 4], work[W_DER + 4], C_FLOOR)
    coupled_rc(re, work[W_DER + 2], rc, work[W_DER + 1], ce, dce, cc, dcc, dt, work)
    w0 = x[1]
    w1 = x[2]
    xn[1] = (work[0] * w0 + work[1] * w1) + work[4] * i
    xn[2] = (work[2] * w0 + work[3] * w1) + work[5] * i
    if jac:
        F[1 * nn + 0] = (work[6] * w0 + work[7] * w1) + work[10] * i
        F[2 * nn + 0] = (work[8] * w0 + work[9] * w1) + work[11] * i
        F[1 * nn + 1] = work[0]
        F[1 * nn + 2] = work[1]
        F[2 * nn + 1] = work[2]
        F[2 * nn + 2] = work[3]
        B[1] = work[4]
        B[2] = work[5]
    return 0


@kernel
def _irc_output(im, fm, x, i, u, du, t, jac, H, work):
    ue = x[1]
    uc = x[2]
    r0, dr0 = floor0(work[W_VAL], work[W_DER], R_FLOOR)
    rc = work[W_VAL + 1]
    drc = work[W_DER + 1]
    re = work[W_VAL + 2]
    dre = work[W_DER + 2]
    rs = re + rc
    drs = dre + drc
    num = rc * ue + re * uc
    par = re * rc / rs
    y = u + num / rs - par * i - r0 * i
    if jac:
        dpar = (dre * rc + re * drc) / rs - re * rc * drs / (rs * rs)
        H[0] = du - dr0 * i + (drc * ue + dre * uc) / rs - num * drs / (rs * rs) - dpar * i
        H[1] = rc / rs
        H[2] = re / rs
    return y, -par - r0, 0


# ---------------------------------------------------------------------------------------- static_terms
@kernel(inline=True)
def _exponential_zone(a, da, b, db, z, q):
    """Tremblay's ``A e^{−B Q (1 − z)}`` and its total z-derivative (static_terms.exponential_zone)."""
    e, de = clipped_exp(-b * q * (1.0 - z))
    return a * e, da * e + a * de * (b * q - db * q * (1.0 - z))


@kernel
def _static_term(im, fm, z, work):
    """``(g, dg/dz)`` of the static-term model ``sub``; parameters [R0, then the model's own in param_names
    order] already in ``work``."""
    sub = im[H_SUB]
    v = W_VAL
    d = W_DER
    if sub == 1:  # shepherd: −K/z_s
        k = work[v + 1]
        inv, dinv = guarded_inv(z)
        return -k * inv, -work[d + 1] * inv - k * dinv
    if sub == 2:  # unnewehr: −K z
        k = work[v + 1]
        return -k * z, -k - work[d + 1] * z
    if sub == 3:  # nernst: −K0 ln z_s + K1 ln(1 − z_s)
        k0 = work[v + 1]
        k1 = work[v + 2]
        lz, dlz = guarded_log(z)
        l1z, dl1z = guarded_log1m(z)
        return -k0 * lz + k1 * l1z, -work[d + 1] * lz - k0 * dlz + work[d + 2] * l1z + k1 * dl1z
    if sub == 4:  # fang: −K0 ln(τ1 + z) + K1 ln(τ2 + 1 − z), arguments floored at ε
        k0 = work[v + 1]
        k1 = work[v + 2]
        la, dla = floored_log(work[v + 3] + z)
        lb, dlb = floored_log(work[v + 4] + 1.0 - z)
        return (-k0 * la + k1 * lb,
                -work[d + 1] * la - k0 * (work[d + 3] + 1.0) * dla + work[d + 2] * lb + k1 * (work[d + 4] - 1.0) * dlb)
    if sub == 5:  # tremblay1: −K/z_s + A e^{−B Q (1 − z)}
        k = work[v + 1]
        inv, dinv = guarded_inv(z)
        ex, dex = _exponential_zone(work[v + 2], work[d + 2], work[v + 3], work[d + 3], z, fm[F_CAP])
        return -k * inv + ex, -work[d + 1] * inv - k * dinv + dex
    # plett: K0 − K1/z_s − K2 z + K3 ln z_s + K4 ln(1 − z_s)
    k0 = work[v + 1]
    k1 = work[v + 2]
    k2 = work[v + 3]
    k3 = work[v + 4]
    k4 = work[v + 5]
    inv, dinv = guarded_inv(z)
    lz, dlz = guarded_log(z)
    l1z, dl1z = guarded_log1m(z)
    g = k0 - k1 * inv - k2 * z + k3 * lz + k4 * l1z
    dg = (work[d + 1] - work[d + 2] * inv - k1 * dinv - work[d + 3] * z - k2 + work[d + 4] * lz + k3 * dlz
          + work[d + 5] * l1z + k4 * dl1z)
    return g, dg


@kernel
def _static_output(im, fm, x, i, u, du, t, jac, H, work):
    z = x[0]
    r0, dr0 = floor0(work[W_VAL], work[W_DER], R_FLOOR)
    g, dg = _static_term(im, fm, z, work)
    if jac:
        H[0] = du + dg - dr0 * i
    return u + g - r0 * i, -r0, 0


# ---------------------------------------------------------------------------------------- tremblay (liu, tremblay2)
# parameters [tc, K, A, B, R0]: step reads 0, output 1 … 4
@kernel
def _tremblay_step(im, fm, x, i, dt, t, jac, xn, F, B, work):
    nn = im[H_N]  # row length of F
    a, a_z = lowpass_coef(work[W_VAL], work[W_DER], dt)
    istar = x[1]
    xn[1] = a * istar + (1.0 - a) * i
    if jac:
        F[1 * nn + 0] = a_z * (istar - i)
        F[1 * nn + 1] = a
        B[1] = 1.0 - a
    return 0


@kernel
def _tremblay_output(im, fm, x, i, u, du, t, jac, H, work):
    z = x[0]
    istar = x[1]
    q = fm[F_CAP]
    r0, dr0 = floor0(work[W_VAL + 4], work[W_DER + 4], R_FLOOR)
    k = work[W_VAL + 1]
    dk = work[W_DER + 1]
    inv, dinv = guarded_inv(z)
    it_term = -k * q * (1.0 - z) * inv
    d_it = -dk * q * (1.0 - z) * inv + k * q * inv - k * q * (1.0 - z) * dinv
    w = 1.1 - z
    wc = w if w > EPS_SINGULAR else EPS_SINGULAR
    if istar < 0.0:  # charge: 1/(1.1 − z), guarded
        g_star = 1.0 / wc
        dg_star = 1.0 / (wc * wc) if w > EPS_SINGULAR else 0.0
    else:
        g_star = inv
        dg_star = dinv
    ex, dex = _exponential_zone(work[W_VAL + 2], work[W_DER + 2], work[W_VAL + 3], work[W_DER + 3], z, q)
    y = u + it_term - k * g_star * istar + ex - r0 * i
    if jac:
        H[0] = du + d_it - (dk * g_star + k * dg_star) * istar + dex - dr0 * i
        H[1] = -k * g_star
    return y, -r0, 0


# ---------------------------------------------------------------------------------------- esc
# parameters [R0, R1 … Rn, M, M0, tau1 … taun, gamma]: output reads 0 … n + 2, step n + 3 … 2n + 3
@kernel
def _esc_step(im, fm, x, i, dt, t, jac, xn, F, B, work):
    nn = im[H_N]  # row length of F
    n = im[H_SUB]
    cap = fm[F_CAP]
    for j in range(1, n + 1):
        a, a_z = lowpass_coef(work[W_VAL + n + 2 + j], work[W_DER + n + 2 + j], dt)
        xn[j] = a * x[j] + (1.0 - a) * i
        if jac:
            F[j * nn + 0] = a_z * (x[j] - i)
            F[j * nn + j] = a
            B[j] = 1.0 - a
    g = work[W_VAL + 2 * n + 3]
    dg = work[W_DER + 2 * n + 3]
    c = (1.0 if i >= 0.0 else fm[F_ETA]) / (3600.0 * cap)
    rate = c * i * g
    u = rate * dt
    ah = math.exp(-abs(u))
    sg = sign(i)
    jh = n + 1
    js = n + 2
    h = x[jh]
    xn[jh] = ah * h - (1.0 - ah) * sg
    moving = abs(i) > cap / 100.0
    xn[js] = sg if moving else x[js]
    if jac:
        dah_du = -ah * sign(u)
        F[jh * nn + 0] = dah_du * (c * i * dg) * dt * (h + sg)
        F[jh * nn + jh] = ah
        F[js * nn + js] = 0.0 if moving else 1.0
        B[jh] = dah_du * (c * g) * dt * (h + sg)
    return 0


@kernel
def _esc_output(im, fm, x, i, u, du, t, jac, H, work):
    n = im[H_SUB]
    h = x[n + 1]
    moving = abs(i) > fm[F_CAP] / 100.0
    s = sign(i) if moving else x[n + 2]
    r0, dr0 = floor0(work[W_VAL], work[W_DER], R_FLOOR)
    m = work[W_VAL + n + 1]
    m0 = work[W_VAL + n + 2]
    y = u + m0 * s + m * h - r0 * i
    dy_z = du + work[W_DER + n + 2] * s + work[W_DER + n + 1] * h - dr0 * i
    for j in range(1, n + 1):
        r = work[W_VAL + j]
        y = y - r * x[j]
        dy_z = dy_z - work[W_DER + j] * x[j]
        if jac:
            H[j] = -r
    if jac:
        H[0] = dy_z
        H[n + 1] = m
        H[n + 2] = 0.0 if moving else m0
    return y, -r0, 0


# ---------------------------------------------------------------------------------------- family dispatch
@kernel(inline=True)
def base_step(im, fm, x, i, dt, t, jac, xn, F, B, work):
    """The base model's step on ``x[:nb]``: B1 for the SOC, then the family's other states (``F, B`` pre-zeroed)."""
    nn = im[H_N]  # row length of F
    zn, dz_di = soc_step(x[0], i, dt, fm[F_CAP], fm[F_ETA])
    xn[0] = zn
    if jac:
        F[0 * nn + 0] = 1.0
        B[0] = dz_di
    fam = im[H_FAMILY]
    if fam == 1:
        return _rc_step(im, fm, x, i, dt, t, jac, xn, F, B, work)
    if fam == 2:
        return _irc_step(im, fm, x, i, dt, t, jac, xn, F, B, work)
    if fam == 4:
        return _tremblay_step(im, fm, x, i, dt, t, jac, xn, F, B, work)
    if fam == 5:
        return _esc_step(im, fm, x, i, dt, t, jac, xn, F, B, work)
    return 0  # static_terms: SOC only


@kernel(inline=True)
def base_output(im, fm, x, i, u, du, t, jac, H, work):
    """The base model's output with ``(u, du)`` its OCV and slope at ``x[0]``."""
    fam = im[H_FAMILY]
    if fam == 1:
        return _rc_output(im, fm, x, i, u, du, t, jac, H, work)
    if fam == 2:
        return _irc_output(im, fm, x, i, u, du, t, jac, H, work)
    if fam == 3:
        return _static_output(im, fm, x, i, u, du, t, jac, H, work)
    if fam == 4:
        return _tremblay_output(im, fm, x, i, u, du, t, jac, H, work)
    return _esc_output(im, fm, x, i, u, du, t, jac, H, work)


# ================================================================================================ effects
@kernel(inline=True)
def _effective_current(im, x, i):
    b = im[H_BIAS]
    return i - x[b] if b >= 0 else i


@kernel
def model_error_scale(fm, v, j, z, t):
    """``(s_j, ds_j/dz)`` of :meth:`~socbench.models.effects.ModelError.scale`: component ``j`` of the model-error
    effect whose values start at ``fm[v]`` (its ``kernel_values`` layout), bilinear in SOC and temperature, held
    outside both grids; the SOC derivative 0 outside the SOC grid."""
    KT = int(fm[v + 4])
    KZ = int(fm[v + 5])
    ot = v + 6
    oz = ot + KT
    g = oz + KZ + j * KT * KZ
    kz = _count_le(fm, oz, KZ, z) - 1
    hi_k = KZ - 2 if KZ > 1 else 0
    if kz < 0:
        kz = 0
    elif kz > hi_k:
        kz = hi_k
    width = 1.0
    wz = 0.0
    inside = False
    if KZ > 1:
        width = fm[oz + kz + 1] - fm[oz + kz]
        wz = (z - fm[oz + kz]) / width
        if wz < 0.0:
            wz = 0.0
        elif wz > 1.0:
            wz = 1.0
        inside = z >= fm[oz] and z <= fm[oz + KZ - 1]
    kt = 0
    wt = 0.0
    if KT > 1:
        kt, wt = temperature_weight(fm, ot, KT, t)
    kt1 = min(kt + 1, KT - 1)
    kz1 = min(kz + 1, KZ - 1)
    lo = (1.0 - wt) * fm[g + kt * KZ + kz] + wt * fm[g + kt1 * KZ + kz]
    hi = (1.0 - wt) * fm[g + kt * KZ + kz1] + wt * fm[g + kt1 * KZ + kz1]
    return (1.0 - wz) * lo + wz * hi, ((hi - lo) / width if inside else 0.0)


@kernel
def model_step(im, fm, x, i, dt, temp, has_temp, jac, xn, F, B, work):
    """``x⁺`` into ``xn`` (and ``F``, ``B`` when ``jac``) of any lowered model; returns the status (0: fine)."""
    t = temp if has_temp else T_REF_C
    load_params(im, fm, x[0], t, im[H_STEP0], im[H_STEP1], work)
    return step_loaded(im, fm, x, i, dt, temp, has_temp, jac, xn, F, B, work)


@kernel(inline=True)
def step_loaded(im, fm, x, i, dt, temp, has_temp, jac, xn, F, B, work):
    """:func:`model_step` with the step's parameters already in ``work`` (:func:`load_params`).

    With effects, the composition of :class:`~socbench.models.effects.AugmentedModel.step`: base step on the
    effective current, SOC gain and leak, the effects' own states, then ``∂/∂b = −∂/∂I`` for a current bias.
    """
    nn = im[H_N]  # row length of F
    t = temp if has_temp else T_REF_C
    n = im[H_N]
    if jac:
        for r in range(n):
            B[r] = 0.0
            for c in range(n):
                F[r * nn + c] = 0.0
    neff = im[H_NEFF]
    if neff == 0:
        return base_step(im, fm, x, i, dt, t, jac, xn, F, B, work)
    ie = _effective_current(im, x, i)
    st = base_step(im, fm, x, ie, dt, t, jac, xn, F, B, work)
    if st != 0:
        return st
    nb = im[H_NB]
    cap = fm[F_CAP]
    z = x[0]
    dz = xn[0] - z
    tab = im[H_EFFECTS]
    gain = 1.0
    for e in range(neff):  # SOC gains: capacity (state), coulombic efficiency
        code = im[tab + EFFECT_WIDTH * e]
        if code == 3:
            gain = gain * x[im[tab + EFFECT_WIDTH * e + 1]]
        elif code == 7:
            gain = gain * (fm[im[tab + EFFECT_WIDTH * e + 3]] if ie < 0.0 else 1.0)
    xn[0] = z + gain * dz
    leak_dz = 0.0
    for e in range(neff):  # leak: self discharge, U_oc at the reference temperature
        if im[tab + EFFECT_WIDTH * e] == 8:
            u, du = ocv_eval(im, fm, z, T_REF_C)
            c = fm[im[tab + EFFECT_WIDTH * e + 3]] * dt
            xn[0] -= c * u
            leak_dz = leak_dz + c * du
    if jac:
        for c in range(nb):
            F[0 * nn + c] = gain * F[0 * nn + c]
        F[0 * nn + 0] += 1.0 - gain - leak_dz
        B[0] = gain * B[0]
        for e in range(neff):
            if im[tab + EFFECT_WIDTH * e] == 3:  # ∂z⁺/∂cap = (gain of the others)·Δz
                col = im[tab + EFFECT_WIDTH * e + 1]
                g = x[col]
                others = gain / g if g != 0.0 else 0.0
                F[0 * nn + col] += others * dz * 1.0
    for e in range(neff):  # the effects' own states
        code = im[tab + EFFECT_WIDTH * e]
        s0 = im[tab + EFFECT_WIDTH * e + 1]
        v = im[tab + EFFECT_WIDTH * e + 3]
        if code == 2:  # hysteresis [M, M0, gamma, h_ref]
            h = x[s0]
            c = fm[v + 2] * (1.0 if ie >= 0.0 else fm[F_ETA]) / (3600.0 * cap)
            a = math.exp(-abs(ie * c * dt))
            sg = sign(ie)
            moving = abs(ie) > cap / 100.0
            xn[s0] = a * h - (1.0 - a) * sg
            xn[s0 + 1] = sg if moving else x[s0 + 1]
            if jac:
                F[s0 * nn + s0] = a
                F[(s0 + 1) * nn + (s0 + 1)] = 0.0 if moving else 1.0
                B[s0] = -a * c * dt * sg * (h + sg)
        elif code == 3 or code == 4 or code == 9:  # capacity, current bias, R0 offset: random walks
            xn[s0] = x[s0]
            if jac:
                F[s0 * nn + s0] = 1.0
        elif code == 5:  # extra RC [R, C]
            a, b, _, _ = rc_coef(fm[v], 0.0, fm[v + 1], 0.0, dt, jac)
            xn[s0] = a * x[s0] + b * ie
            if jac:
                F[s0 * nn + s0] = a
                B[s0] = b
        elif code == 10:  # model error: four Gauss–Markov states ε⁺ = e^{−dt/τ} ε [τ_slow, τ_fast, τ_r, τ_mid, …]
            for c in range(4):
                phi = math.exp(-dt / fm[v + c])
                xn[s0 + c] = phi * x[s0 + c]
                if jac:
                    F[(s0 + c) * nn + (s0 + c)] = phi
    b = im[H_BIAS]
    if jac and b >= 0:
        for r in range(n):
            F[r * nn + b] -= B[r]
    return 0


@kernel
def model_output(im, fm, x, i, temp, has_temp, jac, H, work):
    """``(y, D, status)`` of any lowered model, ``H`` filled when ``jac``."""
    t = temp if has_temp else T_REF_C
    load_params(im, fm, x[0], t, im[H_OUT0], im[H_OUT1], work)
    return output_loaded(im, fm, x, i, temp, has_temp, jac, H, work)


@kernel(inline=True)
def output_loaded(im, fm, x, i, temp, has_temp, jac, H, work):
    """:func:`model_output` with the output's parameters already in ``work`` (:func:`load_params`); the
    composition of AugmentedModel.output with effects."""
    t = temp if has_temp else T_REF_C
    u, du = ocv_eval(im, fm, x[0], t)
    neff = im[H_NEFF]
    if neff == 0:
        return base_output(im, fm, x, i, u, du, t, jac, H, work)
    n = im[H_N]
    if jac:
        for c in range(n):
            H[c] = 0.0
    ie = _effective_current(im, x, i)
    y, D, st = base_output(im, fm, x, ie, u, du, t, jac, H, work)
    if st != 0:
        return y, D, st
    nb = im[H_NB]
    cap = fm[F_CAP]
    tab = im[H_EFFECTS]
    k = 1.0  # the over-potential factor: the product of temperature's k(T) and capacity's 1 + g
    scaled = False
    for e in range(neff):
        code = im[tab + EFFECT_WIDTH * e]
        v = im[tab + EFFECT_WIDTH * e + 3]
        if code == 1:  # temperature [Ea, dUdT, t_ref]
            t_ref = fm[v + 2]
            tk = (temp if has_temp else t_ref) + KELVIN
            k = k * math.exp(fm[v] / R_GAS * (1.0 / tk - 1.0 / (t_ref + KELVIN)))
            scaled = True
        elif code == 3 and fm[v] != 0.0:  # capacity [r_growth]: a fade alone leaves the output as it is
            k = k * (1.0 + fm[v])
            scaled = True
    if scaled:  # y = U + K·(h_base − U)
        y = u + k * (y - u)
        D = k * D  # D is returned with or without the Jacobians (the particle filter's R reads it)
        if jac:
            for c in range(nb):
                H[c] = k * H[c]
            H[0] += (1.0 - k) * du
    for e in range(neff):  # additive terms
        code = im[tab + EFFECT_WIDTH * e]
        s0 = im[tab + EFFECT_WIDTH * e + 1]
        v = im[tab + EFFECT_WIDTH * e + 3]
        if code == 1:  # temperature's entropic term
            t_ref = fm[v + 2]
            tk = (temp if has_temp else t_ref) + KELVIN
            y = y + fm[v + 1] * (tk - KELVIN - t_ref)
        elif code == 2:  # hysteresis [M, M0, gamma, h_ref]
            moving = abs(ie) > cap / 100.0
            s = sign(ie) if moving else x[s0 + 1]
            y = y + (fm[v] * (x[s0] - fm[v + 3]) + fm[v + 1] * (s + fm[v + 3]))
            if jac:
                H[s0] += fm[v]
                H[s0 + 1] += 0.0 if moving else fm[v + 1]
        elif code == 5:  # extra RC
            y = y + -x[s0]
            if jac:
                H[s0] += -1.0
        elif code == 9:  # r0_offset: −ΔR0·I
            y = y + -x[s0] * ie
            D = D + -x[s0] * 1.0
            if jac:
                H[s0] += -ie
        elif code == 10:  # model error: s_slow (ε_slow + ε_mid) + s_fast ε_fast − s_r ε_r I
            z = x[0]
            s1, d1 = model_error_scale(fm, v, 0, z, t)
            s2, d2 = model_error_scale(fm, v, 1, z, t)
            s3, d3 = model_error_scale(fm, v, 2, z, t)
            slow = x[s0] + x[s0 + 3]
            y = y + (s1 * slow + s2 * x[s0 + 1] - s3 * x[s0 + 2] * ie)
            D = D + -s3 * x[s0 + 2]
            if jac:
                H[s0] += s1
                H[s0 + 1] += s2
                H[s0 + 2] += -s3 * ie
                H[s0 + 3] += s1
                H[0] += d1 * slow + d2 * x[s0 + 1] - d3 * x[s0 + 2] * ie
        elif code == 6:  # butler_volmer [I0, dR, n_cells, Ea, t_ref]: I0(T) = I0·exp[−(Ea/R)(1/T − 1/T_ref)]
            tk = (temp if has_temp else T_REF_C) + KELVIN
            g = fm[v + 2] * 2.0 * R_GAS * tk / FARADAY
            i0 = fm[v] * math.exp(-fm[v + 3] / R_GAS * (1.0 / tk - 1.0 / (fm[v + 4] + KELVIN)))
            xx = ie / (2.0 * i0)
            y = y + (-g * math.asinh(xx) + fm[v + 1] * ie)
            D = D + (-g / (2.0 * i0 * math.sqrt(1.0 + xx * xx)) + fm[v + 1])
    b = im[H_BIAS]
    if jac and b >= 0:
        H[b] -= D
    return y, D, 0


# ================================================================================================ many points
# A particle cloud or the sigma points of a run: ``npts`` points row-major in ``X`` (point ``p`` at ``X + p·n``). The
# parameters of every point are evaluated together (load_params: points innermost), then each point's step or output
# reads its own from ``work``. ``PW``: :func:`points_scratch` floats.
@kernel(inline=True)
def points_scratch(npts):
    """Floats of scratch the ``*_points`` functions need for ``npts`` points."""
    return (2 * MAX_PARAMS + 1) * npts


@kernel(inline=True)
def _point_params(PW, npts, p, j0, j1, work):
    for j in range(j0, j1):
        work[W_VAL + j] = PW[j * npts + p]
        work[W_DER + j] = PW[(MAX_PARAMS + j) * npts + p]


@kernel
def model_step_points(im, fm, X, npts, I, dt, temp, has_temp, XN, F, B, work, PW):
    """:func:`model_step` without Jacobians of ``npts`` points (point ``p`` at current ``I[p]``) into ``XN``; returns
    the first nonzero status (0: fine)."""
    n = im[H_N]
    t = temp if has_temp else T_REF_C
    j0 = im[H_STEP0]
    j1 = im[H_STEP1]
    load_params_points(im, fm, X, n, npts, t, j0, j1, PW, ptr_off(PW, 2 * MAX_PARAMS * npts))
    jac = n < 0  # run-time False: a literal would make numba compile a copy of every callee
    for p in range(npts):
        _point_params(PW, npts, p, j0, j1, work)
        st = step_loaded(im, fm, ptr_off(X, p * n), I[p], dt, temp, has_temp, jac, ptr_off(XN, p * n), F, B, work)
        if st != 0:
            return st
    return 0


@kernel
def model_output_points(im, fm, X, npts, i, temp, has_temp, Y, D, H, work, PW):
    """:func:`model_output` without Jacobians of ``npts`` points at current ``i``: ``Y[p]``, ``D[p]``; returns the
    first nonzero status (0: fine)."""
    n = im[H_N]
    t = temp if has_temp else T_REF_C
    j0 = im[H_OUT0]
    j1 = im[H_OUT1]
    load_params_points(im, fm, X, n, npts, t, j0, j1, PW, ptr_off(PW, 2 * MAX_PARAMS * npts))
    jac = n < 0
    for p in range(npts):
        _point_params(PW, npts, p, j0, j1, work)
        y, d, st = output_loaded(im, fm, ptr_off(X, p * n), i, temp, has_temp, jac, H, work)
        if st != 0:
            return st
        Y[p] = y
        D[p] = d
    return 0


# ================================================================================================ batch entry
@kernel
def eval_points(im, fm2, X, I, DT, TEMP, has_temp, jac, XN, F, B, Y, H, D, status):
    """Step and output at every point ``p`` (variant ``p`` of ``fm2`` when it has one row per point, else row 0):
    the entry point the equality tests use (arrays in, the evaluator's pointers inside)."""
    work = np.empty(WORK_SIZE)
    V, L = fm2.shape
    n = X.shape[1]
    imp = ptr(im)
    wp = ptr(work)
    for p in range(X.shape[0]):
        fm = ptr_at(fm2, (p if V > 1 else 0) * L)
        s1 = model_step(imp, fm, ptr_at(X, p * n), I[p], DT[p], TEMP[p], has_temp, jac, ptr_at(XN, p * n),
                        ptr_at(F, p * n * n), ptr_at(B, p * n), wp)
        y, d, s2 = model_output(imp, fm, ptr_at(X, p * n), I[p], TEMP[p], has_temp, jac, ptr_at(H, p * n), wp)
        Y[p] = y
        D[p] = d
        status[p] = max(s1, s2)
    keep_alive((work,))


@kernel
def eval_cloud(im, fm, X, I, i_out, dt, temp, has_temp, XN, Y, D):
    """:func:`model_step_points` (point ``p`` at current ``I[p]``) and :func:`model_output_points` (at ``i_out``) on
    the cloud ``X`` (npts × n) at one ``dt`` and temperature: the particle filter's path, for the equality tests;
    returns the status."""
    npts, n = X.shape
    work = np.empty(WORK_SIZE)
    PW = np.empty(points_scratch(npts))
    F = np.empty(n * n)
    B = np.empty(n)
    H = np.empty(n)
    s1 = model_step_points(ptr(im), ptr(fm), ptr(X), npts, ptr(I), dt, temp, has_temp, ptr(XN), ptr(F), ptr(B),
                           ptr(work), ptr(PW))
    s2 = model_output_points(ptr(im), ptr(fm), ptr(X), npts, i_out, temp, has_temp, ptr(Y), ptr(D), ptr(H),
                             ptr(work), ptr(PW))
    keep_alive((work, PW, F, B, H))
    return max(s1, s2)
