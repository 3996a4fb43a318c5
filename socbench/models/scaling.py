"""A model with some of its parameters scaled: the variants the diagnosis' base refit and the fit test's rest fit try.

Resistances, capacitances and their SOC lookups have a ``scaled`` method (a constant times ``s``, a lookup's every
node times ``s``); a leading batch axis on the scales gives one variant per row, so a fit evaluates all its finite-
difference variants in one simulation.
"""

from __future__ import annotations


def refittable_params(model) -> list:
    """The parameters of ``model`` that can be scaled (those with a ``scaled`` method: resistances, capacitances,
    their SOC lookups)."""
    values = model.params.values
    return [p for p in model.required_params() if p in values and hasattr(values[p], "scaled")]


def branch_index(name: str) -> int | None:
    """``j`` of an RC branch's parameter (``R_j``, ``C_j``, ``j ≥ 1``); None for any other (``R0``, …)."""
    j = name[1:]
    return int(j) if name[:1] in ("R", "C") and j.isdigit() and int(j) >= 1 else None


def branch_params(model) -> list:
    """Of :func:`refittable_params`, those of the RC branches (``R1``, ``C1``, ``R2``, …): what a rest's relaxation
    depends on (no current flows, so ``R0`` is not seen)."""
    return [p for p in refittable_params(model) if branch_index(p) is not None]


def scaled_model(model, names, scales):
    """``model`` with each parameter of ``names`` scaled by ``scales[..., m]`` (a leading batch axis gives one variant
    per row)."""
    values = dict(model.params.values)
    for m, p in enumerate(names):
        values[p] = values[p].scaled(scales[..., m])
    return type(model)(model.params.replace(values=values), model.mode)
