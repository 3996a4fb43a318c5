"""Choose how to fit by validation: fit with each candidate setting, keep the one that predicts validation records best.

How densely the identification record is sampled after each current edge, and whether each sample is weighted by
the time it stands for, decide which part of the response a fit listens to (the ohmic jump and the first seconds, or
the long relaxations). No setting is best for every model and cell, and the test record must not decide it. So
:func:`select_fit` fits the model once per candidate in :data:`FIT_CANDIDATES`, simulates each fit open loop on the
*validation* records (other drive cycles of the same cell, never the held-out one) and keeps the fit with the lowest
mean validation RMSE. The result lists every candidate's score, so the choice can be checked.

A characterisation campaign over several temperatures (:func:`select_temperature_fit`) chooses the same way among
:data:`FIT_SETTINGS` (the SOC form × the sample weighting), then tries two more candidates: a setting **per
temperature** (each identification record fitted with the setting whose fit predicts the validation records nearest
its temperature best: what suits the warm cell need not suit the cold one) and the chosen one with the **charge-transfer
term** (:func:`~socbench.identify.temperature.fit_temperatures` ``charge_transfer=True``); each is kept only if it
lowers the mean validation RMSE.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, DataError, ModelError
from ..models.registry import make_model
from ..profile import Profile
from .fit import FIT_COMPRESSION, FitResult, fit_model
from .hppc import gap_soc_jumps
from .temperature import TemperatureFit, fit_temperatures, record_temperature

#: candidate fit settings (keyword arguments of :func:`~socbench.identify.fit.fit_model`)
FIT_CANDIDATES: dict = {
    # kept 0, 1, 5, 21, 85, 341 s after every current change, then every 1200 s: listens to edges
    "edges": {"compress": dict(FIT_COMPRESSION)},
    # kept 0, 1, 3, 7, 15, 31 s after every change, then every 60 s: edges and relaxations alike
    "dense": {"compress": {"first_step_s": 1.0, "growth": 2.0, "max_step_s": 60.0}},
    # the edge grid, each kept sample weighted by the time it stands for: a fit of the uniformly sampled record
    "time-weighted": {"compress": dict(FIT_COMPRESSION), "time_weighted": True},
}


def validation_rmse(fit, record: Profile) -> float:
    """Open-loop voltage RMSE of ``fit`` (a :class:`FitResult`, or a model) on ``record``, from the record's reference
    SOC at its start (else the SOC the model reads off its first voltage, ``Model.soc_from_voltage``, as the diagnosis
    starts its simulations), the charge its reference holds across gaps taken as the fit takes it
    (:func:`~socbench.identify.hppc.gap_soc_jumps`)."""
    record.require("voltage_v")
    model = make_model(fit.name, fit.params) if isinstance(fit, FitResult) else fit
    e = record.voltage_v - model.simulate(record, soc_jumps=gap_soc_jumps(record, model.capacity_ah)).voltage_v
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


#: the fit settings a campaign chooses among: the paper's SOC polynomials or a piecewise-linear SOC lookup, each with
#: the sample weightings of :data:`FIT_CANDIDATES`
FIT_SETTINGS: dict = {f"{mode}/{label}": {"mode": mode, **kw} for mode in ("paper", "lookup")
                      for label, kw in FIT_CANDIDATES.items()}
#: the label of the candidate with a setting per temperature
PER_TEMPERATURE = "per temperature"
#: the label suffix of the chosen setting fitted again with the charge-transfer term
CT_SUFFIX = " + charge transfer"
#: what a failed candidate fit raises (it is reported, not fatal, while another candidate fits)
FIT_ERRORS = (ModelError, DataError, FloatingPointError, np.linalg.LinAlgError)


@dataclass(frozen=True, eq=False)
class CampaignSelection:
    """The chosen temperature fit, its label, and every candidate's outcome: ``{"mean_rmse_v", "rmse_v"}`` (one RMSE
    per validation record, in their order) or ``{"error"}``; ``settings`` the keywords of each candidate."""

    fit: TemperatureFit
    chosen: str
    tried: dict
    settings: dict

    @property
    def params(self):
        return self.fit.params

    @property
    def rmse_v(self) -> float:
        return self.fit.rmse_v

    @property
    def warnings(self) -> list:
        return self.fit.warnings


def select_temperature_fit(name: str, records, validation, score=None, capacity_ah: float | None = None
                           ) -> CampaignSelection:
    """Fit ``name`` on the identification ``records`` (one per temperature, or one) with every setting of
    :data:`FIT_SETTINGS`, keep the one whose assembled set has the lowest mean ``score`` over the ``validation``
    records; over several temperatures try :data:`PER_TEMPERATURE` and the chosen setting + :data:`CT_SUFFIX` (module
    docstring). ``score(model, record)`` is an open-loop voltage RMSE (default: from the record's reference SOC on the
    model's axis, the noise recipe's residual); ``capacity_ah`` the SOC axis' ``Q_ref`` (:func:`fit_temperatures`).
    Raises :class:`~socbench.errors.ModelError` when no setting fits."""
    records, validation = list(records), list(validation)
    if not validation:
        raise ConfigError("select_temperature_fit needs at least one validation record")
    score = score or _recipe_rmse
    tried, fits, settings = {}, {}, {}

    def attempt(label, **kw):
        settings[label] = kw
        try:
            res = fit_temperatures(name, records, capacity_ah=capacity_ah, **kw)
            model = make_model(name, res.params)
            rmse = [float(score(model, rec)) for rec in validation]
        except FIT_ERRORS as exc:
            tried[label] = {"error": f"{type(exc).__name__}: {exc}"}
            return
        tried[label] = {"mean_rmse_v": float(np.mean(rmse)), "rmse_v": rmse}
        fits[label] = res

    for label, kw in FIT_SETTINGS.items():
        attempt(label, **kw)
    if not fits:
        raise ModelError(f"{name}: no fit setting gave a usable model ({tried})")
    chosen = min(fits, key=lambda k: tried[k]["mean_rmse_v"])
    if len(records) > 1:
        # the validation records nearest each identification record's temperature judge that record's setting (none
        # when a validation record tells no temperature: then every record keeps the chosen one)
        temps = np.array([record_temperature(r)[0] for r in records])
        try:
            near = [int(np.argmin(np.abs(temps - record_temperature(v)[0]))) for v in validation]
        except DataError:
            near = []
        own = [[j for j, k in enumerate(near) if k == i] for i in range(len(records))]
        per_t = [min(fits, key=lambda k, js=js: float(np.mean([tried[k]["rmse_v"][j] for j in js])))
                 if js else chosen for js in own]
        if len(set(per_t)) > 1:
            attempt(PER_TEMPERATURE, per_record=[FIT_SETTINGS[k] for k in per_t])
            if PER_TEMPERATURE in fits:
                tried[PER_TEMPERATURE]["per_temperature"] = per_t
                if tried[PER_TEMPERATURE]["mean_rmse_v"] < tried[chosen]["mean_rmse_v"]:
                    chosen = PER_TEMPERATURE
        label = chosen + CT_SUFFIX
        attempt(label, charge_transfer=True, **settings[chosen])
        if label in fits and tried[label]["mean_rmse_v"] < tried[chosen]["mean_rmse_v"]:
            chosen = label
    return CampaignSelection(fits[chosen], chosen, tried, settings)


def _recipe_rmse(model, record: Profile) -> float:
    from ..estimators.model_error import residual

    e = residual(model, record)
    return float(np.sqrt(np.mean(e * e)))
