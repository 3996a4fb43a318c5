"""Where an HPPC without a reference SOC started: read off other records of the same cell that carry one.

An HPPC record without a reference SOC (and without a start SOC given) is counted from its most charged point, taken
as full (:func:`socbench.identify.hppc.analyze_hppc`). A test put on the cycler part charged (80–95 %, a cell taken
from storage) then has every rest point, and the OCV curve through them, ``δ = 1 − z_start`` too high on the SOC axis.
A model fitted on it reads any record whose own reference SOC is right ``δ`` off: on an NMC cell, whose OCV moves
several mV per SOC point, tens of mV (an independent generator's HPPC started at 84 % beside a drive record with its
reference: 100 mV open loop).

Records measured on the same cell that do carry a reference SOC (the evaluation records of a diagnosis) place the
test. The model fitted on the HPPC counted from full is run open loop on each of them from its reference start moved
by ``δ`` (:data:`SHIFT_GRID`, one batched simulation per record): moving the model's start by ``δ`` is moving its
curve by ``−δ``, what starting the HPPC at ``1 − δ`` does. The ``δ`` of the least mean RMSE is the HPPC's offset
when it is at least :data:`MIN_SHIFT` and lowers that RMSE by :data:`GAIN` (the bar of the other choices the base fit
makes on these records); else the HPPC stays counted from full.

Such a test often stops above empty too, and without a declared capacity its axis is counted with the charge it
moved, short of the cell's. The records' reference counts charge with a capacity of its own
(:func:`reference_capacity_ah`: the slope of the reference against the charge counted from the record's current,
:func:`socbench.checks.implied_reference_capacity`);
where that is more than :data:`CAPACITY_TOL` above the charge the HPPC moved, the HPPC did not span full to empty and
its axis is counted with the references' capacity before its start is placed. Where the offset is not taken (a test
from full), the capacity still is when the test shows no end-of-discharge knee
(:data:`~socbench.identify.hppc.NO_KNEE`): it stopped above empty, and counted with the charge it moved, its SOC axis
runs fast by the share it left out — an axis a voltage fit does not see (the OCV points move with it) but every SOC a
filter reports on it does (an independent generator's HPPCs from full stopping at 10–40 %, beside a drive with its
reference: the charge moved 10–41 % short, EKF SOC errors of 10–30 %).

A record that charges before its test (a charge to full, or sets that open with a charge pulse) has its first sample
below its most charged point: the start returned is that sample's SOC, ``z₁ − δ`` with ``z₁`` its SOC counted from the
top as full.

:func:`place_start` does both for an HPPC record (the diagnosis' base fit, :func:`socbench.diagnose.core.fit_base`,
and ``socbench fit`` with ``--validation`` records).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..checks import implied_reference_capacity
from ..errors import DataError
from ..models import make_model
from ..segments import restart_soc
from .fit import fit_model
from .hppc import NO_KNEE, analyze_hppc

#: the offsets tried [fraction of SOC]: a test started up to half empty; a little below 0 so that a minimum at 0 is a
#: minimum, not the grid's end
GRID_STEP = 0.01
SHIFT_GRID = np.round(np.arange(-0.05, 0.5 + 1e-9, GRID_STEP), 2)
#: the step of the second, finer grid about the first one's best
FINE_STEP = 0.001
#: the least offset taken: within it the records' own reference errors (a start read to ±1 point, a nominal capacity)
#: and the curve's shape near full decide as much as where the test started
MIN_SHIFT = 0.02
#: the mean open-loop RMSE on the records must fall by this share
GAIN = 0.10
#: the references' capacity replaces the charge an HPPC moved when it is this share larger (the count's own error,
#: a nominal capacity's)
CAPACITY_TOL = 0.03


@dataclass(frozen=True)
class StartShift:
    """``shift``: the offset δ of least mean RMSE on the records; ``rmse_v``: ``(at δ = 0, at δ)``; ``kept``: whether
    it is taken (at least :data:`MIN_SHIFT`, :data:`GAIN` lower)."""

    shift: float
    rmse_v: tuple
    kept: bool
    records: tuple

    def to_dict(self) -> dict:
        return {"shift": self.shift, "start_soc": round(1.0 - self.shift, 4), "rmse_v": list(self.rmse_v),
                "kept": self.kept, "records": list(self.records),
                "note": "the model fitted on the HPPC counted from full, run open loop on each record from its "
                        "reference start moved by the offset; the offset of least mean RMSE, taken when it is at "
                        f"least {MIN_SHIFT:g} and lowers that RMSE by {100 * GAIN:.0f} %"}


def start_shift(model, records) -> StartShift | None:
    """The offset of an HPPC's start (see the module docstring) from ``records`` (those with a reference SOC are
    used); None when none has one or no offset gives a finite RMSE."""
    used = [p for p in records if p.get("soc_ref") is not None and p.voltage_v is not None]
    if not used:
        return None
    rmse = _rmse_by_shift(model, used, SHIFT_GRID)
    if not np.any(np.isfinite(rmse)):
        return None
    j = int(np.nanargmin(np.where(np.isfinite(rmse), rmse, np.nan)))
    at0 = float(rmse[int(np.argmin(np.abs(SHIFT_GRID)))])
    # the grid's step again, finer (FINE_STEP) about its best: a start a point off leaves the top of every record
    # that far off the curve, an error a drifting effect then takes up
    fine = SHIFT_GRID[j] + np.arange(-1.0, 1.0 + 1e-9, FINE_STEP / GRID_STEP) * GRID_STEP
    fine_rmse = _rmse_by_shift(model, used, fine)
    if np.any(np.isfinite(fine_rmse)) and np.nanmin(fine_rmse) < rmse[j]:
        k = int(np.nanargmin(np.where(np.isfinite(fine_rmse), fine_rmse, np.nan)))
        shift, best = float(fine[k]), float(fine_rmse[k])
    else:
        shift, best = float(SHIFT_GRID[j]), float(rmse[j])
    kept = bool(shift >= MIN_SHIFT and best <= (1.0 - GAIN) * at0)
    return StartShift(round(shift, 4), (at0, best), kept, tuple(p.name for p in used))


def _rmse_by_shift(model, records, shifts) -> np.ndarray:
    """Voltage RMSE of ``model`` open loop on ``records`` (pooled) from each one's reference start plus each shift."""
    sse, n = np.zeros(len(shifts)), 0
    for p in records:
        z0 = float(restart_soc(p, 0, model))
        with np.errstate(all="ignore"):
            sim = model.simulate(p, x0=model.x0(z0 + np.asarray(shifts), (len(shifts),)))
        e = p.voltage_v[None, :] - sim.voltage_v
        sse += np.where(np.all(np.isfinite(e), axis=1), np.sum(e * e, axis=1), np.inf)
        n += p.n
    return np.sqrt(sse / n)


def reference_capacity_ah(records) -> float | None:
    """The capacity [Ah] the records' reference SOC counts with: the median over the records of the one each moves with
    against its counted current (:func:`socbench.checks.implied_reference_capacity`); None without one."""
    qs = [q for q in map(implied_reference_capacity, records) if q is not None]
    return float(np.median(qs)) if qs else None


def place_start(name: str, profile, capacity_ah, records, **fit_kwargs) -> tuple:
    """``(start SOC or None, capacity, report or None)`` of the HPPC ``profile`` for model ``name``: where it has no
    reference SOC of its own, steps down (discharge steps) and ``records`` with a reference SOC place it
    (:func:`start_shift` on the model fitted counted from its most charged point as full, ``fit_kwargs`` its setting),
    the SOC of its first sample — and, where no capacity is given (``capacity_ah`` None) and the references count with
    one :data:`CAPACITY_TOL` larger than the charge the HPPC moved, that capacity. Where the offset is not taken, the
    test keeps its top at full, and the references' capacity is still taken where the test shows no end-of-discharge
    knee (it stopped above empty: the charge it moved is short of the cell's whatever its start); else
    ``(None, capacity_ah, report)``. ``report`` (None where the records are not asked) says what they read."""
    if profile.get("soc_ref") is not None or not any(p.get("soc_ref") is not None for p in records):
        return None, capacity_ah, None
    try:
        analysis = analyze_hppc(profile, capacity_ah=capacity_ah)
        if analysis.steps != "discharge":
            return None, capacity_ah, None  # a test up to full: its top is full, its count the charge to full
        q_ref = reference_capacity_ah(records) if capacity_ah is None else None
        q = q_ref if q_ref is not None and q_ref > (1.0 + CAPACITY_TOL) * analysis.capacity_ah else capacity_ah
        short = q is not capacity_ah and any(n.startswith(NO_KNEE) for n in analysis.notes)
        # the first sample's SOC counted from the most charged point as full (below 1 where the record charges first:
        # a charge to full, or a test whose sets open with a charge pulse), the charge to the top counted with q
        first = 1.0 - (1.0 - float(analysis.soc[0])) * analysis.capacity_ah / (q or analysis.capacity_ah)
        plain = fit_model(name, profile, mode="constant", capacity_ah=q, **fit_kwargs)
    except DataError:  # not an HPPC, or no fit: the caller's own fit says why
        return None, capacity_ah, None
    found = start_shift(make_model(name, plain.params), records)
    if found is None:
        return (None, q, _capacity_kept(q, analysis)) if short else (None, capacity_ah, None)
    report = {**found.to_dict(), "start_soc": round(first - found.shift, 4), "capacity_ah": plain.params.capacity_ah,
              "capacity_from": "the references" if q is not capacity_ah else
              "given" if capacity_ah else "the HPPC's charge"}
    if found.kept:
        return first - found.shift, q, report
    return (None, q, _capacity_kept(q, analysis, report)) if short else (None, capacity_ah, report)


_SHORT_NOTE = ("the HPPC shows no end-of-discharge knee (it stopped above empty), so the charge it moved is short of "
               "the cell's capacity: counted with the capacity the records' reference SOC counts with")


def _capacity_kept(q: float, analysis, report: dict | None = None) -> dict:
    """The report of a test whose start stays at full and whose axis is counted with the references' capacity ``q``:
    ``report`` (the start search's, where it ran) with what the capacity was read from and why."""
    base = report if report is not None else {"capacity_ah": float(q), "capacity_from": "the references", "kept": False}
    return {**base, "capacity_kept": True, "hppc_charge_ah": float(analysis.capacity_ah), "capacity_note": _SHORT_NOTE}
