"""``socbench leaderboard``: every estimator on every model over every scenario's seeds, ranked.

    socbench leaderboard [--models a,b] [--estimators a,b] [--scenarios a,b] [--seeds N] [--jobs N]
                         [--backend serial|process|dask] [--scheduler ADDR] [--noise model|sensor] [--out DIR]

Defaults: every registered model × coulomb, ekf, ukf, pf × flight-0kg, flight-10kg, dji-m100-replay × 10 seeds
(seeds 0 … N−1), the ``process`` backend on every core, ``--out leaderboard-out``. Writes ``leaderboard.csv``,
``leaderboard.md`` and figures to ``--out``, and keeps every finished fit and cell in ``--out/store``: rerunning the
same command after an interrupt resumes where it stopped and recomputes nothing that had finished.

``--scenarios`` also takes a catalog group: ``measured`` runs every measured-data scenario (Panasonic, CALCE, DJI
flights; ``socbench scenarios`` lists them). A scenario whose data is missing (no ``SOCBENCH_DATA_DIR``) is skipped
with one line; with none left the command says so and exits 0.

``--noise model`` (default) gives every voltage-reading filter the covariances of the noise recipe
(:mod:`socbench.estimators.model_error`: the fitted model's error measured on the scenario's lab tests and validation
flights, or a measured scenario's validation records; never the scored record); ``--noise sensor`` the sensor noise
alone.
"""

from __future__ import annotations

import signal
import sys
import warnings

from ..domain import WARN_FRACTION
from ..errors import ConfigError, DataError, SocbenchWarning
from ..io import output_dir
from ..study import (
    BACKENDS,
    DEFAULT_ESTIMATORS,
    DEFAULT_SCENARIOS,
    DEFAULT_SEEDS,
    Store,
    StudyConfig,
    Toolkit,
    parse_names,
    run_study,
)

DEFAULT_OUT = "leaderboard-out"


def add_arguments(parser) -> None:
    parser.add_argument("--models", help="comma-separated model names (default: every registered model)")
    parser.add_argument("--estimators", help=f"comma-separated estimators (default: {','.join(DEFAULT_ESTIMATORS)})")
    parser.add_argument("--scenarios", help=f"comma-separated scenarios (default: {','.join(DEFAULT_SCENARIOS)})")
    parser.add_argument("--seeds", type=int, default=DEFAULT_SEEDS,
                        help=f"Monte Carlo runs per cell, seeds 0..N-1 (default {DEFAULT_SEEDS})")
    parser.add_argument("--jobs", type=int, default=None, help="worker processes (default: every core)")
    parser.add_argument("--backend", default="process", choices=BACKENDS, help="where cells run (default process)")
    parser.add_argument("--scheduler", help="dask.distributed scheduler address (default: a LocalCluster)")
    parser.add_argument("--out", default=DEFAULT_OUT, help=f"output folder (default ./{DEFAULT_OUT})")
    parser.add_argument("--no-figures", action="store_true", help="skip the figures (tables only)")
    parser.add_argument("--recompute-stale", action="store_true",
                        help="recompute stored fits and cells that were computed by a different version of the code")
    parser.add_argument("--noise", default="model", choices=("model", "sensor"),
                        help="filter covariances: model = the noise recipe (default), sensor = sensor noise only")


def expand_groups(text: str | None, toolkit: Toolkit) -> str | None:
    """``--scenarios`` with catalog group names (``measured``) replaced by their scenarios."""
    if text is None:
        return None
    known = set(toolkit.scenario_names())
    out = []
    for name in (n.strip() for n in str(text).split(",") if n.strip()):
        members = [] if name in known else toolkit.scenario_group(name)
        out.extend(members if members else [name])
    return ",".join(dict.fromkeys(out))


def build_config(args, toolkit: Toolkit, log=print) -> StudyConfig | None:
    """The study to run; None when every requested scenario is unavailable (said on one line each)."""
    if args.seeds is None or args.seeds < 1:
        raise ConfigError(f"--seeds must be at least 1, got {args.seeds}")
    models = parse_names(args.models, toolkit.model_names(), "model", toolkit.model_names())
    estimators = parse_names(args.estimators, toolkit.estimator_names(), "estimator", DEFAULT_ESTIMATORS)
    scenarios = parse_names(expand_groups(args.scenarios, toolkit), toolkit.scenario_names(), "scenario",
                            DEFAULT_SCENARIOS)
    runnable = []
    for name in scenarios:
        why = toolkit.scenario_missing(name)
        if why is None:
            runnable.append(name)
        else:
            log(f"skipping scenario {name}: unavailable ({why})")
    if not runnable:
        return None
    return StudyConfig(models=models, estimators=estimators, scenarios=tuple(runnable),
                       seeds=tuple(range(args.seeds)), noise=getattr(args, "noise", "model"))


def _terminate(signum, frame):
    raise KeyboardInterrupt


#: the error types of a cell that failed on its input (a scenario's record, a parameter file), not on the code
USER_ERRORS = ("DataError: ", "ConfigError: ")


def run(args) -> int:
    from ..report import write_report

    toolkit = Toolkit()
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"--jobs must be at least 1, got {args.jobs}")
    if args.scheduler and args.backend != "dask":
        raise ConfigError("--scheduler needs --backend dask")
    config = build_config(args, toolkit)
    if config is None:
        print("leaderboard: no scenario left to run (the measured-data scenarios need SOCBENCH_DATA_DIR); nothing "
              "written")
        return 0
    out = output_dir(args.out, "--out")
    store = Store(out / "store")
    print(f"leaderboard: {len(config.models)} models × {len(config.estimators)} estimators × "
          f"{len(config.scenarios)} scenarios × {len(config.seeds)} seeds = {config.n_cells} cells "
          f"({args.backend} backend, noise {config.noise}) → {out}", flush=True)
    previous = signal.signal(signal.SIGTERM, _terminate)  # `kill` stops the study as cleanly as Ctrl-C does
    try:
        result = run_study(config, store, backend=args.backend, jobs=args.jobs, scheduler=args.scheduler,
                           toolkit=toolkit, log=lambda msg: print(f"  {msg}", file=sys.stderr, flush=True),
                           recompute_stale=args.recompute_stale)
    finally:
        signal.signal(signal.SIGTERM, previous)
    report = write_report(result, out, figures=not args.no_figures)
    failed = sum(rec["row"]["failed_runs"] for rec in result.cells)
    runs = sum(rec["row"]["n_runs"] for rec in result.cells)
    print(f"{len(result.cells)} cells ({len(result.computed)} computed, {len(result.reused)} reused from the store) "
          f"in {result.seconds:.1f} s; {failed} of {runs} runs failed")
    if result.stale:
        print(f"  warning: {len(result.stale)} fits/cells come from other code (--recompute-stale refreshes them)")
    for sentence in report["best"]:
        print(f"  {sentence}")
    outside = sorted((rec["row"] for rec in result.cells if (rec["row"].get("out_of_domain") or 0) >= WARN_FRACTION),
                     key=lambda r: -r["out_of_domain"])
    if outside:
        w = outside[0]
        warnings.warn(f"{len(outside)} cells spent ≥ {100 * WARN_FRACTION:.0f} % of their samples outside the model's "
                      f"domain (out_of_domain column; worst {w['model']} + {w['estimator']} on {w['scenario']}: "
                      f"{100 * w['out_of_domain']:.1f} %)", SocbenchWarning, stacklevel=2)
    print(f"wrote {out / 'leaderboard.csv'}, {out / 'leaderboard.md'} and {len(report['figures'])} figures")
    # a cell that failed on its input (a scenario's measured record unreadable): the user's to fix, said here too
    user = sorted({e.split(": ", 1)[1] for rec in result.cells
                   if (e := rec.get("error") or "").startswith(USER_ERRORS)})
    if user and all(rec.get("error") for rec in result.cells):
        raise DataError(f"every cell failed on its input; {user[0]}" + (f" (and {len(user) - 1} more, in "
                                                                         "leaderboard.md)" if len(user) > 1 else ""))
    for message in user:
        warnings.warn(f"a cell failed on its input: {message}", SocbenchWarning, stacklevel=2)
    return 0
