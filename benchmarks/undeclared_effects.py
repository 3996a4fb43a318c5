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

from socbench.diagnose.randomized import CUT, SOC_SLACK, draw_case, rates, run_case  # noqa: E402

TARGETS = {  # issue 13, "Must show"
    "named_first_single": 0.90,
    "cut_30_single": 0.90,
    "nothing_added_null": 0.95,
    "both_named_pair": 0.70,
    "soc_not_worse": 0.90,
}
LABELS = {
    "named_first_single": "hidden effect named first (single-effect cases)",
    "cut_30_single": f"held-out voltage RMSE cut ≥ {100 * CUT:.0f} % (single-effect cases)",
    "nothing_added_null": "nothing added (null cases)",
    "both_named_pair": "both effects named (two-effect cases)",
    "soc_not_worse": f"held-out SOC RMSE not worse by > {100 * SOC_SLACK:.1f} points, EKF and UKF (all cases)",
}


def one(index: int, seed: int) -> dict:
    import warnings

    warnings.filterwarnings("ignore")
    w0, c0 = time.perf_counter(), time.process_time()
    case = draw_case(index, seed)
    gen = time.process_time() - c0
    r = run_case(case)
    r["generate_cpu_s"] = gen
    r["case_wall_s"] = time.perf_counter() - w0
    r["case_cpu_s"] = time.process_time() - c0
    return r


def _pct(x):
    return "–" if x is None else f"{100 * x:.0f} %"


def markdown(summary: dict) -> str:
    R = summary["rates"]
    L = [f"Command: `{summary['command']}` — {summary['cases']} cases, seed {summary['seed']}, {summary['jobs']} "
         f"worker process(es) on {summary['machine']}; wall time {summary['wall_s']:.0f} s, CPU "
         f"{summary['cpu_s']:.0f} s in total (per case: median {summary['case_cpu_median_s']:.1f} s, max "
         f"{summary['case_cpu_max_s']:.1f} s CPU; slowest diagnosis {summary['diagnosis_wall_max_s']:.1f} s wall).",
         "", "| rate | measured | target | met |", "|---|---|---|---|"]
    for key, target in TARGETS.items():
        v = R[key]
        met = "yes" if v["rate"] is not None and v["rate"] >= target else "**no**"
        L.append(f"| {LABELS[key]} | {v['hits']}/{v['n']} = {_pct(v['rate'])} | ≥ {100 * target:.0f} % | {met} |")
    L += ["", "Per effect (single-effect cases; pairs: named when it was one of the two hidden; footprint: RMS voltage "
          "the hidden effect adds on the evaluation records over the voltage noise, median; wrongly first: cases "
          "where it was named first without being hidden):", "",
          "| effect | single cases | named first | RMSE cut ≥ 30 % | SOC not worse | footprint / noise | "
          "in pairs | named in pair | wrongly first |", "|---|---|---|---|---|---|---|---|---|"]
    for row in R["rows"]:
        fp = "–" if row["median_footprint"] is None else f"{row['median_footprint']:.1f}"
        L.append(f"| {row['effect']} | {row['single']} | {_pct(row['named_first'])} | {_pct(row['cut_30'])} | "
                 f"{_pct(row['soc_not_worse'])} | {fp} | {row['pairs']} | {_pct(row['named_in_pair'])} | "
                 f"{row['wrongly_first']} |")
    if R["errors"]:
        L += ["", f"{R['errors']} case(s) stopped with an error (counted as misses)."]
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--json", required=True, help="summary JSON (rates, rows, every case)")
    ap.add_argument("--md", help="Markdown table")
    ap.add_argument("--resume", action="store_true", help="keep the finished cases of OUT.json.cases.jsonl")
    args = ap.parse_args(argv)
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
            with ProcessPoolExecutor(args.jobs) as pool:
                futures = {pool.submit(one, k, args.seed): k for k in todo}
                for fut in as_completed(futures):
                    r = fut.result()
                    results[r["index"]] = r
                    f.write(json.dumps(r, default=float) + "\n")
                    f.flush()
                    print(f"[{len(results)}/{args.cases}] case {r['index']} {r['kind']} {r['effects']} -> "
                          f"{r['added']} ({r['case_cpu_s']:.1f} s CPU)", flush=True)
        else:
            for k in todo:
                r = one(k, args.seed)
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
