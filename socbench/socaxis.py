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

What a reference column counts can also be read off the column itself (:func:`read_reference_count`), to *report*
how its axis and the model's differ (never to convert: that would score the filter on an axis fitted to its truth).
Over records ``r`` with a reference, by least squares on every sample::

    z_ref(t) = z_r − (A(t) − c·t)/Q_data          A(t) = ∫₀ᵗ I dt  the records' own count [Ah], t in hours

one start ``z_r`` per record, ``Q_data`` and ``c`` shared: the capacity the reference counts with, and a current
``c`` [A] the records' sensor reads that the reference does not count. What they hold depends on what the reference
is. A count of the records' own current (the Panasonic and CALCE loaders') gives their capacity and ``c = 0``: nothing
the records do not already say. A cycler's count with a nominal capacity gives that nominal. An independent count, or
the cell's true SOC (a simulation's), holds what the current column misses: a faded cell's capacity, a sensor
offset, a leak (as a current); :mod:`socbench.diagnose` reports it and never fits on it, since the SOC errors it
reports are measured against that same reference.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .errors import ConfigError
from .profile import Profile

#: the meta.extra key a loader sets when its reference SOC is ``1 − Ah/C`` counted from full with capacity C [Ah]
REFERENCE_CAPACITY_KEY = "soc_ref_capacity_ah"


#: the least span of a record's reference SOC (strictly inside (0, 1)) from which :func:`read_reference_count` reads
#: what it counts
COUNT_MIN_SPAN = 0.10
#: where the records' count and their time move together closer than this (|correlation| within records, a steady
#: current) a capacity cannot be told from a current the reference leaves out: ``c`` is not read (taken as 0)
COUNT_COLLINEAR = 0.999


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


def read_reference_count(profiles, uncounted: bool = True) -> dict | None:
    """What the reference SOC of ``profiles`` counts (module docstring): ``{"capacity_ah": Q_data,
    "uncounted_current_a": c, "residual_soc_rms": how far the reference lies from that count (RMS, SOC fraction),
    "span": the largest span of a record's reference, "records": how many were read}``, or None where no record's
    reference spans :data:`COUNT_MIN_SPAN` or the fit gives no positive capacity. Only the samples strictly inside
    (0, 1) count (a reference clipped at full or empty stops counting there), and only the records whose reference
    spans :data:`COUNT_MIN_SPAN` with a current that counts some charge. ``c`` is None with ``uncounted=False`` (the
    count alone, ``z = z_r − A/Q``) and where a steady current cannot tell it from the capacity
    (:data:`COUNT_COLLINEAR`). A record is counted through a logging gap as its current column holds it
    (:meth:`~socbench.profile.Profile.amp_hours`): the diagnosis reads its records after cutting them at the gaps the
    current does not bridge (:func:`socbench.diagnose.data.split_at_gaps`)."""
    cols = []
    for p in profiles:
        ref = getattr(p, "soc_ref", None)
        if ref is None or ref.ndim != 1:
            continue
        inside = (ref > 0.0) & (ref < 1.0)
        if np.count_nonzero(inside) < 3 or float(np.ptp(ref[inside])) < COUNT_MIN_SPAN:
            continue
        a = p.amp_hours()[inside]
        if not float(np.ptp(a)) > 0.0:  # a reference that moves while the current counts nothing: no capacity in it
            continue
        cols.append((ref[inside], a, p.time_s[inside] / 3600.0))
    if not cols:
        return None
    # within each record (its mean removed, which takes its start z_r): z_ref = −A/Q + (c/Q)·t
    z, a, t = (np.concatenate([x - x.mean() for x in xs]) for xs in zip(*cols))
    steady = not uncounted or abs(np.dot(a, t)) >= COUNT_COLLINEAR * np.sqrt(np.dot(a, a) * np.dot(t, t))
    design = a[:, None] if steady else np.column_stack([a, t])
    coef = np.linalg.lstsq(design, z, rcond=None)[0]
    if not (np.isfinite(coef).all() and coef[0] < 0.0):
        return None
    q = -1.0 / float(coef[0])
    return {"capacity_ah": q, "uncounted_current_a": None if steady else float(coef[1]) * q,
            "residual_soc_rms": float(np.sqrt(np.mean((z - design @ coef) ** 2))),
            "span": max(float(np.ptp(c[0])) for c in cols), "records": len(cols)}


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
