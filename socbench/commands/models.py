"""``socbench models``: the model registry (name, states, parameters, source)."""

from __future__ import annotations

from ..models import model_class, model_names, paper_params
from ..models.registry import make_model


def add_arguments(parser) -> None:
    parser.add_argument("--verbose", "-v", action="store_true", help="also print what was corrected against the paper")


def describe(name: str) -> dict:
    """Name, title, state names, parameter names and source of a registered model (on its paper parameter set)."""
    cls = model_class(name)
    model = make_model(name, paper_params(name))
    return {
        "name": name,
        "paper_number": cls.paper_number,
        "title": cls.title,
        "states": list(model.state_names),
        "params": list(model.required_params()),
        "source": cls.source,
        "corrections": cls.corrections,
    }


def run(args) -> int:
    rows = [describe(n) for n in model_names()]
    print(f"{len(rows)} models registered\n")
    print(f"{'#':>2}  {'name':<12} {'states':<26} {'parameters':<34} source")
    for r in rows:
        num = "" if r["paper_number"] is None else str(r["paper_number"])
        print(f"{num:>2}  {r['name']:<12} {','.join(r['states']):<26} {','.join(r['params']):<34} {r['source']}")
        if args.verbose and r["corrections"]:
            print(f"    corrected: {r['corrections']}")
    return 0
