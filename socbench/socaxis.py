"""Two definitions of SOC, and the one conversion between them.

A model counts charge on its own axis: ``z_model = 1 − Ah/Q_ref`` with ``Q_ref = params.capacity_ah`` (a set fitted at
several temperatures counts every temperature with the same ``Q_ref``, :mod:`socbench.identify.temperature`). A
measured record defines its reference SOC with *its* capacity ``Q_data`` (Panasonic: the charge delivered at that
temperature, ``meta.capacity_ah``; CALCE: the counted capacity): ``z_data = 1 − Ah/Q_data``. Both count the same
charge ``Ah`` from full, so::

    z_data = 1 − (1 − z_model)·Q_ref/Q_data          σ_data = σ_model·Q_ref/Q_data
    z_model = 1 − (1 − z_data)·Q_data/Q_ref          σ_model = σ_data·Q_data/Q_ref

The SOC a filter reports (and is scored on, and the initial guess it is given) follows the data's definition; the
filter itself runs on the model's axis. :func:`run_on_data_axis` does the round trip for ``socbench estimate``, the
measured scenarios of the leaderboard and the docs script.

Which records carry a counted reference: a loader that counts the reference SOC from full with a capacity stores it
in ``meta.extra["soc_ref_capacity_ah"]`` (Panasonic, CALCE). Anything else (a simulated truth, a BMS estimate, no
reference at all) is left on the model's axis (ratio 1): there the reference is not a charge count with a known
capacity, and converting would invent one.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .errors import ConfigError
from .profile import Profile

#: the meta.extra key a loader sets when its reference SOC is ``1 − Ah/C`` counted from full with capacity C [Ah]
REFERENCE_CAPACITY_KEY = "soc_ref_capacity_ah"


def reference_capacity(profile: Profile) -> float | None:
    """The capacity [Ah] the profile's reference SOC is counted with, or None (not a counted reference)."""
    q = profile.meta.extra.get(REFERENCE_CAPACITY_KEY)
    return float(q) if q else None


@dataclass(frozen=True)
class SocAxis:
    """The model's capacity ``Q_ref`` and the data's ``Q_data``; identity when they are equal."""

    model_capacity_ah: float
    data_capacity_ah: float

    def __post_init__(self):
        for name in ("model_capacity_ah", "data_capacity_ah"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"SocAxis.{name} must be a positive capacity, got {v!r}")

    @property
    def ratio(self) -> float:
        """``Q_ref/Q_data``: one unit of model SOC in units of data SOC."""
        return self.model_capacity_ah / self.data_capacity_ah

    @property
    def identity(self) -> bool:
        return self.model_capacity_ah == self.data_capacity_ah

    def to_data(self, z, sd=None):
        """Model SOC (and its SD) → data SOC (and SD)."""
        zd = 1.0 - (1.0 - np.asarray(z, dtype=float)) * self.ratio
        return zd if sd is None else (zd, np.asarray(sd, dtype=float) * self.ratio)

    def to_model(self, z, sd=None):
        """Data SOC (and its SD) → model SOC (and SD)."""
        zm = 1.0 - (1.0 - np.asarray(z, dtype=float)) / self.ratio
        return zm if sd is None else (zm, np.asarray(sd, dtype=float) / self.ratio)

    def estimate_to_data(self, estimate):
        """An :class:`~socbench.estimators.estimate.Estimate` with SOC and its SD on the data's axis (states, if stored,
        stay on the model's)."""
        if self.identity:
            return estimate
        soc, sd = self.to_data(estimate.soc, estimate.soc_std)
        info = {**estimate.info, "soc_axis": self.to_dict()}
        return dataclasses.replace(estimate, soc=soc, soc_std=sd, info=info)

    def to_dict(self) -> dict:
        return {"model_capacity_ah": self.model_capacity_ah, "data_capacity_ah": self.data_capacity_ah,
                "ratio": self.ratio}


def soc_capacity(params_or_model) -> float:
    """The charge [Ah] one unit of a model's SOC counts: ``capacity_ah``, over the initial ``cap`` of a capacity effect
    where the model (an :class:`~socbench.models.effects.AugmentedModel`) or the parameter set (its ``effects``) has
    one. That effect moves the SOC by ``cap·Δz`` (``cap = Q_model/Q_true``): its SOC is the faded cell's, counted
    with ``Q_model/cap``, and a reference counted with the faded cell's measured capacity is already on that axis
    (converted with ``Q_model``, the fade would be taken off twice)."""
    params = getattr(params_or_model, "params", params_or_model)
    q = float(params.capacity_ah)
    effects = getattr(params_or_model, "effects", None)
    if effects is None or effects is params.effects:  # a parameter set: its effects are name/values records
        caps = [e["values"].get("cap0", 1.0) for e in params.effects if e["name"] == "capacity"]
    else:
        caps = [e["cap0"] for e in effects if e.name == "capacity"]
    for cap in caps:
        cap = np.unique(np.asarray(cap, dtype=float))
        if cap.size != 1:  # one axis per variant: a SocAxis has one
            raise ConfigError("soc_capacity needs one capacity-effect value, not a batch of different ones")
        q /= float(cap[0])
    return q


def soc_axis(params, profile: Profile) -> SocAxis:
    """The axis pair of a parameter set or a model (:func:`soc_capacity`) on a record (its counted reference capacity,
    else the model's own: identity)."""
    q_ref = soc_capacity(params)
    q_data = reference_capacity(profile)
    return SocAxis(q_ref, q_data if q_data is not None else q_ref)


def run_on_data_axis(estimator, profile: Profile, axis: SocAxis, soc0=None, soc0_sd=None, seed=None, **run_options):
    """Run ``estimator`` on ``profile`` with the initial guess ``soc0`` (and its SD ``soc0_sd``) given on the data's
    axis; returns the estimate on the data's axis. ``soc0=None``: the filter's own default (the SOC read off the first
    voltage, on the model's axis); ``soc0_sd=None``: the filter's option ``soc0_sd`` read on the data's axis.
    ``run_options`` (e.g. ``segments``) go to ``estimator.run``."""
    z0 = None
    if soc0 is not None:
        z0 = np.clip(axis.to_model(soc0), 0.0, 1.0)
    sd = estimator.options["soc0_sd"] if soc0_sd is None else soc0_sd
    P0 = float(axis.to_model(1.0, sd)[1]) ** 2
    if not axis.identity:  # on the model's axis the record's charge counts with Q_ref (the coulomb counter reads it)
        profile = profile.with_(meta=dataclasses.replace(profile.meta, capacity_ah=axis.model_capacity_ah))
    est = estimator.run(profile, soc0=z0, P0=P0, seed=seed, **run_options)
    return axis.estimate_to_data(est)
