"""Compiled bootstrap particle filter (:mod:`socbench.estimators.pf`), one run after the other over a run slice.

The same steps as the numpy engine (its docstring has the equations): update with the χ² gate, the tempered
(progressive-correction) measurement update with resampling and the shrinkage kernel between stages, systematic
resampling with roughening or the shrinkage kernel, prediction with the current-noise draw and the additive noise,
the SOC clamp flag and the divergence freeze. Random numbers: the counter-based streams of
:mod:`socbench.estimators.draws` (``absorb`` is that module's function, compiled as is; the few lines composing it
are mirrored here and checked against the numpy ones by the tests), so run ``r`` sees exactly the numbers the numpy
PF gives its row ``r``.

``pfopt`` slots: :data:`PF_FIELDS`. ``counts (R, 2)``: resamplings and tempered samples per run.
"""

from __future__ import annotations

import math

import numpy as np

from ..estimators import draws as D
from .evaluate import WORK_SIZE, keep_alive, model_output_points, model_step, model_step_points, points_scratch, ptr
from .filters import DT0, W_EXTRA, freeze, measurement_var, record
from .jit import kernel
from .linalg import diverged_var, eigh_jacobi, gate

absorb = kernel(D.absorb)
sin_cos_reduced = kernel(inline=True)(D.sin_cos_reduced)

PF_FIELDS = ("n_particles", "resample_threshold", "roughening", "kernel_h", "max_stages", "temper_threshold",
             "temper_h", "current_sd", "additive", "rough_factor")
N_P, RS_THR, ROUGH, KERNEL_H, MAX_STAGES, TEMPER_THR, TEMPER_H, SD_I, ADDITIVE, ROUGH_C = range(10)
#: additive noise modes
ADD_NONE, ADD_WALK, ADD_ROOT = 0, 1, 2
TEMPER_ITERS = 24


# ================================================================================================ random numbers
@kernel
def prefix(seed, stream, k, r):
    """``A(A(A(seed, stream), k), r)`` (draws.prefix for one run). Every hash argument is cast to uint64: numba
    computes int64 ⊕ uint64 in float64."""
    return absorb(absorb(absorb(np.uint64(seed), np.uint64(stream)), np.uint64(k)), np.uint64(r))


@kernel
def uniform0(pre):
    """The uniform at counter 0 of a prefix (draws.uniforms)."""
    return float(absorb(np.uint64(pre), np.uint64(0)) >> D.S11) * D.TWO_M53


@kernel(inline=True)
def cos_sin_turn(u):
    """draws.cos_sin_turn for one uniform: ``(cos 2πu, sin 2πu)`` (the quadrant by selects, not branches: it is
    random, and a loop of them vectorises)."""
    q = math.floor(4.0 * u + 0.5)
    s, c = sin_cos_reduced((u - 0.25 * q) * D.TWO_PI)
    quadrant = np.int64(q) & 3
    odd = (quadrant & 1) == 1
    cos = s if odd else c
    sin = c if odd else s
    return (-cos if quadrant == 1 or quadrant == 2 else cos), (-sin if quadrant >= 2 else sin)


@kernel(inline=True)
def pair_uniforms(pre, j):
    """``(u₁ ∈ (0, 1], u₂ ∈ [0, 1))`` of the Box–Muller pair ``j`` (counters 2j, 2j + 1) of a prefix."""
    q = np.uint64(2 * j)
    u1 = float((absorb(pre, q) >> D.S11) + D.ONE) * D.TWO_M53
    u2 = float(absorb(pre, q + D.ONE) >> D.S11) * D.TWO_M53
    return u1, u2


@kernel
def normal(pre, c):
    """The standard normal at counter ``c`` of a prefix (draws.normals: Box–Muller on the pair ⌊c/2⌋)."""
    u1, u2 = pair_uniforms(np.uint64(pre), c // 2)
    cos, sin = cos_sin_turn(u2)
    rho = math.sqrt(-2.0 * math.log(u1))
    return rho * cos if c % 2 == 0 else rho * sin


@kernel
def normals_into(pre, out, count, scratch):
    """``out[0 … count − 1]``: the normals at counters ``0 … count − 1`` of a prefix (``scratch``: 3·⌈count/2⌉
    floats). Two passes over the pairs: the hashes and the turn's cos/sin (plain arithmetic: SIMD), then the radius
    (log and sqrt: libm calls, which would keep the first pass from vectorising)."""
    pre = np.uint64(pre)
    pairs = (count + 1) // 2
    for j in range(pairs):
        u1, u2 = pair_uniforms(pre, j)
        cos, sin = cos_sin_turn(u2)
        scratch[j] = u1
        scratch[pairs + j] = cos
        scratch[2 * pairs + j] = sin
    for j in range(pairs):
        rho = math.sqrt(-2.0 * math.log(scratch[j]))
        out[2 * j] = rho * scratch[pairs + j]
        if 2 * j + 1 < count:
            out[2 * j + 1] = rho * scratch[2 * pairs + j]


@kernel(inline=True)
def normals_scratch(count):
    """Floats of scratch :func:`normals_into` needs for ``count`` normals."""
    return 3 * ((count + 1) // 2)


# ================================================================================================ PF pieces
# Every helper takes pointers (evaluate.ptr; particle clouds row-major N × n): array arguments would be
# reference-counted on every call.
@kernel
def exp_weights(lw, ll, phi, N, e):
    """``a = lw + φ·ll``: ``e_p = exp(a_p − max a)`` into ``e``; returns ``(max a, Σe, Σe²)``.

    One exponential per particle gives both the normalised weights ``w = e/Σe`` (pf.normalise_log) and the effective
    sample size ``1/Σw² = (Σe)²/Σe²`` (pf.ess), to rounding.
    """
    m = lw[0] + phi * ll[0]
    for p in range(1, N):
        a = lw[p] + phi * ll[p]
        if a > m:
            m = a
    s1 = 0.0
    s2 = 0.0
    for p in range(N):
        v = math.exp((lw[p] + phi * ll[p]) - m)
        e[p] = v
        s1 += v
        s2 += v * v
    return m, s1, s2


@kernel(inline=True)
def temper_bisect(lw, ll, phi_max, target, N, e):
    """pf.temper_exponent's bisection: the largest ``φ`` with ``ESS(lw + φ·ll) ≥ target`` (at least
    ``phi_max/2^24``)."""
    lo = 0.0
    hi = phi_max
    for _ in range(TEMPER_ITERS):
        mid = 0.5 * (lo + hi)
        _, s1, s2 = exp_weights(lw, ll, mid, N, e)
        if s1 * s1 / s2 >= target:
            lo = mid
        else:
            hi = mid
    return max(lo, phi_max * 0.5**TEMPER_ITERS)


@kernel(inline=True)
def systematic(w, u, N, cum, idx):
    """pf.systematic_indices for one run: ``idx[i] = #{j : cumsum(w)_j ≤ (u + i)/N}``, at most N − 1."""
    c = 0.0
    for j in range(N):
        c += w[j]
        cum[j] = c
    j = 0
    for i in range(N):
        pos = (u + i) / N
        while j < N and cum[j] <= pos:
            j += 1
        idx[i] = j if j < N else N - 1


@kernel
def weighted_mean_root(X, w, N, n, mean, root, Vm, ev, U, work):
    """pf.weighted_mean_root: weighted mean and the symmetric square root of the weighted covariance."""
    for a in range(n):
        s = 0.0
        for p in range(N):
            s += w[p] * X[p * n + a]
        mean[a] = s
    for a in range(n):
        for b in range(n):
            s = 0.0
            for p in range(N):
                s += w[p] * (X[p * n + a] - mean[a]) * (X[p * n + b] - mean[b])
            Vm[a * n + b] = s
    for a in range(n):
        for b in range(a, n):
            v = 0.5 * (Vm[a * n + b] + Vm[b * n + a])
            Vm[a * n + b] = v
            Vm[b * n + a] = v
    eigh_jacobi(Vm, n, ev, U, work)
    for a in range(n):
        for b in range(n):
            s = 0.0
            for k in range(n):
                s += U[a * n + k] * math.sqrt(max(ev[k], 0.0)) * U[b * n + k]
            root[a * n + b] = s


@kernel(inline=True)
def resample_into(X, idx, N, n, Xr):
    for i in range(N):
        for a in range(n):
            Xr[i * n + a] = X[idx[i] * n + a]


@kernel(inline=True)
def shrink_with(Xr, mean, root, h, pre, N, n, X, E, Es):
    """``X = a·Xr + (1 − a)·mean + h·root·ε`` (pf.shrink), ε from the stream prefix ``pre`` (``E``: N·n scratch,
    ``Es``: normals_into's)."""
    a_ = math.sqrt(1.0 - h * h)
    normals_into(pre, E, N * n, Es)
    for p in range(N):
        for a in range(n):
            s = 0.0
            for d in range(n):
                s += root[a * n + d] * E[p * n + d]
            X[p * n + a] = a_ * Xr[p * n + a] + (1.0 - a_) * mean[a] + h * s


@kernel(inline=True)
def clamp_particles(X, N, n):
    out = False
    for p in range(N):
        if X[p * n] < 0.0:
            X[p * n] = 0.0
            out = True
        elif X[p * n] > 1.0:
            X[p * n] = 1.0
            out = True
    return out


@kernel
def likelihoods(imp, fmp, X, v, i, temp, has_temp, nz, extra, N, Y, Rk, ll, Hp, sp, PW):
    """``Y, R`` and ``log N(v; Y, R + extra)`` (up to the constant; ``extra`` the weights' extra variance,
    noise.NoiseModel.weight_extra) of every particle (the model on the whole cloud at once,
    :func:`~.evaluate.model_output_points`; ``Rk`` holds the feedthroughs ``D`` in between); returns the model
    status."""
    st = model_output_points(imp, fmp, X, N, i, temp, has_temp, Y, Rk, Hp, sp, PW)
    if st != 0:
        return st
    for p in range(N):
        r = measurement_var(nz, Rk[p])
        Rk[p] = r
        r += extra
        res = v - Y[p]
        ll[p] = -0.5 * res * res / r - 0.5 * math.log(r)
    return 0


# ================================================================================================ the filter
@kernel
def pf(r0, r1, im, fm, x0, L0, std0, cur, volt, temp, has_temp, dts, hv, nz, walk, Qroot, opt, pfopt, seed,
       outf, outb, xs, pd, store, failed, failed_at, status, repairs, counts):
    """Bootstrap particle filter (estimators/pf.py) over runs ``r0 … r1 − 1``; ``hv (T − 1,)`` the current variance
    the hold misses over each step (``pf.hold_spread``; zeros under a Q override)."""
    T = cur.shape[1]
    n = x0.shape[1]
    N = int(pfopt[N_P])
    max_stages = max(int(pfopt[MAX_STAGES]), 1)
    target = pfopt[RS_THR] * N
    accept = pfopt[TEMPER_THR] * N
    threshold = pfopt[RS_THR] * N
    K_rough = pfopt[ROUGH]
    h = pfopt[KERNEL_H]
    sd_i = pfopt[SD_I]
    additive = int(pfopt[ADDITIVE])
    stream_initial = np.int64(D.INITIAL)  # the streams as run-time integers, for the same reason
    stream_resample = np.int64(D.RESAMPLE)
    stream_current = np.int64(D.CURRENT)
    stream_additive = np.int64(D.ADDITIVE)
    stream_roughen = np.int64(D.ROUGHEN)
    stream_hold = np.int64(D.HOLD)
    jac = n > 0  # run-time True (a literal would make numba compile a copy of every callee)
    X = np.empty((N, n))
    Xr = np.empty((N, n))
    w = np.empty(N)
    lw = np.empty(N)
    ll = np.empty(N)
    tmp = np.empty(N)
    Y = np.empty(N)
    Rk = np.empty(N)
    cum = np.empty(N)
    idx = np.empty(N, dtype=np.int64)
    H = np.empty(n)
    Xn = np.empty((N, n))
    Ip = np.empty(N)  # the particles' currents
    PW = np.empty(points_scratch(N))
    Bv = np.empty(n)
    mean = np.empty(n)
    var = np.empty(n)
    mean_r = np.empty(n)
    x_mean = np.empty(n)  # the cloud mean stepped (for ∂f/∂I there across a logger pause)
    ev = np.empty(n)
    E = np.empty(N * n)  # normals of one stream
    Ei = np.empty(N)  # the current-noise normals
    Es = np.empty(normals_scratch(N * n))
    F = np.empty((n, n))
    root = np.empty((n, n))
    Vm = np.empty((n, n))
    U = np.empty((n, n))
    work = np.empty((n, n))
    scratch = np.empty(WORK_SIZE)
    imp, fmp, Hp, Xnp, Ipp, PWp, Bp, Fp, sp = (ptr(im), ptr(fm), ptr(H), ptr(Xn), ptr(Ip), ptr(PW), ptr(Bv), ptr(F),
                                               ptr(scratch))
    Xp, Xrp, wp, lwp, llp, tmpp, Yp, Rkp, cump, idxp = (ptr(X), ptr(Xr), ptr(w), ptr(lw), ptr(ll), ptr(tmp), ptr(Y),
                                                       ptr(Rk), ptr(cum), ptr(idx))
    meanp, varp, mean_rp, evp, rootp, Vmp, Up, workp = (ptr(mean), ptr(var), ptr(mean_r), ptr(ev), ptr(root), ptr(Vm),
                                                        ptr(U), ptr(work))
    Ep, Eip, Esp, nzp, x_meanp = ptr(E), ptr(Ei), ptr(Es), ptr(nz), ptr(x_mean)
    outfp, outbp, xsp, pdp = ptr(outf), ptr(outb), ptr(xs), ptr(pd)
    R_all = outf.shape[1]
    for r in range(r0, r1):
        normals_into(prefix(seed, stream_initial, stream_initial, r), Ep, N * n, Esp)  # stream 0, sample 0
        for p in range(N):
            for a in range(n):
                s = 0.0
                for d in range(n):
                    s += L0[r, a, d] * E[p * n + d]
                X[p, a] = x0[r, a] + s
        pending_clamp = clamp_particles(Xp, N, n)
        for p in range(N):
            w[p] = 1.0 / N
            lw[p] = math.log(w[p])  # the log-weights are carried from sample to sample (numpy takes log(w) anew)
        consecutive = np.int64(0)
        looked = False  # whether the run has assimilated a sample yet
        for k in range(T):
            ik = cur[r, k]
            tk = temp[r, k]
            vk = volt[r, k]
            extra = nz[W_EXTRA] if looked else 0.0  # noise.NoiseModel.weight_extra
            # ---------------------------------------------------------------- update
            st = likelihoods(imp, fmp, Xp, vk, ik, tk, has_temp, nzp, extra, N, Yp, Rkp, llp, Hp, sp, PWp)
            if st != 0:
                status[r] = st
                break
            yhat = 0.0
            for p in range(N):
                yhat += w[p] * Y[p]
            S = 0.0
            SR = 0.0
            for p in range(N):
                d_ = Y[p] - yhat
                S += w[p] * (d_ * d_)
                SR += w[p] * Rk[p]
            S = S + SR
            e = vk - yhat
            nis = e * e / S
            gated, consecutive = gate(nis, opt[0], consecutive, opt[1])
            looked = looked or not gated
            # tempered assimilation (pf.ParticleFilter.assimilate)
            left = 0.0 if gated else 1.0
            stages = 0
            s1 = 0.0
            for s_ in range(max_stages):
                if not left > 0.0:
                    break
                phi = left
                m, s1, s2 = exp_weights(lwp, llp, phi, N, tmpp)
                if s_ != max_stages - 1 and s1 * s1 / s2 < accept:  # the whole likelihood would collapse the cloud
                    phi = temper_bisect(lwp, llp, left, target, N, tmpp)
                    m, s1, s2 = exp_weights(lwp, llp, phi, N, tmpp)
                ls = math.log(s1)
                for p in range(N):
                    lw[p] = ((lw[p] + phi * ll[p]) - m) - ls
                left = left - phi
                stages += 1
                if left > 0.0:
                    for p in range(N):
                        w[p] = math.exp(lw[p])
                    weighted_mean_root(Xp, wp, N, n, mean_rp, rootp, Vmp, evp, Up, workp)
                    systematic(wp, uniform0(prefix(seed, D.STAGE + 2 * s_, k, r)), N, cump, idxp)
                    resample_into(Xp, idxp, N, n, Xrp)
                    shrink_with(Xrp, mean_rp, rootp, pfopt[TEMPER_H], prefix(seed, D.STAGE + 2 * s_ + 1, k, r), N, n,
                                Xp, Ep, Esp)
                    clamp_particles(Xp, N, n)
                    for p in range(N):
                        lw[p] = -math.log(N)
                    st = likelihoods(imp, fmp, Xp, vk, ik, tk, has_temp, nzp, extra, N, Yp, Rkp, llp, Hp, sp, PWp)
                    if st != 0:
                        break
            if st != 0:
                status[r] = st
                break
            if stages > 0:  # the last normalisation's exponentials: w = exp(lw) to rounding
                for p in range(N):
                    w[p] = tmp[p] / s1
            if stages > 1:
                counts[r, 1] += 1
            for a in range(n):
                s = 0.0
                for p in range(N):
                    s += w[p] * X[p, a]
                mean[a] = s
            for a in range(n):
                s = 0.0
                for p in range(N):
                    d_ = X[p, a] - mean[a]
                    s += w[p] * (d_ * d_)
                var[a] = s
            bad = diverged_var(meanp, n, var[0], nis, opt[2], opt[3])
            if bad:
                failed[r] = bad
                failed_at[r] = k
                freeze(outf, outb, xs, pd, store, r, k, T, n, x0[r, 0], std0[r], volt[r, 0])
                break
            record(outfp, outbp, xsp, pdp, store, R_all, T, r, k, mean[0], math.sqrt(var[0]), yhat, e, S,
                   pending_clamp, gated, meanp, varp, n)
            if k + 1 == T:
                break
            # ---------------------------------------------------------------- resample
            sw = 0.0
            for p in range(N):
                sw += w[p] * w[p]
            if 1.0 / sw < threshold:
                if h > 0.0:
                    weighted_mean_root(Xp, wp, N, n, mean_rp, rootp, Vmp, evp, Up, workp)
                systematic(wp, uniform0(prefix(seed, stream_resample, k, r)), N, cump, idxp)
                resample_into(Xp, idxp, N, n, Xrp)
                for p in range(N):
                    w[p] = 1.0 / N
                    lw[p] = math.log(w[p])
                counts[r, 0] += 1
                pre = prefix(seed, stream_roughen, k, r)
                if h > 0.0:
                    shrink_with(Xrp, mean_rp, rootp, h, pre, N, n, Xp, Ep, Esp)
                else:
                    if K_rough > 0.0:
                        for a in range(n):  # roughening_sd: K (max − min) N^(−1/d), on the resampled cloud
                            lo = Xr[0, a]
                            hi = Xr[0, a]
                            for p in range(1, N):
                                lo = min(lo, Xr[p, a])
                                hi = max(hi, Xr[p, a])
                            ev[a] = K_rough * (hi - lo) * pfopt[ROUGH_C]
                        normals_into(pre, Ep, N * n, Esp)
                        for p in range(N):
                            for a in range(n):
                                Xr[p, a] += ev[a] * E[p * n + a]
                    for p in range(N):
                        for a in range(n):
                            X[p, a] = Xr[p, a]
            # ---------------------------------------------------------------- predict
            dt = dts[k]
            if sd_i > 0.0:
                normals_into(prefix(seed, stream_current, k, r), Eip, N, Esp)
            if additive != ADD_NONE:
                normals_into(prefix(seed, stream_additive, k, r), Ep, N * n, Esp)
            for p in range(N):
                Ip[p] = ik + sd_i * Ei[p] if sd_i > 0.0 else ik
            st = model_step_points(imp, fmp, Xp, N, Ipp, dt, tk, has_temp, Xnp, Fp, Bp, sp, PWp)
            if st != 0:
                status[r] = st
                break
            for p in range(N):
                for a in range(n):
                    X[p, a] = Xn[p, a]
                if additive == ADD_WALK:
                    for a in range(n):
                        X[p, a] += math.sqrt(walk[a] * (dt / nz[DT0])) * E[p * n + a]
                elif additive == ADD_ROOT:
                    for a in range(n):
                        s = 0.0
                        for d in range(n):
                            s += Qroot[a, d] * E[p * n + d]
                        X[p, a] += s
            if hv[k] > 0.0:  # the current the hold misses across a logger pause: each state on its own (pf.hold_spread)
                st = model_step(imp, fmp, meanp, ik, dt, tk, has_temp, jac, x_meanp, Fp, Bp, sp)
                if st != 0:
                    status[r] = st
                    break
                normals_into(prefix(seed, stream_hold, k, r), Ep, N * n, Esp)
                spread = math.sqrt(hv[k])
                for p in range(N):
                    for a in range(n):
                        X[p, a] += spread * Bv[a] * E[p * n + a]
            pending_clamp = clamp_particles(Xp, N, n)
            bad = False
            for p in range(N):
                for a in range(n):
                    if not math.isfinite(X[p, a]):
                        bad = True
            if bad:
                failed[r] = 1  # non-finite state
                failed_at[r] = k + 1
                freeze(outf, outb, xs, pd, store, r, k + 1, T, n, x0[r, 0], std0[r], volt[r, 0])
                break
    keep_alive((X, Xr, w, lw, ll, tmp, Y, Rk, cum, idx, H, Xn, Ip, PW, Bv, mean, var, mean_r, x_mean, ev, E, Ei, Es, F,
                root, Vm, U, work, scratch))
