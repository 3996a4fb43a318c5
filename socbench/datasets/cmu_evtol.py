"""CMU eVTOL battery dataset (Sony-Murata VTC6 18650, 3 Ah, NMC): a cell's whole life, as published or resampled.

Two layouts, told apart by their header:

* **original** (the dataset's ``VAHnn.csv``, DOI 10.1184/R1/14226830; its README lists the columns): ``time_s,
  Ecell_V, I_mA, EnergyCharge_W_h, QCharge_mA_h, EnergyDischarge_W_h, QDischarge_mA_h, Temperature__C, cycleNumber,
  Ns``, the current in mA, positive = charge (the cycler's sign: flipped on the way in, and the flip checked by the
  voltage's response, :func:`~socbench.datasets.canonical.check_current_sign`); a repeated time stamp (the files
  join several tester files) keeps its later record, and the count is kept in ``meta.extra``;
* **resampled** (PROVENANCE.md of ``cmu_evtol_vtc6_resampled``): ``time_s, current_A_pos_discharge, voltage_V,
  temperature_C`` (cell surface), positive = discharge, on a uniform grid of 30, 166 or 186 s (linear interpolation
  of the original ~1 Hz logs by a third party).

Each file is hundreds of eVTOL missions (take-off ≈ 75 s at 15–20 A, cruise ≈ 800 s at 4–5 A, landing ≈ 105 s at
15–20 A, each after a CC-CV charge and a rest) with, every 50 missions, a reference performance test whose C/5
discharge from full (4.2 V) to the 2.5 V cut-off measures the capacity the cell has left.

What the resampling leaves: the capacity checks (five hours at a constant current lose nothing at any of the grids) and
the trends over life; not the missions' dynamics (a take-off is two or three samples at 30 s, none at 166 s), nor
their charge balance (at 30 s a mission's counted discharge exceeds the charge counted back into the cell by ≈ 7 %).
:func:`capacity_checks` and :func:`missions` cut the life record into those pieces.

No reference SOC: the charges stop at 4.0–4.2 V CV limits whose SOC the files do not say. A capacity check, counted
from full with its own measured capacity, is its own reference (:func:`capacity_check_record`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..profile import Profile, ProfileMeta, true_runs
from ..socaxis import REFERENCE_CAPACITY_KEY
from .canonical import _numeric, _read_frame, check_current_sign
from .header import sniff_csv
from .units import check_cell_units

#: each layout's leading columns: time, current, voltage, temperature (one resampled copy adds a cycle index after them)
LAYOUTS = {"resampled": ("time_s", "current_A_pos_discharge", "voltage_V", "temperature_C"),
           "original": ("time_s", "Ecell_V", "I_mA", "EnergyCharge_W_h", "QCharge_mA_h", "EnergyDischarge_W_h",
                        "QDischarge_mA_h", "Temperature__C", "cycleNumber", "Ns")}
#: time, current, voltage and temperature columns of each layout, and the factor that makes the current A, + = discharge
SIGNALS = {"resampled": (("time_s", "current_A_pos_discharge", "voltage_V", "temperature_C"), 1.0),
           "original": (("time_s", "I_mA", "Ecell_V", "Temperature__C"), -1e-3)}
#: the VTC6's nominal capacity (dataset documentation)
CAPACITY_AH = 3.0
CHEMISTRY = "NMC"
VOLTAGE_RANGE = (2.0, 4.5)
MAX_ABS_CURRENT = 40.0  # the data peak at 21.5 A
#: a current below this is a rest [A]
REST_A = 0.05
#: a capacity check's discharge runs on across dips (its hourly pauses) this short [s]
PAUSE_S = 600.0
#: a capacity check: a discharge at no more than this C-rate (median) …
CHECK_C_RATE = 0.25
#: … that moves at least this share of the nominal capacity
CHECK_MIN_SHARE = 0.5
#: a mission: a discharge whose peak current is at least this C-rate (the take-off)
MISSION_PEAK_C_RATE = 2.0


def _layout(columns) -> str | None:
    cols = tuple(columns)
    return next((name for name, head in LAYOUTS.items() if cols[:len(head)] == head), None)


def sniff(path) -> bool:
    return sniff_csv(path, lambda columns: _layout(columns) is not None)


def load_cmu_evtol(path) -> Profile:
    """Load one CMU eVTOL life record (either layout) as a :class:`Profile` (positive = discharge, no reference
    SOC)."""
    path = Path(path)
    src = str(path)
    df = _read_frame(path)
    layout = _layout(df.columns)
    if layout is None:
        raise DataError("not a CMU eVTOL record: expected the columns " + " | ".join(
            ", ".join(head) for head in LAYOUTS.values()) + f"; got {', '.join(df.columns)}", file=src)
    if len(df) < 2:
        raise DataError("fewer than two data rows", file=src)
    (tc, ic, vc, temp_c), scale = SIGNALS[layout]
    t, i_raw, v, temp = (_numeric(df, c, src) for c in (tc, ic, vc, temp_c))
    i = scale * i_raw
    check_cell_units(v, i, voltage_range=VOLTAGE_RANGE, max_abs_current=MAX_ABS_CURRENT, cell="3 Ah 18650 cell",
                     src=src, voltage_column=vc, current_column=ic)
    step = np.diff(t)
    if (step < 0).any() or (layout == "resampled" and (step == 0).any()):
        k = int(np.argmax(step < 0) if (step < 0).any() else np.argmax(step == 0))
        raise DataError(f"time does not increase ({t[k]:g} s then {t[k + 1]:g} s)", file=src, column=tc, row=k + 2)
    repeated = 0
    if (step == 0).any():  # joined tester files repeat a stamp: the later record holds (ZOH: the earlier lasts 0 s)
        keep = np.r_[step > 0, True]
        repeated = int((~keep).sum())
        t, i, v, temp = t[keep], i[keep], v[keep], temp[keep]
        step = np.diff(t)
    if layout == "original":
        check_current_sign(t, i, v, src=src, column=ic, convention="the dataset's convention: positive = charge")
    extra = {"dataset": "CMU eVTOL battery dataset (Bills et al., Sci. Data 10, 344, 2023)"
                        + (", third-party resampled copy" if layout == "resampled" else ""),
             "layout": layout, "grid_s": float(np.median(step)), "nominal_capacity_ah": CAPACITY_AH,
             "repeated_stamps_dropped": repeated}
    meta = ProfileMeta(name=path.stem, source=src, capacity_ah=CAPACITY_AH, n_series=1, chemistry=CHEMISTRY,
                       extra=extra)
    return Profile(t - t[0], i, v, temp, None, meta)


def _discharges(profile: Profile, bridge_s: float = 0.0) -> list[tuple[int, int]]:
    """The discharge runs (current above :data:`REST_A`), joined across dips no longer than ``bridge_s``."""
    t, i = profile.time_s, profile.current_a
    runs = true_runs(i > REST_A)
    out: list[list[int]] = []
    for a, b in runs:
        if out and t[a] - t[out[-1][1] - 1] <= bridge_s and not (i[out[-1][1]:a] < -REST_A).any():
            out[-1][1] = b
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def rest_start(profile: Profile, k: int) -> int:
    """The first sample of the rest that ends at sample ``k`` (``k`` itself when none does)."""
    quiet = np.abs(profile.current_a[:k]) < REST_A
    while k > 0 and quiet[k - 1]:
        k -= 1
    return k


def rest_stop(profile: Profile, k: int) -> int:
    """One past the last sample of the rest that starts at sample ``k``."""
    quiet = np.abs(profile.current_a) < REST_A
    while k < profile.n and quiet[k]:
        k += 1
    return k


@dataclass(frozen=True)
class CapacityCheck:
    """A reference test's C/5 discharge: samples ``start:stop`` of the life record (from the rest before it, at full —
    or its first sample where the CV charge runs straight into it — to the first sample at rest after the cut-off),
    the charge it delivered [Ah] and the missions flown before it."""

    start: int
    stop: int
    capacity_ah: float
    missions_before: int


def missions(profile: Profile) -> list[tuple[int, int]]:
    """``[(start, stop), …]``: each mission with the rests around it (from the rest after its charge to the end of
    the rest after its landing)."""
    q = profile.meta.capacity_ah or CAPACITY_AH
    out = []
    for a, b in _discharges(profile):
        if profile.current_a[a:b].max() >= MISSION_PEAK_C_RATE * q:
            out.append((rest_start(profile, a), rest_stop(profile, b)))
    return out


def capacity_checks(profile: Profile) -> list[CapacityCheck]:
    """Every capacity check of the life record, in order (module docstring)."""
    q = profile.meta.capacity_ah or CAPACITY_AH
    ah = profile.amp_hours()
    flown = [a for a, _ in missions(profile)]
    out = []
    for a, b in _discharges(profile, PAUSE_S):
        i = profile.current_a[a:b]
        moved = float(ah[b - 1] - ah[a]) if b > a else 0.0
        if np.median(i) <= CHECK_C_RATE * q and i.max() < MISSION_PEAK_C_RATE * q and moved >= CHECK_MIN_SHARE * q:
            # to the cut-off: the last sample under load carries the step to the first one at rest (ZOH)
            start, stop = rest_start(profile, a), min(b + 1, profile.n)
            out.append(CapacityCheck(start, stop, float(ah[stop - 1] - ah[start]), sum(s < a for s in flown)))
    return out


def capacity_check_record(profile: Profile, check: CapacityCheck, with_reference: bool = True) -> Profile:
    """The capacity check as a record of its own (time from 0), its reference SOC counted from 1 at its start with
    its own measured capacity (so 0 at the cut-off) when ``with_reference``."""
    rec = profile.slice(check.start, check.stop)
    rec = rec.with_(time_s=rec.time_s - rec.time_s[0])
    name = f"{profile.name}_check{check.missions_before}"
    extra = {**profile.meta.extra, "test": "capacity check (C/5 discharge from full to 2.5 V)",
             "missions_before": check.missions_before, "measured_capacity_ah": check.capacity_ah}
    soc = None
    if with_reference:
        ah = rec.amp_hours()
        soc = np.clip(1.0 - (ah - ah[0]) / check.capacity_ah, 0.0, 1.0)
        extra[REFERENCE_CAPACITY_KEY] = check.capacity_ah
    meta = ProfileMeta(name=name, source=profile.meta.source, capacity_ah=profile.meta.capacity_ah,
                       n_series=profile.meta.n_series, chemistry=profile.meta.chemistry, extra=extra)
    return rec.with_(soc_ref=soc, meta=meta)


def mission_record(profile: Profile, k: int) -> Profile:
    """Mission ``k`` (:func:`missions`) as a record of its own (time from 0)."""
    a, b = missions(profile)[k]
    rec = profile.slice(a, b)
    meta = ProfileMeta(name=f"{profile.name}_mission{k}", source=profile.meta.source,
                       capacity_ah=profile.meta.capacity_ah, n_series=profile.meta.n_series,
                       chemistry=profile.meta.chemistry, extra={**profile.meta.extra, "test": f"eVTOL mission {k}"})
    return rec.with_(time_s=rec.time_s - rec.time_s[0], meta=meta)
