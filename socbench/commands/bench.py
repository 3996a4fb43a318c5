"""``socbench bench [--quick] --json OUT.json``: socbench's engines against a bare filterpy loop and its references.

Full mode: EKF/UKF at 1 … 10 000 runs and the PF at 1 … 1000 runs against the bare filterpy loop (numpy and compiled
engines), every estimator against its reference on 200 runs × 3600 steps, a cold compile, fitting every model,
``socbench estimate`` on the Panasonic US06 (with the data), the default leaderboard. ``--quick`` (under a minute on an
idle machine once the kernels are compiled): fewer run counts and steps, every model fitted with at most 2
least-squares evaluations, no cold compile, no leaderboard. What is measured is in :mod:`socbench.bench`; the figures
and how to read them are in docs/performance.md.
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
    from ..bench import ESTIMATORS, SCALED, run_bench, sizes_for
    from ..io import atomic_write_text, output_file

    output_file(args.json, "--json")
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
    scaled = [n for n in SCALED if n in names]
    if scaled:
        print("\nµs per run-step (speed-up against the bare filterpy loop)")
        for n in scaled:
            runs = list(result[f"{n}_compiled_us_per_run_step"])
            print(f"{n:4} bare filterpy {result[f'{n}_bare_us_per_step']:.1f} µs/step; compiled "
                  + ", ".join(f"R={R}: {result[f'{n}_compiled_us_per_run_step'][R]:.3g} "
                              f"({result[f'{n}_compiled_speedup_vs_bare'][R]:.0f}×)" for R in runs))
            print(f"{'':5}numpy " + ", ".join(f"R={R}: {result[f'{n}_numpy_us_per_run_step'][R]:.3g} "
                                             f"({result[f'{n}_numpy_speedup_vs_bare'][R]:.1f}×)" for R in runs))
    print(f"\n{'':7}{'engine':>9}{'socbench µs/run-step':>22}{'reference µs/step':>19}{'max |diff|':>12}"
          f"{'compiled−numpy':>16}")
    for n in names:
        print(f"{n:7}{result[f'{n}_engine']:>9}{result[f'{n}_sweep_us_per_run_step']:>22.2f}"
              f"{result[f'{n}_reference_us_per_step']:>19.1f}{result[f'{n}_max_abs_diff']:>12.1e}"
              f"{result[f'{n}_compiled_vs_numpy_max_abs_diff']:>16.1e}")
    board = result["default_leaderboard_s"]
    first = result.get("first_call_s") or {}
    cold = result.get("cold_compile")
    print(f"kernels: first call {first.get('total', 0.0):.1f} s in this process"
          + (f"; cold compile {cold['wall_s']:.1f} s wall, {cold['cpu_s']:.1f} CPU-s" if cold else ""))
    us06 = result.get("estimate_us06_s")
    if us06:
        print(f"socbench estimate on {us06['data']}: EKF {us06['ekf']:.2f} s, UKF {us06['ukf']:.2f} s")
    print(f"fit all models: {result['fit_all_models_s']:.1f} s ({result['fit_data']}, {result['fit_effort']} effort); "
          "default leaderboard: "
          + ("skipped" if board is None else f"{board:.1f} s"))
    print(f"identical results (≤ {result['tolerance']:g}): {'yes' if result['identical_results'] else 'NO'}; "
          f"{m['cpu_count']} CPUs, numpy {m['numpy_version']}, Python {m['python_version']}, "
          f"load {m['loadavg'][0]:.1f}" if m["loadavg"] else "")
    print(f"wrote {args.json}")
    return 0 if result["identical_results"] else 1
