"""How the cost of the batched engines grows with runs, steps, particles and states (docs/performance.md).

    python benchmarks/scaling.py [--repeats 3] [--json OUT.json] [--small]

One sweep per axis, everything else held at a base setting (dp on the paper pack, the Monte Carlo sweep of
``socbench bench``): runs R, steps T (EKF, UKF, PF), particles N (PF), states n (EKF, UKF on R0 + k RC chains,
n = k + 1).
Each cell is the median of ``--repeats`` runs; both wall and process-CPU time are reported (CPU time is the steadier
figure on a shared machine) as µs per run-step and as ms per step of the whole batch. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from socbench.bench import SENSOR, machine, monte_carlo_sweep  # noqa: E402
from socbench.estimators import SensorNoise, make_estimator  # noqa: E402
from socbench.models import make_model, paper_params  # noqa: E402
from socbench.models.params import Constant  # noqa: E402


def chain_model(k: int):
    """R0 + k RC branches (``nrc``) on the paper pack: dp's two polynomial branches, then constant slower ones."""
    base = paper_params("dp")
    values = {name: base.values[name] for name in ("R0", "R1", "C1", "R2", "C2") if int(name[1:]) <= k}
    for j in range(3, k + 1):
        values[f"R{j}"] = Constant(0.002)
        values[f"C{j}"] = Constant(2e4 * 3.0**j)
    return make_model("nrc", dataclasses.replace(base, values=values))


def measure(model, estimator: str, runs: int, steps: int, particles: int, repeats: int) -> dict:
    profile, soc0, P0 = monte_carlo_sweep(model, runs, steps, seed=7)
    opts = {"n_particles": particles} if estimator == "pf" else {}
    est = make_estimator(estimator, model, SensorNoise(**SENSOR), **opts)
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        est.run(profile, soc0=soc0, P0=P0, seed=1)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    w, c = statistics.median(wall), statistics.median(cpu)
    return {"estimator": estimator, "model": model.name, "states": model.n_states, "runs": runs, "steps": steps,
            "particles": particles if estimator == "pf" else None,
            "wall_us_per_run_step": w / (runs * steps) * 1e6, "cpu_us_per_run_step": c / (runs * steps) * 1e6,
            "cpu_ms_per_step": c / steps * 1e3, "wall_s": wall, "cpu_s": cpu}


def sweeps(small: bool):
    base_T = 200 if small else 600
    runs = (1, 10, 100, 1000) if not small else (1, 10, 100)
    for est in ("ekf", "ukf"):
        for R in runs:
            yield "runs", est, 2, R, base_T, 0
        for T in (base_T // 2, base_T, 4 * base_T):
            yield "steps", est, 2, 100, T, 0
        for k in (1, 2, 4, 6):
            yield "states", est, k, 100, base_T, 0
    for R in runs[:-1] + ((200,) if not small else ()):
        yield "runs", "pf", 2, R, base_T // 2, 50
    for N in (25, 50, 100, 200):
        yield "particles", "pf", 2, 50, base_T // 2, N


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None)
    ap.add_argument("--small", action="store_true", help="smaller sweeps (a minute or two)")
    args = ap.parse_args(argv)
    rows = []
    models = {}
    print("| axis | estimator | states n | runs R | steps T | particles N | CPU µs/run-step | wall µs/run-step "
          "| CPU ms/step (batch) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for axis, est, k, R, T, N in sweeps(args.small):
        model = models.setdefault(k, chain_model(k))
        row = {"axis": axis, **measure(model, est, R, T, N, args.repeats)}
        rows.append(row)
        print(f"| {axis} | {est} | {row['states']} | {R} | {T} | {N or '–'} | {row['cpu_us_per_run_step']:.2f} | "
              f"{row['wall_us_per_run_step']:.2f} | {row['cpu_ms_per_step']:.3f} |", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine(), "repeats": args.repeats, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
