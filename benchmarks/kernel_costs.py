"""Where a compiled filter's time goes, on one core: the work per run-step of each kernel and of its main pieces.

``socbench bench`` gives wall-time ratios, which on a shared 2-core machine depend on whether the batch's two threads
get both cores. This script measures process CPU time with one thread (``SOCBENCH_THREADS=1`` is set here), the
figure that bounds the single-core ratio, and times the pieces of the particle filter and the model interpreter in
compiled loops of their own (the paper dp model, the bench's sweep: ``socbench.bench.monte_carlo_sweep``):

* ``filters``   EKF (1000 runs × 2000 steps), UKF (100 × 2000), PF (100 particles, 100 runs × 1000 steps): µs of CPU
                per run-step, and for the PF ns per particle-step (minimum over ``--repeats`` after a warm-up run);
* ``model``     the interpreter per point: ``model_step``/``model_output`` one point at a time (with and without
                Jacobians: the EKF's path) and a 100-point cloud at once (``model_*_points``: the PF's path);
* ``normals``   one counter-based normal (``kernels.pf.normals_into``: hashes, Box–Muller with the turn-reduced
                cos/sin) and the libm functions a particle-step calls (``expm1``, ``exp``, ``log``), ns per call in a
                loop of independent calls.

    python benchmarks/kernel_costs.py [--repeats 5] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

os.environ["SOCBENCH_THREADS"] = "1"  # before socbench reads it: one core's work

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from socbench.bench import SENSOR, monte_carlo_sweep  # noqa: E402
from socbench.estimators import SensorNoise, make_estimator  # noqa: E402
from socbench.models import make_model, paper_params  # noqa: E402

POINTS = 100_000


def _min_cpu(fn, repeats: int) -> float:
    fn()  # warm-up (compile or load from the cache)
    best = math.inf
    for _ in range(repeats):
        c0 = time.process_time()
        fn()
        best = min(best, time.process_time() - c0)
    return best


def filters(model, repeats: int) -> dict:
    out = {}
    for name, R, T in (("ekf", 1000, 2000), ("ukf", 100, 2000), ("pf", 100, 1000)):
        prof, soc0, P0 = monte_carlo_sweep(model, R, T, 7)
        opts = {"n_particles": 100} if name == "pf" else {}
        est = make_estimator(name, model, SensorNoise(**SENSOR), engine="compiled", **opts)
        us = _min_cpu(lambda est=est, prof=prof, soc0=soc0, P0=P0: est.run(prof, soc0=soc0, P0=P0, seed=7),
                      repeats) / (R * T) * 1e6
        out[name] = {"runs": R, "steps": T, "cpu_us_per_run_step": us}
        if name == "pf":
            out[name]["cpu_ns_per_particle_step"] = us * 1e3 / 100
    return out


def _compiled_loops():
    """The compiled timing loops (numba, compiled on first use; not cached: this is a script)."""
    import numba

    from socbench.kernels import evaluate as E
    from socbench.kernels.pf import normals_into

    @numba.njit(error_model="numpy")
    def point_loop(im, fm, Z, I, jac, step):
        work = np.empty(E.WORK_SIZE)
        x, xn, F, B, H = np.zeros(3), np.zeros(3), np.zeros(9), np.zeros(3), np.zeros(3)
        s = 0.0
        for p in range(Z.size):
            x[0] = Z[p]
            if step:
                E.model_step(E.ptr(im), E.ptr(fm), E.ptr(x), I[p], 1.0, 25.0, False, jac, E.ptr(xn), E.ptr(F),
                             E.ptr(B), E.ptr(work))
                s += xn[1]
            else:
                y, _, _ = E.model_output(E.ptr(im), E.ptr(fm), E.ptr(x), I[p], 25.0, False, jac, E.ptr(H),
                                         E.ptr(work))
                s += y
        return s

    @numba.njit(error_model="numpy")
    def cloud_loop(im, fm, Z, I, N, step):
        work = np.empty(E.WORK_SIZE)
        X, XN = np.zeros((N, 3)), np.zeros((N, 3))
        F, B, H, Y, D = np.zeros(9), np.zeros(3), np.zeros(3), np.zeros(N), np.zeros(N)
        PW = np.zeros(E.points_scratch(N))
        s = 0.0
        for b in range(Z.size // N):
            for p in range(N):
                X[p, 0] = Z[b * N + p]
            if step:
                E.model_step_points(E.ptr(im), E.ptr(fm), E.ptr(X), N, E.ptr_off(E.ptr(I), b * N), 1.0, 25.0, False,
                                    E.ptr(XN), E.ptr(F), E.ptr(B), E.ptr(work), E.ptr(PW))
                s += XN[0, 1]
            else:
                E.model_output_points(E.ptr(im), E.ptr(fm), E.ptr(X), N, I[b], 25.0, False, E.ptr(Y), E.ptr(D),
                                      E.ptr(H), E.ptr(work), E.ptr(PW))
                s += Y[0]
        return s

    @numba.njit(error_model="numpy")
    def normals_loop(reps, out, scratch):
        s = 0.0
        for k in range(reps):
            normals_into(np.uint64(k * 7919 + 1), E.ptr(out), out.size, E.ptr(scratch))
            s += out[3]
        return s

    @numba.njit(error_model="numpy")
    def libm_loop(u, which):
        s = 0.0
        for p in range(u.size):
            if which == 0:
                s += math.expm1(-u[p])
            elif which == 1:
                s += math.exp(-u[p])
            else:
                s += math.log(u[p])
        return s

    return point_loop, cloud_loop, normals_loop, libm_loop


def pieces(model, repeats: int) -> dict:
    from socbench.kernels.lowering import lower
    from socbench.kernels.pf import normals_scratch

    point_loop, cloud_loop, normals_loop, libm_loop = _compiled_loops()
    L = lower(model)
    im, fm = L.im, np.ascontiguousarray(L.fm[0])
    rng = np.random.default_rng(0)
    # SOCs as a filter sees them: a cloud of 100 close points around a slowly moving mean
    Z = np.repeat(rng.uniform(0.1, 0.9, POINTS // 100), 100) + rng.normal(0.0, 0.005, POINTS)
    current = rng.uniform(-10.0, 40.0, POINTS)
    ns = lambda seconds: seconds / POINTS * 1e9  # noqa: E731
    yes, no = Z.size > 0, Z.size < 0  # run-time booleans
    model_ns = {
        "step_point_jacobians": ns(_min_cpu(lambda: point_loop(im, fm, Z, current, yes, yes), repeats)),
        "output_point_jacobians": ns(_min_cpu(lambda: point_loop(im, fm, Z, current, yes, no), repeats)),
        "step_point": ns(_min_cpu(lambda: point_loop(im, fm, Z, current, no, yes), repeats)),
        "output_point": ns(_min_cpu(lambda: point_loop(im, fm, Z, current, no, no), repeats)),
        "step_cloud_100": ns(_min_cpu(lambda: cloud_loop(im, fm, Z, current, 100, yes), repeats)),
        "output_cloud_100": ns(_min_cpu(lambda: cloud_loop(im, fm, Z, current, 100, no), repeats)),
    }
    out = np.empty(100)
    scratch = np.empty(normals_scratch(100))
    reps = POINTS // 100
    u = rng.uniform(0.01, 1.0, POINTS)
    draw_ns = {
        "normal": ns(_min_cpu(lambda: normals_loop(reps, out, scratch), repeats)),
        "libm_expm1": ns(_min_cpu(lambda: libm_loop(u, 0), repeats)),
        "libm_exp": ns(_min_cpu(lambda: libm_loop(u, 1), repeats)),
        "libm_log": ns(_min_cpu(lambda: libm_loop(u, 2), repeats)),
    }
    return {"model_ns_per_point": model_ns, "ns_per_call": draw_ns}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    model = make_model("dp", paper_params("dp"))
    result = {"loadavg": list(os.getloadavg()), "filters": filters(model, args.repeats),
              **pieces(model, args.repeats)}
    result["loadavg_after"] = list(os.getloadavg())
    f = result["filters"]
    print(f"one core, dp model (load {result['loadavg'][0]:.1f} → {result['loadavg_after'][0]:.1f}):")
    for name, row in f.items():
        extra = f", {row['cpu_ns_per_particle_step']:.0f} ns per particle-step" if name == "pf" else ""
        print(f"  {name}: {row['cpu_us_per_run_step']:.3f} µs CPU per run-step ({row['runs']} runs × "
              f"{row['steps']} steps){extra}")
    print("  model, ns per point: " + ", ".join(f"{k} {v:.1f}" for k, v in result["model_ns_per_point"].items()))
    print("  ns per call: " + ", ".join(f"{k} {v:.1f}" for k, v in result["ns_per_call"].items()))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
