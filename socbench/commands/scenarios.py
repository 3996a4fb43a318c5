"""``socbench scenarios [--details]``: the scenario catalog, one line each (``--details``: the key numbers)."""

from __future__ import annotations

from ..scenarios import load_scenario, scenario_names


def add_arguments(parser) -> None:
    parser.add_argument("--details", action="store_true",
                        help="also run each scenario's truth once and print duration, mean current and stop reason")


def run(args) -> int:
    names = scenario_names()
    print(f"{len(names)} scenarios in the catalog\n")
    print(f"{'name':<16} {'kind':<8} description")
    for name in names:
        sc = load_scenario(name)
        print(sc.summary())
        if args.details:
            rec = sc.truth_record()
            loaded = rec.current[0] != 0
            print(f"{'':<16} {'':<8} {rec.time[-1] / 60:.1f} min, mean |I| under load "
                  f"{abs(rec.current[0][loaded]).mean():.1f} A, stop: {rec.stop_reason}, declared capacity "
                  f"{sc.declared_capacity_ah:.2f} Ah (true {sc.true_capacity_ah:.2f})")
    return 0
