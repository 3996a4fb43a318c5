"""``socbench scenarios [NAME_OR_PATH ...] [--details]``: the scenario catalog, one line each.

With names or TOML paths, only those are listed (a bad file is a one-line error, exit 2); ``--details`` also runs each
scenario's truth once and prints its duration, mean current under load and stop reason.
"""

from __future__ import annotations

from ..scenarios import load_scenario, scenario_names


def add_arguments(parser) -> None:
    parser.add_argument("scenarios", nargs="*", metavar="NAME_OR_PATH",
                        help="catalog names or scenario TOML files (default: the whole catalog)")
    parser.add_argument("--details", action="store_true",
                        help="also run each scenario's truth once: duration, mean current under load, stop reason")


def run(args) -> int:
    scenarios = [load_scenario(n) for n in (args.scenarios or scenario_names())]
    if not args.scenarios:
        print(f"{len(scenarios)} scenarios in the catalog\n")
    print(f"{'name':<16} {'kind':<8} description")
    for sc in scenarios:
        print(sc.summary())
        if args.details:
            rec = sc.truth_record()
            loaded = rec.current[0] != 0
            print(f"{'':<16} {'':<8} {rec.time[-1] / 60:.1f} min, mean |I| under load "
                  f"{abs(rec.current[0][loaded]).mean():.1f} A, stop: {rec.stop_reason}, declared capacity "
                  f"{sc.declared_capacity_ah:.2f} Ah (true {sc.true_capacity_ah:.2f})")
    return 0
