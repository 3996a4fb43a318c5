"""Compiled time loops of the Kalman-type filters: EKF, UKF and the coulomb counter, parallel over runs.

Each kernel runs the runs ``r0 … r1 − 1`` of a batch one after the other (the time loop inside a run), with
the equations of its numpy engine (:mod:`socbench.estimators.ekf`, ``ukf``, ``coulomb``: the docstrings there) and the
same safety rules (:mod:`socbench.kernels.linalg`: Joseph form, symmetrise, PSD repair, SOC clamp flag, χ² gate with
release, divergence). A run that fails stops computing: its outputs from the failing sample on repeat the last
recorded values (:func:`freeze`, the semantics of ``estimators.base.Recorder``). Runs are independent, so the
caller splits a batch into slices and runs them on threads (the kernels release the GIL;
:func:`socbench.kernels.engine.parallel_runs`) — cheaper to compile than numba's ``prange``. Each kernel allocates its
work arrays once and hands the evaluator and the linear algebra pointers to them (:func:`~.evaluate.ptr`).

Shared arguments (built by :mod:`socbench.kernels.engine`):

* ``im, fm``     the lowered model (:mod:`socbench.kernels.lowering`);
* ``x0 (R, n)``, ``P0 (R, n, n)``; ``cur, volt, temp (R, T)``, ``has_temp``; ``dts (T − 1,)``; ``hv (T − 1,)``
                 the current variance the zero-order hold misses over each step (``Inputs.hold_var``);
* ``nz``         noise numbers (:data:`NOISE_FIELDS`), ``walk (n,)`` random-walk variances per ``nz[DT0]``,
                 ``Qo (n, n)`` a constant Q override (used when ``nz[Q_OVR] = 1``);
* ``opt``        safety options (:data:`OPTION_FIELDS`);
* outputs        ``outf (5, R, T)``: soc, soc_std, v_pred, innovation, innovation_var; ``outb (2, R, T)``: clamped,
                 gated (the bytes of a bool array); ``xs, pd (R, T, n)`` when ``store``; ``failed (R,)``
                 (int8: the reason code of a failed run, ``safety.DIVERGENCE_REASONS``), ``failed_at (R,)``;
                 ``status (R,)``: 1 where the model met a condition where numpy raises (the caller
                 reruns the batch with numpy); ``repairs (R,)``: covariances the PSD repair acted on
                 (``Estimate.info["psd_repairs"]``).

Noise (:mod:`socbench.estimators.noise`): ``R_k = σ_V² + σ_in²·D_k²`` (or the override), ``Q_k = σ_in²·B_k B_kᵀ +
hv_k·diag(B_k²) + diag(walk)·dt_k/dt0`` (or the override matrix).
"""

from __future__ import annotations

import math

import numpy as np

from .evaluate import WORK_SIZE, keep_alive, model_output, model_step, ptr, ptr_at
from .jit import kernel
from .linalg import cholesky_lower, diverged_cov, diverged_var, eigh_jacobi, gate, repair_psd, symmetrise

#: nz slots
NOISE_FIELDS = ("voltage_var", "input_var", "r_override", "dt0", "has_walk", "q_override", "current_var", "bias_var",
                "weight_extra_var")
V_VAR, IN_VAR, R_OVR, DT0, HAS_WALK, Q_OVR, CUR_VAR, BIAS_VAR, W_EXTRA = range(9)
#: opt slots
OPTION_FIELDS = ("gate_threshold", "gate_release", "var_max", "nis_max", "psd_floor", "psd_rel_floor", "schedule_soc",
                 "gate_widen")
G_THR, G_REL, VAR_MAX, NIS_MAX, PSD_ABS, PSD_REL, SCHEDULE, WIDEN = range(8)


# ================================================================================================ shared pieces
# Helpers called inside a time loop take pointers (evaluate.ptr), never arrays: an array argument is reference-counted
# with atomic operations on every call, even of an inlined function (~10 ns per array).
@kernel(inline=True)
def measurement_var(nz, D):
    """``R_k`` (noise.NoiseModel.R); ``nz`` a pointer to the noise numbers."""
    if nz[R_OVR] == nz[R_OVR]:  # an override (NaN: none)
        return nz[R_OVR]
    return nz[V_VAR] + nz[IN_VAR] * D * D


@kernel(inline=True)
def equilibrium(im, fm, z, t, has_temp, jac, xe, He, n, work):
    """``(E, status)``: the equilibrium voltage ``E(z, T) = h([z, 0, …, 0], 0, T)``, ``∂E/∂z`` into ``He[0]`` when
    ``jac`` (estimators.base.equilibrium: what a filter reads the SOC off under parameter scheduling)."""
    xe[0] = z
    for a in range(1, n):
        xe[a] = 0.0
    y, D, st = model_output(im, fm, xe, 0.0, t, has_temp, jac, He, work)
    return y, st


@kernel(inline=True)
def process_cov(nz, walk, Qo, B, n, dt, var, hold, Q):
    """``Q_k`` into ``Q`` (n × n): the sensor-noise form with input variance ``var`` plus the hold's ``hold·diag(B²)``
    (noise.NoiseModel.Q) or the override matrix, plus ``diag(walk)·dt/dt0`` where ``nz[HAS_WALK]`` (the sensor's and
    the model's random walks, or an estimator's own; engine.noise_arrays leaves it off under an override, as
    NoiseModel.Q does)."""
    if nz[Q_OVR] != 0.0:
        for a in range(n * n):
            Q[a] = Qo[a]
    else:
        for a in range(n):
            for b in range(n):
                Q[a * n + b] = var * B[a] * B[b]
            Q[a * n + a] += hold * B[a] * B[a]
    if nz[HAS_WALK] != 0.0:
        for a in range(n):
            Q[a * n + a] += walk[a] * (dt / nz[DT0])


@kernel(inline=True)
def propagate(F, P, Q, n, FP):
    """``P ← F P Fᵀ + Q`` (all n × n; ``FP``: scratch)."""
    for a in range(n):
        for b in range(n):
            s = 0.0
            for c in range(n):
                s += F[a * n + c] * P[c * n + b]
            FP[a * n + b] = s
    for a in range(n):
        for b in range(n):
            s = 0.0
            for c in range(n):
                s += FP[a * n + c] * F[b * n + c]
            P[a * n + b] = s + Q[a * n + b]


@kernel(inline=True)
def record(outf, outb, xs, pd, store, R, T, r, k, soc, std, v_pred, e, S, clamped, gated, x, diag, n):
    """Sample ``k`` of run ``r`` into the outputs (pointers to ``outf (5, R, T)``, ``outb (2, R, T)``, ``xs, pd
    (R, T, n)``)."""
    rk = r * T + k
    outf[rk] = soc
    outf[R * T + rk] = std
    outf[2 * R * T + rk] = v_pred
    outf[3 * R * T + rk] = e
    outf[4 * R * T + rk] = S
    outb[rk] = 1 if clamped else 0  # outb: uint8 (the flags' bytes)
    outb[R * T + rk] = 1 if gated else 0
    if store:
        for a in range(n):
            xs[rk * n + a] = x[a]
            pd[rk * n + a] = diag[a]


@kernel
def freeze(outf, outb, xs, pd, store, r, kf, T, n, soc0, std0, v0):
    """Outputs of a run failed at sample ``kf``: from ``kf`` on, the values of ``kf − 1`` (or the initial guess)."""
    for k in range(kf, T):
        if k == 0:
            outf[0, r, 0] = soc0
            outf[1, r, 0] = std0
            outf[2, r, 0] = v0
            outf[3, r, 0] = 0.0
            outf[4, r, 0] = 1.0
            if store:
                for a in range(n):
                    xs[r, 0, a] = 0.0
                    pd[r, 0, a] = 0.0
                xs[r, 0, 0] = soc0
                pd[r, 0, 0] = std0 * std0
        else:
            for f in range(5):
                outf[f, r, k] = outf[f, r, k - 1]
            if store:
                for a in range(n):
                    xs[r, k, a] = xs[r, k - 1, a]
                    pd[r, k, a] = pd[r, k - 1, a]
        outb[0, r, k] = 0
        outb[1, r, k] = 0


@kernel(inline=True)
def clamp_soc(x):
    if x[0] < 0.0:
        x[0] = 0.0
        return True
    if x[0] > 1.0:
        x[0] = 1.0
        return True
    return False


@kernel(inline=True)
def project_soc(x, P, n):
    """``estimators.safety.project_soc`` on one run (pointers ``x``, ``P`` n × n): the state projected onto the
    SOC bound it crossed, ``x ← x − P[:, 0]·(z − b)/P[0, 0]``; the SOC alone clipped where ``P[0, 0]`` is not a
    positive finite number."""
    z = x[0]
    if 0.0 <= z <= 1.0:
        return False
    b = 0.0 if z < 0.0 else 1.0
    pzz = P[0]
    ok = math.isfinite(pzz) and pzz > 0.0
    for a in range(n):
        if not math.isfinite(P[a * n]):
            ok = False
    if ok:
        d = z - b
        for a in range(n):
            x[a] = x[a] - P[a * n] * (d / pzz)
    x[0] = b
    return True


@kernel(inline=True)
def settle(x, P, n, nis, opt, w, V, work):
    """The update's safety tail (``estimators.base.settle_update``) up to recording: ``(clamped, failed,
    repaired)`` (pointers: ``x``, ``P`` n × n, ``opt``, scratch ``w``, ``V``, ``work``)."""
    symmetrise(P, n)
    repaired = repair_psd(P, n, opt[PSD_ABS], opt[PSD_REL], w, V, work)
    clamped = project_soc(x, P, n)
    return clamped, diverged_cov(x, n, P, nis, opt[VAR_MAX], opt[NIS_MAX]), repaired


@kernel(inline=True)
def kalman_buffers(n):
    """The work arrays of a Kalman-type kernel, allocated once per kernel call (never in its time loop): vectors
    ``x, H, K, B, w`` ``(n,)``, matrices ``P, F, Q, M, V, work`` ``(n, n)`` and the evaluator's scratch (roles: state,
    output Jacobian, gain, input column of the step, eigenvalues; covariance, step Jacobian, process noise, product
    scratch, eigenvectors, linalg scratch)."""
    return (np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty(n), np.empty((n, n)), np.empty((n, n)),
            np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty(WORK_SIZE))


@kernel(inline=True)
def load_run(x0, P0, r, n, x, P):
    for a in range(n):
        x[a] = x0[r, a]
        for b in range(n):
            P[a, b] = P0[r, a, b]


# ================================================================================================ EKF family
#: the update of the EKF-family kernel (``variant``); ``vopt`` and ``vout`` per variant:
#:   EKF   the Kalman update in Joseph form (estimators/ekf.py)                     vopt —           vout —
#:   AEKF  the EKF with fading-memory Sage–Husa R̂ (and Q̂) (estimators/aekf.py)     vopt [d, r_min_ratio, r_max_ratio,
#:                                                                                  adapt_r, adapt_q]
#:                                                                                  vout [r̂, q̂_zz] per run
#:   HINF  the extended H∞ posterior with the feasibility cap (estimators/hinf.py)  vopt [θ, margin, prior_cap]
#:                                                                                  vout [samples with θ capped]
VAR_EKF, VAR_AEKF, VAR_HINF = 0, 1, 2


@kernel(inline=True)
def joseph(P, K, H, Rk, n, A, M):
    """``P ← (I − K H) P (I − K H)ᵀ + R_k K Kᵀ`` (pointers; ``A``, ``M`` n × n scratch)."""
    for a in range(n):
        for b in range(n):
            A[a * n + b] = (1.0 if a == b else 0.0) - K[a] * H[b]
    for a in range(n):
        for b in range(n):
            s = 0.0
            for c in range(n):
                s += A[a * n + c] * P[c * n + b]
            M[a * n + b] = s
    for a in range(n):
        for b in range(n):
            s = 0.0
            for c in range(n):
                s += M[a * n + c] * A[b * n + c]
            P[a * n + b] = s + Rk * (K[a] * K[b])


@kernel
def ekf(r0, r1, im, fm, x0, P0, cur, volt, temp, has_temp, dts, hv, nz, walk, Qo, opt, variant, vopt, vout, outf, outb,
        xs, pd, store, failed, failed_at, status, repairs):
    """The EKF family over runs ``r0 … r1 − 1``: linearised prediction and a scalar update that is the EKF's
    (estimators/ekf.py), the adaptive EKF's or the H∞ filter's (``variant``, see :data:`VAR_EKF`)."""
    T = cur.shape[1]
    n = x0.shape[1]
    jac = n > 0  # True, as a run-time value: a literal would make numba compile a copy of every callee
    x, H, K, B, w, P, F, Q, M, V, work, scratch = kalman_buffers(n)
    xn = np.empty(n)
    xe = np.empty(n)  # the equilibrium point and its output Jacobian (parameter scheduling of the output)
    He = np.empty(n)
    PHt = np.empty(n)
    col = np.empty(n)
    A = np.empty((n, n))
    G = np.empty((n, n))
    qh = np.empty((n, n))
    imp, fmp, xp, xnp, Hp, Bp, Fp, sp = ptr(im), ptr(fm), ptr(x), ptr(xn), ptr(H), ptr(B), ptr(F), ptr(scratch)
    Pp, Qp, Mp, Vp, wp, workp, Ap, Kp = ptr(P), ptr(Q), ptr(M), ptr(V), ptr(w), ptr(work), ptr(A), ptr(K)
    xep, Hep = ptr(xe), ptr(He)
    nzp, walkp, Qop, optp = ptr(nz), ptr(walk), ptr(Qo), ptr(opt)
    outfp, outbp, xsp, pdp = ptr(outf), ptr(outb), ptr(xs), ptr(pd)
    R_all = outf.shape[1]
    aekf = variant == VAR_AEKF
    hinf = variant == VAR_HINF
    for r in range(r0, r1):
        load_run(x0, P0, r, n, x, P)
        consecutive = np.int64(0)
        r_hat = 0.0
        capped = 0
        if aekf:
            for a in range(n):
                for b in range(n):
                    qh[a, b] = 0.0
        for k in range(T):
            ik = cur[r, k]
            tk = temp[r, k]
            # ---------------------------------------------------------------- update
            y, D, st = model_output(imp, fmp, xp, ik, tk, has_temp, jac, Hp, sp)
            if st != 0:
                status[r] = st
                break
            if opt[SCHEDULE] != 0.0:  # the output's SOC column is the equilibrium slope (base.scheduled_output)
                _, st = equilibrium(imp, fmp, x[0], tk, has_temp, jac, xep, Hep, n, sp)
                if st != 0:
                    status[r] = st
                    break
                H[0] = He[0]
            Rk = measurement_var(nzp, D)
            r_nom = Rk
            if aekf:
                if k == 0:
                    r_hat = r_nom
                if vopt[3] != 0.0:
                    Rk = r_hat
            S = 0.0
            for a in range(n):
                s = 0.0
                for b in range(n):
                    s += P[a, b] * H[b]
                PHt[a] = s
                S += H[a] * s
            S = S + Rk
            e = volt[r, k] - y
            nis = e * e / S
            gated, consecutive = gate(nis, opt[G_THR], consecutive, opt[G_REL])
            if opt[WIDEN] != 0.0 and not gated and nis > opt[G_THR] and H[0] != 0.0:
                # the gate released: P_zz += max(0, e²/χ² − S)/H_z², so the innovation lies on the gate
                # (safety.widen_on_release); P H and S follow from the widened P
                dz = max(e * e / opt[G_THR] - S, 0.0) / (H[0] * H[0])
                P[0, 0] = P[0, 0] + dz
                PHt[0] = PHt[0] + dz * H[0]
                S = S + H[0] * H[0] * dz
            if hinf:  # the Kalman posterior P_K (ungated), then P⁺ = (P_K⁻¹ − θ_k e_z e_zᵀ)⁻¹ (Sherman–Morrison)
                for a in range(n):
                    K[a] = PHt[a] / S
                    for b in range(n):
                        G[a, b] = P[a, b]
                joseph(Pp, Kp, Hp, Rk, n, Ap, Mp)
                symmetrise(Pp, n)
                pzz = P[0, 0]
                th = vopt[1] / pzz
                if not (th < vopt[0] or th != th):  # np.minimum(θ, ρ / P_zz): NaN propagates
                    th = vopt[0]
                if vopt[2] != 0.0:  # the prior cap, np.minimum(θ_k, np.maximum(1/P_zz − 1/P⁻_zz, 0)) (G: the prior)
                    lim = 1.0 / pzz - 1.0 / G[0, 0]
                    if not (lim > 0.0 or lim != lim):
                        lim = 0.0
                    if not (th < lim or th != th):
                        th = lim
                if th < vopt[0] and not gated:
                    capped += 1
                c = th / (1.0 - th * pzz)
                for a in range(n):
                    col[a] = P[a, 0]
                for a in range(n):
                    for b in range(n):
                        P[a, b] = P[a, b] + c * (col[a] * col[b])
                for a in range(n):
                    if gated:
                        K[a] = 0.0
                    else:
                        s = 0.0
                        for b in range(n):
                            s += P[a, b] * H[b]
                        K[a] = s / Rk
                    x[a] = x[a] + K[a] * e
                if gated:
                    for a in range(n):
                        for b in range(n):
                            P[a, b] = G[a, b]
            else:
                for a in range(n):
                    K[a] = 0.0 if gated else PHt[a] / S
                    x[a] = x[a] + K[a] * e
                joseph(Pp, Kp, Hp, Rk, n, Ap, Mp)
            clamped, bad, repaired = settle(xp, Pp, n, nis, optp, wp, Vp, workp)
            if repaired:
                repairs[r] += 1
            if bad:
                failed[r] = bad
                failed_at[r] = k
                freeze(outf, outb, xs, pd, store, r, k, T, n, x0[r, 0], math.sqrt(P0[r, 0, 0]), volt[r, 0])
                break
            for a in range(n):
                w[a] = P[a, a]
            record(outfp, outbp, xsp, pdp, store, R_all, T, r, k, x[0], math.sqrt(P[0, 0]), y, e, S, clamped, gated,
                   xp, wp, n)
            if aekf and not gated:  # the noise estimates (gated samples do not adapt)
                d = vopt[0]
                HPHt = S - Rk
                rr = (1.0 - d) * r_hat + d * (e * e - HPHt)
                if rr < vopt[1] * r_nom:
                    rr = (1.0 - d) * r_hat + d * e * e
                r_hat = min(max(rr, vopt[1] * r_nom), vopt[2] * r_nom)
                for a in range(n):
                    for b in range(n):
                        qh[a, b] = (1.0 - d) * qh[a, b] + d * ((K[a] * e) * (K[b] * e))
            if k + 1 == T:
                break
            # ---------------------------------------------------------------- predict
            st = model_step(imp, fmp, xp, ik, dts[k], tk, has_temp, jac, xnp, Fp, Bp, sp)
            if st != 0:
                status[r] = st
                break
            if opt[SCHEDULE] != 0.0:  # parameter scheduling: ∂x_j⁺/∂z = 0 but for the SOC (base.scheduled_jacobian)
                for a in range(1, n):
                    F[a, 0] = 0.0
            for a in range(n):
                x[a] = xn[a]
            process_cov(nzp, walkp, Qop, Bp, n, dts[k], nz[IN_VAR], hv[k], Qp)
            if aekf and vopt[4] != 0.0:
                for a in range(n):
                    for b in range(n):
                        Q[a, b] = Q[a, b] + qh[a, b]
            propagate(Fp, Pp, Qp, n, Mp)
            symmetrise(Pp, n)
            bad = diverged_cov(xp, n, Pp, 0.0, np.inf, np.inf)
            if bad:
                failed[r] = bad
                failed_at[r] = k + 1
                freeze(outf, outb, xs, pd, store, r, k + 1, T, n, x0[r, 0], math.sqrt(P0[r, 0, 0]), volt[r, 0])
                break
        if aekf:
            vout[r, 0] = r_hat
            vout[r, 1] = qh[0, 0]
        elif hinf:
            vout[r, 0] = capped
    keep_alive((x, H, K, B, w, P, F, Q, M, V, work, scratch, xn, xe, He, PHt, col, A, G, qh))


# ================================================================================================ UKF
@kernel(inline=True)
def sigma_points(x, P, n, lam, X, L, M, w, V, work):
    """Merwe sigma points of ``(x, P)`` into ``X (2n + 1, n)`` (ukf.sigma_points: Cholesky of (n + λ)P, or the
    symmetric square root when it fails); all pointers, matrices row-major."""
    for a in range(n * n):
        M[a] = (n + lam) * P[a]
    if not cholesky_lower(M, n, L):
        eigh_jacobi(M, n, w, V, work)
        for a in range(n):
            for b in range(n):
                L[a * n + b] = V[a * n + b] * math.sqrt(max(w[b], 0.0))
    for a in range(n):
        X[a] = x[a]
        for j in range(n):
            X[(1 + j) * n + a] = x[a] + L[a * n + j]
            X[(n + 1 + j) * n + a] = x[a] - L[a * n + j]


@kernel
def ukf(r0, r1, im, fm, x0, P0, cur, volt, temp, has_temp, dts, hv, nz, walk, Qo, opt, Wm, Wc, lam, needs_D, needs_B,
        outf, outb, xs, pd, store, failed, failed_at, status, repairs):
    """Unscented Kalman filter (estimators/ukf.py) over runs ``r0 … r1 − 1``."""
    T = cur.shape[1]
    n = x0.shape[1]
    ns = 2 * n + 1
    nojac = n < 0  # False, as a run-time value (see ekf)
    x, H, K, B, w, P, F, Q, M, V, work, scratch = kalman_buffers(n)
    xe = np.empty(n)  # the equilibrium point (parameter scheduling of the output)
    Pxy = np.empty(n)
    Y = np.empty(ns)
    X = np.empty((ns, n))
    Xf = np.empty((ns, n))
    L = np.empty((n, n))
    imp, fmp, Hp, Bp, Fp, sp = ptr(im), ptr(fm), ptr(H), ptr(B), ptr(F), ptr(scratch)
    xp, Pp, Xp, Lp, Mp, Qp, Vp, wp, workp = ptr(x), ptr(P), ptr(X), ptr(L), ptr(M), ptr(Q), ptr(V), ptr(w), ptr(work)
    xep = ptr(xe)
    nzp, walkp, Qop, optp = ptr(nz), ptr(walk), ptr(Qo), ptr(opt)
    outfp, outbp, xsp, pdp = ptr(outf), ptr(outb), ptr(xs), ptr(pd)
    R_all = outf.shape[1]
    for r in range(r0, r1):
        load_run(x0, P0, r, n, x, P)
        consecutive = np.int64(0)
        for k in range(T):
            ik = cur[r, k]
            tk = temp[r, k]
            # ---------------------------------------------------------------- update
            sigma_points(xp, Pp, n, lam, Xp, Lp, Mp, wp, Vp, workp)
            D0 = 0.0
            st = 0
            schedule = opt[SCHEDULE] != 0.0
            zbar = X[0, 0]
            ebar = 0.0
            if schedule:  # y_s = h(X_s|z=z̄) + E(z_s) − E(z̄) (base.scheduled_points_output)
                ebar, st = equilibrium(imp, fmp, zbar, tk, has_temp, nojac, xep, Hp, n, sp)
            for s in range(ns):
                if st != 0:
                    break
                zs = X[s, 0]
                X[s, 0] = zbar if schedule else zs
                y, D, st = model_output(imp, fmp, ptr_at(X, s * n), ik, tk, has_temp, needs_D and s == 0, Hp, sp)
                X[s, 0] = zs
                if st != 0:
                    break
                if schedule:
                    es, st = equilibrium(imp, fmp, zs, tk, has_temp, nojac, xep, Hp, n, sp)
                    y = (y + es) - ebar
                Y[s] = y
                if s == 0:
                    D0 = D
            if st != 0:
                status[r] = st
                break
            Rk = measurement_var(nzp, D0)
            yhat = 0.0
            for s in range(ns):
                yhat += Y[s] * Wm[s]
            S = 0.0
            for a in range(n):
                Pxy[a] = 0.0
            for s in range(ns):
                dy = Y[s] - yhat
                S += dy * dy * Wc[s]
                for a in range(n):
                    Pxy[a] += (X[s, a] - x[a]) * (dy * Wc[s])
            S = S + Rk
            e = volt[r, k] - yhat
            nis = e * e / S
            gated, consecutive = gate(nis, opt[G_THR], consecutive, opt[G_REL])
            for a in range(n):
                K[a] = 0.0 if gated else Pxy[a] / S
                x[a] = x[a] + K[a] * e
            for a in range(n):
                for b in range(n):
                    P[a, b] = P[a, b] - S * (K[a] * K[b])
            clamped, bad, repaired = settle(xp, Pp, n, nis, optp, wp, Vp, workp)
            if repaired:
                repairs[r] += 1
            if bad:
                failed[r] = bad
                failed_at[r] = k
                freeze(outf, outb, xs, pd, store, r, k, T, n, x0[r, 0], math.sqrt(P0[r, 0, 0]), volt[r, 0])
                break
            for a in range(n):
                w[a] = P[a, a]
            record(outfp, outbp, xsp, pdp, store, R_all, T, r, k, x[0], math.sqrt(P[0, 0]), yhat, e, S, clamped,
                   gated, xp, wp, n)
            if k + 1 == T:
                break
            # ---------------------------------------------------------------- predict
            sigma_points(xp, Pp, n, lam, Xp, Lp, Mp, wp, Vp, workp)
            for s in range(ns):
                dz = 0.0
                if schedule:  # every point steps at the mean SOC and keeps its own SOC deviation (base.scheduled_step)
                    dz = X[s, 0] - x[0]
                    X[s, 0] = x[0]
                st = model_step(imp, fmp, ptr_at(X, s * n), ik, dts[k], tk, has_temp, needs_B and s == 0,
                                ptr_at(Xf, s * n), Fp, Bp, sp)
                if st != 0:
                    break
                if schedule:
                    Xf[s, 0] += dz
            if st != 0:
                status[r] = st
                break
            process_cov(nzp, walkp, Qop, Bp, n, dts[k], nz[IN_VAR], hv[k], Qp)
            for a in range(n):
                s_ = 0.0
                for s in range(ns):
                    s_ += Wm[s] * Xf[s, a]
                x[a] = s_
            for a in range(n):
                for b in range(n):
                    s_ = 0.0
                    for s in range(ns):
                        s_ += (Xf[s, a] - x[a]) * Wc[s] * (Xf[s, b] - x[b])
                    P[a, b] = s_ + Q[a, b]
            symmetrise(Pp, n)
            if repair_psd(Pp, n, opt[PSD_ABS], opt[PSD_REL], wp, Vp, workp):
                repairs[r] += 1
            bad = diverged_cov(xp, n, Pp, 0.0, np.inf, np.inf)
            if bad:
                failed[r] = bad
                failed_at[r] = k + 1
                freeze(outf, outb, xs, pd, store, r, k + 1, T, n, x0[r, 0], math.sqrt(P0[r, 0, 0]), volt[r, 0])
                break
    keep_alive((x, H, K, B, w, P, F, Q, M, V, work, scratch, xe, Pxy, Y, X, Xf, L))


# ================================================================================================ coulomb counting
@kernel
def coulomb(r0, r1, im, fm, x0, P0, cur, volt, temp, has_temp, dts, hv, nz, walk, Qo, ratio, outf, outb, xs, pd, store,
            failed, failed_at, status, repairs):
    """Coulomb counting with the declared capacity (estimators/coulomb.py) over runs ``r0 … r1 − 1``."""
    T = cur.shape[1]
    n = x0.shape[1]
    jac = n > 0  # run-time True and False (literals would make numba compile copies of every callee)
    never = n < 0
    x, H, _, B, w, P, F, Q, M, _, _, scratch = kalman_buffers(n)
    xn = np.empty(n)
    imp, fmp, xp, xnp, Hp, Bp, Fp, sp = ptr(im), ptr(fm), ptr(x), ptr(xn), ptr(H), ptr(B), ptr(F), ptr(scratch)
    Pp, Qp, Mp, wp = ptr(P), ptr(Q), ptr(M), ptr(w)
    nzp, walkp, Qop = ptr(nz), ptr(walk), ptr(Qo)
    outfp, outbp, xsp, pdp = ptr(outf), ptr(outb), ptr(xs), ptr(pd)
    R_all = outf.shape[1]
    for r in range(r0, r1):
        load_run(x0, P0, r, n, x, P)
        drift = 0.0
        for k in range(T):
            ik = cur[r, k]
            tk = temp[r, k]
            y, D, st = model_output(imp, fmp, xp, ik, tk, has_temp, jac, Hp, sp)
            if st != 0:
                status[r] = st
                break
            Rk = measurement_var(nzp, D)
            S = 0.0
            for a in range(n):
                s = 0.0
                for b in range(n):
                    s += P[a, b] * H[b]
                S += H[a] * s
            S = S + Rk
            e = volt[r, k] - y
            clamped = clamp_soc(xp)
            var_z = P[0, 0] + nz[BIAS_VAR] * (drift * drift)
            bad = diverged_var(xp, n, var_z, 0.0, np.inf, np.inf)
            if bad:
                failed[r] = bad
                failed_at[r] = k
                freeze(outf, outb, xs, pd, store, r, k, T, n, x0[r, 0], math.sqrt(P0[r, 0, 0]), volt[r, 0])
                break
            for a in range(n):
                w[a] = P[a, a]
            record(outfp, outbp, xsp, pdp, store, R_all, T, r, k, x[0], math.sqrt(var_z), y, e, S, clamped, never, xp,
                   wp, n)
            if k + 1 == T:
                break
            z = x[0]
            st = model_step(imp, fmp, xp, ik, dts[k], tk, has_temp, jac, xnp, Fp, Bp, sp)
            if st != 0:
                status[r] = st
                break
            B[0] *= ratio
            for a in range(n):
                x[a] = xn[a]
            x[0] = z + (xn[0] - z) * ratio
            drift -= B[0]
            process_cov(nzp, walkp, Qop, Bp, n, dts[k], nz[CUR_VAR], hv[k], Qp)
            propagate(Fp, Pp, Qp, n, Mp)
            symmetrise(Pp, n)
    keep_alive((x, H, B, w, P, F, Q, M, scratch, xn))
