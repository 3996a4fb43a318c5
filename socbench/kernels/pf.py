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
from .evaluate import WORK_SIZE, model_output, model_step, ptr, ptr_at
from .filters import DT0, freeze, measurement_var, record
from .jit import kernel
from .linalg import diverged_var, eigh_jacobi, gate

absorb = kernel(D.absorb)

PF_FIELDS = ("n_particles", "resample_threshold", "roughening", "kernel_h", "max_stages", "temper_threshold",
             "temper_h", "current_sd", "additive", "rough_factor", "needs_D")
N_P, RS_THR, ROUGH, KERNEL_H, MAX_STAGES, TEMPER_THR, TEMPER_H, SD_I, ADDITIVE, ROUGH_C, NEEDS_D = range(11)
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


@kernel
def normal(pre, c):
    """The standard normal at counter ``c`` of a prefix (draws.normals: Box–Muller)."""
    pre = np.uint64(pre)
    u1 = float((absorb(pre, np.uint64(2 * c)) >> D.S11) + D.ONE) * D.TWO_M53
    u2 = float(absorb(pre, np.uint64(2 * c + 1)) >> D.S11) * D.TWO_M53
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(D.TWO_PI * u2)


# ================================================================================================ PF pieces
@kernel(inline=True)
def normalise_log(lw, N):
    mx = lw[0]
    for p in range(1, N):
        if lw[p] > mx:
            mx = lw[p]
    s = 0.0
    for p in range(N):
        lw[p] = lw[p] - mx
        s += math.exp(lw[p])
    ls = math.log(s)
    for p in range(N):
        lw[p] = lw[p] - ls


@kernel
def ess_of(lw, ll, phi, N, tmp):
    """ESS of ``normalise_log(lw + φ·ll)`` (``tmp``: scratch)."""
    for p in range(N):
        tmp[p] = lw[p] + phi * ll[p]
    normalise_log(tmp, N)
    s = 0.0
    for p in range(N):
        s += math.exp(2.0 * tmp[p])
    return 1.0 / s


@kernel(inline=True)
def temper_exponent(lw, ll, phi_max, accept, target, N, tmp):
    """pf.temper_exponent for one run."""
    lwp, llp, tp = ptr(lw), ptr(ll), ptr(tmp)
    if not ess_of(lwp, llp, phi_max, N, tp) < accept:
        return phi_max
    lo = 0.0
    hi = phi_max
    for _ in range(TEMPER_ITERS):
        mid = 0.5 * (lo + hi)
        if ess_of(lwp, llp, mid, N, tp) >= target:
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


@kernel(inline=True)
def weighted_mean_root(X, w, N, n, mean, root, Vm, ev, U, work):
    """pf.weighted_mean_root: weighted mean and the symmetric square root of the weighted covariance."""
    for a in range(n):
        s = 0.0
        for p in range(N):
            s += w[p] * X[p, a]
        mean[a] = s
    for a in range(n):
        for b in range(n):
            s = 0.0
            for p in range(N):
                s += w[p] * (X[p, a] - mean[a]) * (X[p, b] - mean[b])
            Vm[a, b] = s
    for a in range(n):
        for b in range(a, n):
            v = 0.5 * (Vm[a, b] + Vm[b, a])
            Vm[a, b] = v
            Vm[b, a] = v
    eigh_jacobi(ptr(Vm), n, ptr(ev), ptr(U), ptr(work))
    for a in range(n):
        for b in range(n):
            s = 0.0
            for k in range(n):
                s += U[a, k] * math.sqrt(max(ev[k], 0.0)) * U[b, k]
            root[a, b] = s


@kernel(inline=True)
def resample_into(X, idx, N, n, Xr):
    for i in range(N):
        for a in range(n):
            Xr[i, a] = X[idx[i], a]


@kernel(inline=True)
def shrink_with(Xr, mean, root, h, pre, N, n, X, eps):
    """``X = a·Xr + (1 − a)·mean + h·root·ε`` (pf.shrink), ε from the stream prefix ``pre`` (``eps``: scratch)."""
    a_ = math.sqrt(1.0 - h * h)
    for p in range(N):
        for d in range(n):
            eps[d] = normal(pre, p * n + d)
        for a in range(n):
            s = 0.0
            for d in range(n):
                s += root[a, d] * eps[d]
            X[p, a] = a_ * Xr[p, a] + (1.0 - a_) * mean[a] + h * s


@kernel(inline=True)
def clamp_particles(X, N):
    out = False
    for p in range(N):
        if X[p, 0] < 0.0:
            X[p, 0] = 0.0
            out = True
        elif X[p, 0] > 1.0:
            X[p, 0] = 1.0
            out = True
    return out


@kernel(inline=True)
def likelihoods(imp, fmp, X, v, i, temp, has_temp, needs_D, nz, N, n, Y, Rk, ll, Hp, sp):
    """``Y, R`` and ``log N(v; Y, R)`` (up to the constant) of every particle; returns the model status."""
    for p in range(N):
        y, d, st = model_output(imp, fmp, ptr_at(X, p * n), i, temp, has_temp, needs_D, Hp, sp)
        if st != 0:
            return st
        Y[p] = y
        Rk[p] = measurement_var(nz, d)
        res = v - y
        ll[p] = -0.5 * res * res / Rk[p] - 0.5 * math.log(Rk[p])
    return 0


# ================================================================================================ the filter
@kernel
def pf(r0, r1, im, fm, x0, L0, std0, cur, volt, temp, has_temp, dts, nz, walk, Qroot, opt, pfopt, seed,
       outf, outb, xs, pd, store, failed, failed_at, status, repairs, counts):
    """Bootstrap particle filter (estimators/pf.py) over runs ``r0 … r1 − 1``."""
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
    needs_D = pfopt[NEEDS_D] != 0.0
    jac = n < 0  # run-time False (literals make numba compile copies of every callee)
    stream_initial = np.int64(D.INITIAL)  # the streams as run-time integers, for the same reason
    stream_resample = np.int64(D.RESAMPLE)
    stream_current = np.int64(D.CURRENT)
    stream_additive = np.int64(D.ADDITIVE)
    stream_roughen = np.int64(D.ROUGHEN)
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
    xn = np.empty(n)
    Bv = np.empty(n)
    mean = np.empty(n)
    var = np.empty(n)
    mean_r = np.empty(n)
    ev = np.empty(n)
    eps = np.empty(n)
    F = np.empty((n, n))
    root = np.empty((n, n))
    Vm = np.empty((n, n))
    U = np.empty((n, n))
    work = np.empty((n, n))
    scratch = np.empty(WORK_SIZE)
    imp, fmp, Hp, xnp, Bp, Fp, sp = ptr(im), ptr(fm), ptr(H), ptr(xn), ptr(Bv), ptr(F), ptr(scratch)
    for r in range(r0, r1):
        pre = prefix(seed, stream_initial, stream_initial, r)  # stream 0, sample 0
        for p in range(N):
            for d in range(n):
                eps[d] = normal(pre, p * n + d)
            for a in range(n):
                s = 0.0
                for d in range(n):
                    s += L0[r, a, d] * eps[d]
                X[p, a] = x0[r, a] + s
        pending_clamp = clamp_particles(X, N)
        for p in range(N):
            w[p] = 1.0 / N
        consecutive = np.int64(0)
        for k in range(T):
            ik = cur[r, k]
            tk = temp[r, k]
            vk = volt[r, k]
            # ---------------------------------------------------------------- update
            st = likelihoods(imp, fmp, X, vk, ik, tk, has_temp, needs_D, nz, N, n, Y, Rk, ll, Hp, sp)
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
            # tempered assimilation (pf.ParticleFilter.assimilate)
            for p in range(N):
                lw[p] = math.log(w[p])
            left = 0.0 if gated else 1.0
            stages = 0
            for s_ in range(max_stages):
                if not left > 0.0:
                    break
                phi = left
                if s_ != max_stages - 1:
                    phi = temper_exponent(lw, ll, left, accept, target, N, tmp)
                for p in range(N):
                    lw[p] = lw[p] + phi * ll[p]
                normalise_log(lw, N)
                left = left - phi
                stages += 1
                if left > 0.0:
                    for p in range(N):
                        w[p] = math.exp(lw[p])
                    weighted_mean_root(X, w, N, n, mean_r, root, Vm, ev, U, work)
                    systematic(w, uniform0(prefix(seed, D.STAGE + 2 * s_, k, r)), N, cum, idx)
                    resample_into(X, idx, N, n, Xr)
                    shrink_with(Xr, mean_r, root, pfopt[TEMPER_H], prefix(seed, D.STAGE + 2 * s_ + 1, k, r), N, n, X,
                                eps)
                    clamp_particles(X, N)
                    for p in range(N):
                        lw[p] = -math.log(N)
                    st = likelihoods(imp, fmp, X, vk, ik, tk, has_temp, needs_D, nz, N, n, Y, Rk, ll, Hp, sp)
                    if st != 0:
                        break
            if st != 0:
                status[r] = st
                break
            for p in range(N):
                w[p] = math.exp(lw[p])
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
            if diverged_var(mean, n, var[0], nis, opt[2], opt[3]):
                failed[r] = True
                failed_at[r] = k
                freeze(outf, outb, xs, pd, store, r, k, T, n, x0[r, 0], std0[r], volt[r, 0])
                break
            record(outf, outb, xs, pd, store, r, k, mean[0], math.sqrt(var[0]), yhat, e, S, pending_clamp, gated,
                   mean, var, n)
            if k + 1 == T:
                break
            # ---------------------------------------------------------------- resample
            sw = 0.0
            for p in range(N):
                sw += w[p] * w[p]
            if 1.0 / sw < threshold:
                if h > 0.0:
                    weighted_mean_root(X, w, N, n, mean_r, root, Vm, ev, U, work)
                systematic(w, uniform0(prefix(seed, stream_resample, k, r)), N, cum, idx)
                resample_into(X, idx, N, n, Xr)
                for p in range(N):
                    w[p] = 1.0 / N
                counts[r, 0] += 1
                pre = prefix(seed, stream_roughen, k, r)
                if h > 0.0:
                    shrink_with(Xr, mean_r, root, h, pre, N, n, X, eps)
                else:
                    if K_rough > 0.0:
                        for a in range(n):  # roughening_sd: K (max − min) N^(−1/d), on the resampled cloud
                            lo = Xr[0, a]
                            hi = Xr[0, a]
                            for p in range(1, N):
                                lo = min(lo, Xr[p, a])
                                hi = max(hi, Xr[p, a])
                            ev[a] = K_rough * (hi - lo) * pfopt[ROUGH_C]
                        for p in range(N):
                            for a in range(n):
                                Xr[p, a] += ev[a] * normal(pre, p * n + a)
                    for p in range(N):
                        for a in range(n):
                            X[p, a] = Xr[p, a]
            # ---------------------------------------------------------------- predict
            dt = dts[k]
            pre_i = prefix(seed, stream_current, k, r)
            pre_q = prefix(seed, stream_additive, k, r)
            for p in range(N):
                i_p = ik + sd_i * normal(pre_i, p) if sd_i > 0.0 else ik
                st = model_step(imp, fmp, ptr_at(X, p * n), i_p, dt, tk, has_temp, jac, xnp, Fp, Bp, sp)
                if st != 0:
                    break
                for a in range(n):
                    X[p, a] = xn[a]
                if additive == ADD_WALK:
                    for a in range(n):
                        X[p, a] += math.sqrt(walk[a] * (dt / nz[DT0])) * normal(pre_q, p * n + a)
                elif additive == ADD_ROOT:
                    for d in range(n):
                        eps[d] = normal(pre_q, p * n + d)
                    for a in range(n):
                        s = 0.0
                        for d in range(n):
                            s += Qroot[a, d] * eps[d]
                        X[p, a] += s
            if st != 0:
                status[r] = st
                break
            pending_clamp = clamp_particles(X, N)
            bad = False
            for p in range(N):
                for a in range(n):
                    if not math.isfinite(X[p, a]):
                        bad = True
            if bad:
                failed[r] = True
                failed_at[r] = k + 1
                freeze(outf, outb, xs, pd, store, r, k + 1, T, n, x0[r, 0], std0[r], volt[r, 0])
                break
