"""Choose how to fit by validation: fit with each candidate setting, keep the one that predicts validation records best.

How densely the identification record is sampled after each current edge, and whether each sample is weighted by
the time it stands for, decide which part of the response a fit listens to (the ohmic jump and the first seconds, or
the long relaxations). No setting is best for every model and cell, and the test record must not decide it. So
:func:`select_fit` fits the model once per candidate in :data:`FIT_CANDIDATES`, simulates each fit open loop on the
*validation* records (other drive cycles of the same cell, never the held-out one) and keeps the fit with the lowest
mean validation RMSE. The result lists every candidate's score, so the choice can be checked.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from ..models.registry import make_model
from ..profile import Profile
from .fit import FIT_COMPRESSION, FitResult, fit_model

#: candidate fit settings (keyword arguments of :func:`~socbench.identify.fit.fit_model`)
FIT_CANDIDATES: dict = {
    # kept 0, 1, 5, 21, 85, 341 s after every current change, then every 1200 s: listens to edges
    "edges": {"compress": dict(FIT_COMPRESSION)},
    # kept 0, 1, 3, 7, 15, 31 s after every change, then every 60 s: edges and relaxations alike
    "dense": {"compress": {"first_step_s": 1.0, "growth": 2.0, "max_step_s": 60.0}},
    # the edge grid, each kept sample weighted by the time it stands for: a fit of the uniformly sampled record
    "time-weighted": {"compress": dict(FIT_COMPRESSION), "time_weighted": True},
}


def validation_rmse(fit: FitResult, record: Profile) -> float:
    """Open-loop voltage RMSE of ``fit`` on ``record``, from the record's reference SOC at its start (else the SOC
    the model reads off its first voltage, ``Model.soc_from_voltage``, as the diagnosis starts its simulations)."""
    record.require("voltage_v")
    model = make_model(fit.name, fit.params)
    e = record.voltage_v - model.simulate(record).voltage_v
    return float(np.sqrt(np.mean(e * e))) if np.all(np.isfinite(e)) else float("inf")


@dataclass(frozen=True, eq=False)
class Selection:
    """The chosen fit, its candidate name, and every candidate's validation RMSE (V) per record."""

    fit: FitResult
    chosen: str
    scores: dict  # candidate -> list of validation RMSE, one per record
    fits: dict = field(default_factory=dict, repr=False)  # candidate -> FitResult

    def mean_score(self, candidate: str) -> float:
        return float(np.mean(self.scores[candidate]))


def select_fit(name: str, identification: Profile, validation, mode: str = "paper", candidates: dict | None = None,
               **fit_kwargs) -> Selection:
    """Fit ``name`` on ``identification`` with every candidate setting; keep the best on ``validation`` records.

    A candidate is a dict of :func:`~socbench.identify.fit.fit_model` keywords; one that names its own ``mode``
    overrides ``mode`` (so fit modes can be chosen by validation too)."""
    candidates = dict(FIT_CANDIDATES if candidates is None else candidates)
    validation = list(validation)
    if not candidates or not validation:
        raise ConfigError("select_fit needs at least one candidate setting and one validation record")
    fits, scores = {}, {}
    for label, kw in candidates.items():
        fits[label] = fit_model(name, identification, **{"mode": mode, **fit_kwargs, **kw})
        scores[label] = [validation_rmse(fits[label], rec) for rec in validation]
    chosen = min(scores, key=lambda k: float(np.mean(scores[k])))
    return Selection(fit=fits[chosen], chosen=chosen, scores=scores, fits=fits)
