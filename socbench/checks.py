"""Cross-checks between a data file and a parameter set, before any simulation runs on them."""

from __future__ import annotations

import warnings

import numpy as np

from .errors import DataError, SocbenchWarning
from .models.params import ModelParams
from .ocv import T_REF_C
from .profile import Profile, gap_steps
from .socaxis import REFERENCE_CAPACITY_KEY, read_reference_count

#: share of samples outside a temperature-aware set's measured range above which the user is warned
TEMPERATURE_OUTSIDE_WARN = 0.01
#: relative difference between a record's declared capacity and a parameter set's above which a reference SOC scored
#: as it stands is on another axis than the model's (:func:`check_reference_axis`)
AXIS_MISMATCH = 0.03
#: record / parameter-set capacity ratios :func:`check_capacity` lets pass (wider than a cell's capacity change between
#: 25 and −20 °C, so a temperature-aware set never trips it)
CAPACITY_RATIO_OK = (0.75, 1.0 / 0.75)
#: factors a voltage range is widened by before a record's median voltage is called another cell or pack's
VOLTAGE_LEVEL_SLACK = (0.7, 1.3)


def _level_matches(median_v: float, lo: float, hi: float) -> bool:
    """Whether a record's median voltage can belong to a cell or pack spanning ``lo … hi`` V: within the range widened
    by :data:`VOLTAGE_LEVEL_SLACK` (room for any realistic over-potential, none for another cell count)."""
    return VOLTAGE_LEVEL_SLACK[0] * lo <= median_v <= VOLTAGE_LEVEL_SLACK[1] * hi


def check_voltage_level(profile: Profile, params: ModelParams, params_name: str = "parameters") -> None:
    """Refuse data whose voltage level cannot belong to the parameter set's cell or pack.

    A single-cell file against a 6S pack's parameters gives errors of 20 V that look like a model failure; the real
    cause is a mismatch (cells in series, wrong file). The measured median voltage must lie within the OCV range of the
    parameter set widened by 30 % (which leaves room for any realistic over-potential).
    """
    if profile.voltage_v is None:
        return
    lo, hi = float(params.ocv(0.0)), float(params.ocv(1.0))
    med = float(np.median(profile.voltage_v))
    if not _level_matches(med, lo, hi):
        raise DataError(
            f"measured voltage (median {med:.2f} V) does not match {params_name} (OCV {lo:.2f}–{hi:.2f} V): "
            "use parameters fitted for this cell or pack (socbench fit)",
            file=profile.meta.source or profile.meta.name,
            column="voltage_v",
        )


def check_same_cell(profile: Profile, fitted_on, role: str) -> None:
    """Refuse a record that cannot come from the cell or pack the fit records ``fitted_on`` measured (``role``: what
    the record is for, e.g. "a --validation record"): its median voltage outside the fit records' voltage range
    widened by 30 %, as :func:`check_voltage_level` widens an OCV range. A 4-cell pack's drive beside a single cell's
    HPPC would otherwise be scored at errors of volts, which a model-error recipe or a diagnosis takes for the
    model's."""
    volts = [p.voltage_v for p in fitted_on if p.voltage_v is not None]
    if profile.voltage_v is None or not volts:
        return
    lo, hi = min(float(np.min(v)) for v in volts), max(float(np.max(v)) for v in volts)
    med = float(np.median(profile.voltage_v))
    if not _level_matches(med, lo, hi):
        names = ", ".join(f"'{p.meta.source or p.name}'" for p in fitted_on)
        raise DataError(
            f"measured voltage (median {med:.2f} V) cannot come from the cell or pack of the fit record {names} "
            f"({lo:.2f}–{hi:.2f} V) it is {role} for: cells in series (n_series) or another file?",
            file=profile.meta.source or profile.meta.name, column="voltage_v")


def check_capacity(profile: Profile, params: ModelParams, params_name: str = "parameters") -> float | None:
    """Warn (one line) when the record declares a capacity far from the parameter set's.

    A parameter set counts charge with its own capacity: on a pack of a quarter of it, the simulated SOC falls four
    times too slowly and the voltage error grows through every discharge, which looks like a model failure. The
    voltage-level check cannot see it (same cell count, same OCV range). Returns the ratio record / parameters (None
    when the record declares no capacity); warns outside [0.75, 1.33] (wider than the capacity change of a cell
    between 25 and −20 °C, so a temperature-aware set never trips it).
    """
    declared = getattr(profile.meta, "capacity_ah", None)
    if not declared or not params.capacity_ah:
        return None
    ratio = float(declared) / float(params.capacity_ah)
    if not CAPACITY_RATIO_OK[0] <= ratio <= CAPACITY_RATIO_OK[1]:
        src = profile.meta.source or profile.meta.name
        warnings.warn(f"{src}: the record declares a capacity of {float(declared):.4g} Ah, {params_name} has "
                      f"{float(params.capacity_ah):.4g} Ah (×{ratio:.2f}): the simulated SOC drifts from the record's "
                      "through every discharge; use parameters fitted for this cell or pack (socbench fit)",
                      SocbenchWarning, stacklevel=2)
    return ratio


def implied_reference_capacity(profile: Profile) -> float | None:
    """The capacity [Ah] a record's reference SOC moves with against its counted current: ``−1/slope`` of the
    least-squares line of ``soc_ref`` on the discharged charge ``Ah`` (``z = z₀ − Ah/Q``) over its samples strictly
    inside (0, 1) (a reference clipped at full or empty stops counting there), when those span at least
    :data:`~socbench.socaxis.COUNT_MIN_SPAN` (else None): :func:`~socbench.socaxis.read_reference_count` without a
    current left out. A reference that is a charge count, a simulated truth or a good BMS estimate all move so."""
    read = read_reference_count([profile], uncounted=False)
    return None if read is None else read["capacity_ah"]


#: a reference SOC that moves by this much or more while the current column counts less than
#: :data:`DEAD_CURRENT_SHARE` of that charge does not describe the same current
#: (:func:`check_current_against_reference`)
DEAD_CURRENT_SPAN = 0.10
DEAD_CURRENT_SHARE = 0.2
#: … and a current column that counts more than this many times what the reference moves is on another scale: time
#: in ms, a current in mA (below the per-sample limits), or a capacity too small (beyond any nominal or temperature
#: difference, :data:`CAPACITY_RATIO_OK`)
OVER_COUNT = 3.0


def recorded_span(profile: Profile, cumulative) -> float:
    """How far ``cumulative`` (a per-sample running quantity: the reference SOC, the counted charge) moves between its
    highest and lowest point over the record's recorded steps only: across a logging gap a reference carries charge
    the current column cannot (the Panasonic HPPC files omit the discharges between pulse sets), and the column holds
    its last current through the gap."""
    if profile.n < 2:
        return 0.0
    recorded = ~gap_steps(profile.dt)
    return float(np.ptp(np.cumsum(np.diff(np.asarray(cumulative, dtype=float))[recorded]))) if recorded.any() else 0.0


def check_current_against_reference(profile: Profile, capacity_ah: float | None, what: str) -> bool:
    """Warn (one line) when the record's reference SOC moves :data:`DEAD_CURRENT_SPAN` or more while its current
    column, counted with ``capacity_ah``, moves less than :data:`DEAD_CURRENT_SHARE` of that (both over the recorded
    steps, gaps left out): a dead, disconnected or mis-scaled current channel (a BMS estimate logged beside it still
    falls), which every error measured on the record then measures too (``what`` says which); or more than
    :data:`OVER_COUNT` times that (time in ms, a current in mA, a capacity too small). Returns whether it warned."""
    ref = profile.soc_ref
    if ref is None or ref.ndim != 1 or not capacity_ah or profile.n < 2:
        return False
    span = recorded_span(profile, ref)
    counted = recorded_span(profile, profile.amp_hours()) / float(capacity_ah)
    src = profile.meta.source or profile.meta.name
    if span >= DEAD_CURRENT_SPAN and counted > OVER_COUNT * span:
        warnings.warn(f"{src}: the current column counts {100 * counted:.0f} points of {float(capacity_ah):.4g} Ah, "
                      f"{counted / span:.0f}× the {100 * span:.0f} points the reference SOC moves: time in ms, current "
                      f"in mA or a capacity too small? {what} measured on this record measure that too",
                      SocbenchWarning, stacklevel=2)
        return True
    if span < DEAD_CURRENT_SPAN or counted >= DEAD_CURRENT_SHARE * span:
        return False
    warnings.warn(f"{src}: the reference SOC moves {100 * span:.0f} points but the current column counts "
                  f"{100 * counted:.1f} points of {float(capacity_ah):.4g} Ah: a dead, "
                  f"disconnected or mis-scaled current channel? {what} measured on this record measure that too",
                  SocbenchWarning, stacklevel=2)
    return True


def check_reference_axis(profile: Profile, params: ModelParams, axis, params_name: str = "parameters") -> None:
    """Warn (one line) when a SOC error is about to compare two SOC axes.

    A reference SOC is converted to the model's axis only when its loader declares it a charge count with a known
    capacity (:mod:`socbench.socaxis`); otherwise it is scored as it stands. When such a record's capacity — the one
    it declares, else the one its reference moves with (:func:`implied_reference_capacity`) — is more than
    :data:`AXIS_MISMATCH` away from the set's (a fit whose capacity is the charge an HPPC discharged down to its last
    pulse level, not to empty), a reference on the record's capacity and the model's SOC part by
    ``|1 − Q_ref/Q_data|`` of SOC at empty, and the SOC error measures that as much as the filter. Silent where
    :func:`check_capacity` already warned (far larger mismatch)."""
    if profile.soc_ref is None or not params.capacity_ah or not axis.identity:
        return
    declared = getattr(profile.meta, "capacity_ah", None)
    q_data = float(declared) if declared else implied_reference_capacity(profile)
    if not q_data:
        return
    ratio = q_data / float(params.capacity_ah)
    if abs(ratio - 1.0) > AXIS_MISMATCH and CAPACITY_RATIO_OK[0] <= ratio <= CAPACITY_RATIO_OK[1]:
        src = profile.meta.source or profile.meta.name
        what = "declares" if declared else "has a reference SOC that moves as if counted with"
        # the remedies: a reference counted with the record's capacity is converted once the record says so; a set
        # fitted at one temperature can instead be fitted on that capacity (a multi-temperature set counts every
        # temperature on its reference capacity, and its cold records deliver less: only the first applies)
        refit = "" if params.capacity_by_temperature is not None else f", or fit with --capacity {q_data:.4g}"
        warnings.warn(f"{src}: the record {what} {q_data:.4g} Ah and {params_name} counts "
                      f"{float(params.capacity_ah):.4g} Ah (×{ratio:.2f}); its reference SOC is scored as it stands, "
                      f"so a reference on the record's capacity and the model's SOC part by up to "
                      f"{100 * abs(1.0 - 1.0 / ratio):.0f} points at empty: declare it in the record's JSON sidecar "
                      f'("{REFERENCE_CAPACITY_KEY}": {q_data:.4g}) to score it on the model\'s axis{refit}',
                      SocbenchWarning, stacklevel=2)


#: a single-temperature set used this far from the temperature it was fitted at [K] gets a warning
SINGLE_TEMPERATURE_K = 5.0


def check_temperature_range(profile: Profile, params: ModelParams, params_name: str = "parameters",
                            fitted_at_c: float | None = None) -> dict:
    """Warn (one line) when a parameter set meets data away from the temperatures it was measured at.

    A set with temperature tables holds its end tables outside ``[T_1, T_K]`` (no extrapolation), and uses the
    reference temperature (:data:`~socbench.ocv.T_REF_C`, held likewise) when the data carry no temperature column.
    Both are fine when rare and misleading when common: warn when more than 1 % of the samples are held, or when
    there is no temperature at all. A set fitted on one record at ``fitted_at_c`` (the median of its temperature
    column, ``socbench fit`` stores it) has no temperature dependence at all: warn when more than 1 % of the samples
    lie more than :data:`SINGLE_TEMPERATURE_K` from it (a cell's resistances change by tens of % over that).
    Returns ``{"temperatures", "below", "above"}`` (shares of samples; for a single-temperature set
    ``{"fitted_at_c", "away"}``, or empty when its temperature is unknown) for the JSON outputs.
    """
    temps = params.temperatures
    src = profile.meta.source or profile.meta.name
    if len(temps) < 2:
        if fitted_at_c is None or profile.temperature_c is None:
            return {}
        t = np.asarray(profile.temperature_c)
        away = float(np.mean(np.abs(t - fitted_at_c) > SINGLE_TEMPERATURE_K))
        if away > TEMPERATURE_OUTSIDE_WARN:
            warnings.warn(f"{src}: {100 * away:.1f} % of the samples lie more than {SINGLE_TEMPERATURE_K:g} K from the "
                          f"{fitted_at_c:.1f} °C {params_name} were fitted at (the record spans {np.min(t):.1f}…"
                          f"{np.max(t):.1f} °C); the set has no temperature dependence: fit HPPCs at several "
                          "temperatures (socbench fit --data HPPC_T1 HPPC_T2 …)", SocbenchWarning, stacklevel=2)
        return {"fitted_at_c": fitted_at_c, "away": away}
    lo, hi = temps[0], temps[-1]
    if profile.temperature_c is None:
        warnings.warn(f"{src}: no temperature column; {params_name} (measured at {lo:g}…{hi:g} °C) are used at "
                      f"{min(max(T_REF_C, lo), hi):g} °C", SocbenchWarning, stacklevel=2)
        return {"temperatures": list(temps), "below": None, "above": None}
    t = np.asarray(profile.temperature_c)
    below, above = float(np.mean(t < lo)), float(np.mean(t > hi))
    for share, side, end in ((below, "below", lo), (above, "above", hi)):
        if share > TEMPERATURE_OUTSIDE_WARN:
            warnings.warn(f"{src}: {100 * share:.1f} % of the samples are {side} the {lo:g}…{hi:g} °C that "
                          f"{params_name} were measured at; the {end:g} °C tables are held there (no extrapolation)",
                          SocbenchWarning, stacklevel=2)
    return {"temperatures": list(temps), "below": below, "above": above}
