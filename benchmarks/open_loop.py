"""Whole-record open loop (prefix scan) against the step loop, per registered model, side by side.

Each model (its reference parameter set) simulates the same record both ways: ``Model.open_loop`` (the SOC path as a
running sum, the other states by prefix scans: ``socbench.models.recurrence``) and ``Model.open_loop_stepwise`` (one
``output`` and one ``step`` call per sample), alternating, ``--repeats`` times; medians of wall time, and the largest
difference between the two voltages. ``--batch`` parameter-free copies of the initial state are run at once (a fit
runs P + 1 parameter variants).

    python benchmarks/open_loop.py [--steps 3000] [--batch 36] [--repeats 3] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from socbench.models import make_model, model_names, paper_params  # noqa: E402


def record(steps: int, capacity_ah: float, seed: int = 0):
    """Pulses of 30 samples between −1 C and 2 C at 1 s, with a rest level: a dynamic record of ``steps`` samples."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps, dtype=float)
    levels = rng.choice([0.0, 0.5, 1.0, 2.0, -1.0], size=steps // 30 + 1) * capacity_ah
    return t, np.repeat(levels, 30)[:steps]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=36)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    out = {}
    load_start = os.getloadavg()[0]
    for name in model_names():
        model = make_model(name, paper_params(name))
        t, i = record(args.steps, model.capacity_ah)
        x0 = model.x0(np.full(args.batch, 0.95))
        fast, loop = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            y_fast = model.open_loop(x0, t, i)[1]
            t1 = time.perf_counter()
            y_loop = model.open_loop_stepwise(x0, t, i)[1]
            t2 = time.perf_counter()
            fast.append(t1 - t0)
            loop.append(t2 - t1)
        f, s = float(np.median(fast)), float(np.median(loop))
        diff = float(np.max(np.abs(y_fast - y_loop)))
        out[name] = {"scan_s": f, "loop_s": s, "speedup": s / f, "max_abs_diff_v": diff}
        print(f"{name:12s} scan {1000 * f:8.2f} ms  loop {1000 * s:8.1f} ms  ×{s / f:7.0f}  "
              f"max |Δy| {out[name]['max_abs_diff_v']:.1e} V", flush=True)
    print(f"{args.batch} states × {args.steps} steps, median of {args.repeats}; load average {load_start:.1f}, "
          f"{os.cpu_count()} cores")
    if args.json:
        Path(args.json).write_text(json.dumps({"steps": args.steps, "batch": args.batch, "repeats": args.repeats,
                                               "load_start": load_start, "models": out}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
