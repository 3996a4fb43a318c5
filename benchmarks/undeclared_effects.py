"""Randomised undeclared-effect benchmark: how often the closed loop names an effect hidden in data it never saw.

    python benchmarks/undeclared_effects.py --cases 200 --seed 2026 --jobs 2 \\
        --json docs/undeclared_effects.json --md docs/undeclared_effects.md

Each case is drawn by :mod:`socbench.diagnose.randomized` (truth cell, fit test, evaluation records; zero, one or two
hidden effects at physical magnitudes) and diagnosed with the defaults of ``socbench diagnose`` given only the base
model's name and the records. Rates (one row per effect, so a weak effect shows):

* single-effect cases: hidden effect named first; held-out voltage RMSE cut by ≥ 30 %;
* two-effect cases: both effects named;
* null cases: nothing added;
* every case: the held-out SOC error of the EKF and of the UKF not worse by more than 0.2 points.

``--refine-ocv coarse|never`` runs the diagnosis with that refinement of the HPPC's rest-point OCV instead of the
default ``always`` (``socbench diagnose --refine-ocv``), for comparisons.

``--oracle`` diagnoses every single-effect case once more with the hidden effect as the only candidate: how often
it is added then bounds what any ranking of the candidates can name first (docs/undeclared_effects_oracle.md).

Every finished case is appended to ``OUT.json.cases.jsonl`` at once, so an interrupted run keeps what it finished;
``--resume`` skips the cases already there. Wall time and CPU seconds are measured here, per case and in total.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one core per worker
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

# --refine-ocv → the diagnosis' refine_ocv, read as `socbench diagnose` reads it
from socbench.commands.diagnose import REFINE_OCV_OPTION as REFINE_OCV  # noqa: E402
from socbench.diagnose.randomized import (  # noqa: E402
    TARGETS,
    case_kind,
    draw_case,
    markdown,
    oracle_accepted,
    pooled_markdown,
    rates,
    run_case,
)
from socbench.kernels.engine import share_cores  # noqa: E402


def one(index: int, seed: int, oracle: bool = False, refine_ocv: str = "always") -> dict:
    import warnings

    warnings.filterwarnings("ignore")
    w0, c0 = time.perf_counter(), time.process_time()
    try:
        case = draw_case(index, seed)
    except Exception as exc:  # a generator failure is reported with the case, never hidden or fatal to the run
        kind, _ = case_kind(index)
        return {"index": index, "seed": seed, "kind": kind, "effects": [], "added": [], "first": None,
                "error": f"generator: {type(exc).__name__}: {exc}", "wall_s": 0.0, "cpu_s": 0.0,
                "case_wall_s": time.perf_counter() - w0, "case_cpu_s": time.process_time() - c0}
    gen = time.process_time() - c0
    options = {"refine_ocv": REFINE_OCV[refine_ocv]}
    r = run_case(case, **options)
    if oracle:
        o0 = time.perf_counter()
        r["oracle_added"] = oracle_accepted(case, **options)
        r["oracle_wall_s"] = time.perf_counter() - o0
    r["generate_cpu_s"] = gen
    r["case_wall_s"] = time.perf_counter() - w0
    r["case_cpu_s"] = time.process_time() - c0
    return r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--json", help="summary JSON (rates, rows, every case); required unless --pool")
    ap.add_argument("--md", help="Markdown table")
    ap.add_argument("--resume", action="store_true", help="keep the finished cases of OUT.json.cases.jsonl")
    ap.add_argument("--oracle", action="store_true",
                    help="diagnose each single-effect case again with the hidden effect as the only candidate "
                         "(an upper bound on naming it first; its time is not in the diagnosis times)")
    ap.add_argument("--refine-ocv", default="always", choices=tuple(REFINE_OCV),
                    help="the diagnosis' refinement of an HPPC's rest-point OCV (socbench diagnose --refine-ocv)")
    ap.add_argument("--render-only", action="store_true",
                    help="recompute the rates from the cases stored in the JSON (--json), write them back, and rewrite "
                         "the Markdown (--md); no case is run again")
    ap.add_argument("--pool", nargs="+", metavar="JSON",
                    help="print the rates over the cases of these runs' JSONs together (and write them to --md); "
                         "no case is run")
    args = ap.parse_args(argv)
    if args.pool:
        text = pooled_markdown([json.loads(Path(p).read_text()) for p in args.pool])
        if args.md:
            Path(args.md).write_text(text)
        print(text)
        return 0
    if not args.json:
        ap.error("--json is required (unless --pool)")
    if args.render_only:
        summary = json.loads(Path(args.json).read_text())
        summary["rates"] = rates(summary["results"])
        Path(args.json).write_text(json.dumps(summary, indent=1, default=float))
        text = markdown(summary)
        if args.md:
            Path(args.md).write_text(text)
        print(text)
        return 0
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    log = Path(str(out) + ".cases.jsonl")
    done = {}
    if args.resume and log.exists():
        for line in log.read_text().splitlines():
            r = json.loads(line)
            if r["seed"] == args.seed:
                done[r["index"]] = r
    elif log.exists():
        log.unlink()
    todo = [k for k in range(args.cases) if k not in done]
    w0, c0 = time.perf_counter(), time.process_time()
    results = dict(done)
    with log.open("a") as f:
        if args.jobs > 1:
            share_cores(args.jobs)  # the compiled kernels' batches: cores // jobs threads per worker
            with ProcessPoolExecutor(args.jobs) as pool:
                futures = {pool.submit(one, k, args.seed, args.oracle, args.refine_ocv): k for k in todo}
                for fut in as_completed(futures):
                    r = fut.result()
                    results[r["index"]] = r
                    f.write(json.dumps(r, default=float) + "\n")
                    f.flush()
                    print(f"[{len(results)}/{args.cases}] case {r['index']} {r['kind']} {r['effects']} -> "
                          f"{r['added']} ({r['case_cpu_s']:.1f} s CPU)", flush=True)
        else:
            for k in todo:
                r = one(k, args.seed, args.oracle, args.refine_ocv)
                results[k] = r
                f.write(json.dumps(r, default=float) + "\n")
                f.flush()
                print(f"[{len(results)}/{args.cases}] case {k} {r['kind']} {r['effects']} -> {r['added']} "
                      f"({r['case_cpu_s']:.1f} s CPU)", flush=True)
    wall = time.perf_counter() - w0
    cases = [results[k] for k in sorted(results)]
    cpu = [r["case_cpu_s"] for r in cases]
    summary = {
        "command": "python benchmarks/undeclared_effects.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "cases": len(cases), "seed": args.seed, "jobs": args.jobs,
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "wall_s": wall if not done else None, "cpu_s": float(np.sum(cpu)),
        "case_cpu_median_s": float(np.median(cpu)), "case_cpu_max_s": float(np.max(cpu)),
        "diagnosis_wall_max_s": float(max(r["wall_s"] for r in cases)),
        "main_process_cpu_s": time.process_time() - c0,
        "targets": TARGETS, "rates": rates(cases), "results": cases,
    }
    if summary["wall_s"] is None:  # resumed: the wall time of this invocation alone would mislead
        summary["wall_s"] = float("nan")
    out.write_text(json.dumps(summary, indent=1, default=float))
    if args.md:
        Path(args.md).write_text(markdown(summary))
    print(markdown(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
