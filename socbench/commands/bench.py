"""``socbench bench [--quick] --json OUT.json``: batched engines against a loop of filterpy runs, side by side.

Full mode: 200 Monte Carlo runs × 3600 steps per batched engine, the filterpy references on a subset, fitting every
model, the default leaderboard. ``--quick`` (under a minute on an idle machine): a smaller sweep, every model fitted
with at most 2 least-squares evaluations (the fitting pipeline's fixed cost), no leaderboard. What is measured is in
:mod:`socbench.bench`; the figures and how to read them are in docs/performance.md.
"""

from __future__ import annotations

import argparse
import json

from ..errors import ConfigError


def add_arguments(parser) -> None:
    parser.add_argument("--quick", action="store_true", help="a small sweep and no leaderboard (under a minute)")
    parser.add_argument("--json", required=True, help="write the measurements here")
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats per measurement (default 3, >= 3)")
    parser.add_argument("--estimators", default=None,
                        help="comma-separated subset of the estimators with a reference backend (default all)")
    parser.add_argument("--tiny", action="store_true", help=argparse.SUPPRESS)  # smoke-test sizes for the tests


def run(args) -> int:
    from ..bench import ESTIMATORS, run_bench, sizes_for
    from ..io import atomic_write_text

    if args.repeats is not None and args.repeats < 3:
        raise ConfigError(f"--repeats must be at least 3 (medians of repeated runs), got {args.repeats}")
    names = ESTIMATORS if not args.estimators else tuple(s.strip() for s in args.estimators.split(",") if s.strip())
    unknown = [n for n in names if n not in ESTIMATORS]
    if unknown or not names:
        raise ConfigError(f"--estimators: unknown '{unknown[0] if unknown else ''}'; known: {', '.join(ESTIMATORS)}")
    sizes, mode = sizes_for(quick=args.quick, tiny=args.tiny, repeats=args.repeats)
    def save(partial):  # after every stage: an interrupted run keeps what it measured ("complete": false)
        atomic_write_text(args.json, json.dumps(partial, indent=2))

    result = run_bench(sizes, mode, names, log=lambda msg: print(msg, flush=True), checkpoint=save)
    save(result)
    m = result["machine"]
    print(f"\n{'':6}{'batched µs/run-step':>20}{'filterpy µs/step':>18}{'speed-up':>10}{'max |diff|':>12}")
    for n in names:
        print(f"{n:6}{result[f'{n}_batched_us_per_run_step']:>20.2f}{result[f'{n}_filterpy_us_per_step']:>18.1f}"
              f"{result[f'{n}_speedup']:>9.0f}×{result[f'{n}_max_abs_diff']:>12.1e}")
    board = result["default_leaderboard_s"]
    print(f"fit all models: {result['fit_all_models_s']:.1f} s ({result['fit_data']}, {result['fit_effort']} effort); "
          "default leaderboard: "
          + ("skipped" if board is None else f"{board:.1f} s"))
    print(f"identical results (≤ {result['tolerance']:g}): {'yes' if result['identical_results'] else 'NO'}; "
          f"{m['cpu_count']} CPUs, numpy {m['numpy_version']}, Python {m['python_version']}, "
          f"load {m['loadavg'][0]:.1f}" if m["loadavg"] else "")
    print(f"wrote {args.json}")
    return 0 if result["identical_results"] else 1
