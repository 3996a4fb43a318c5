"""CALCE A123 LiFePO4 (1.1 Ah, 20 °C) CSV exports: drive cycles from full, the full test sequence, the C/22 OCV test.

Three layouts (PROVENANCE.md of ``calce_a123_lfp``), told apart by their header:

* ``Test_Time_s, Current_A, Voltage_V`` — DST / US06 / FUDS windows that start full (after a CC-CV charge and rest);
* ``Test_Time_s, Step_Time_s, Current_A, Voltage_V`` — the whole A1-008 test file (1C, charges, DST, US06, FUDS);
* ``segment, Step_Time_s, time_s_reconstructed, Current_A, Voltage_V`` — the low-current OCV test: CV top-off, rest,
  C/22 discharge, rest, C/22 charge, rest. Time is the reconstructed column (the export has no test time); step
  boundaries repeat a stamp, and the repeated (zero-length) record is dropped and counted.

``Current_A`` is negative = discharge (Arbin): the sign is flipped on the way in, so in the profile a positive
current is discharge and a negative one charge — :func:`ocv_branches` uses exactly that to split the OCV test.

Reference SOC: the exports carry no amp-hour counter, so charge is counted (:mod:`.counting`): SOC = 1 at the end of
each CC-CV charge to 3.6 V (or at the first sample for the drive-cycle windows, which start full), with
``C =`` :data:`CAPACITY_AH` = 1.0652 Ah, the C/22 discharge 3.50 → 2.00 V of the OCV test (PROVENANCE: 1.065 Ah),
the fullest discharge measured on this cell type; a file whose counted discharge from full goes deeper (the A1-008
DST run: 1.083 Ah) uses that instead, recorded in ``meta.extra["capacity_source"]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import DataError, first_line
from ..profile import Profile, ProfileMeta, true_runs
from .canonical import check_current_sign
from .columns import numeric_column
from .counting import soc_between_full_charges
from .header import sniff_csv
from .units import check_cell_units

CAPACITY_AH = 1.0652
NOMINAL_CAPACITY_AH = 1.1
CHEMISTRY = "LFP"
V_FULL = 3.59  # CC-CV charge limit 3.6 V
V_REST_FULL = 3.45  # rest voltage of a full LFP cell (the drive-cycle windows start at 3.55 V)
VOLTAGE_RANGE = (1.5, 4.0)
MAX_ABS_CURRENT = 12.0  # ~10C for a 1.1 Ah cell; the data peak at 4.2 A
OCV_CURRENT_A = 0.05  # C/22

LAYOUTS = {
    "drive": ("Test_Time_s", "Current_A", "Voltage_V"),
    "sequence": ("Test_Time_s", "Step_Time_s", "Current_A", "Voltage_V"),
    "ocv": ("segment", "Step_Time_s", "time_s_reconstructed", "Current_A", "Voltage_V"),
}
TIME_COLUMN = {"drive": "Test_Time_s", "sequence": "Test_Time_s", "ocv": "time_s_reconstructed"}


def _layout(columns) -> str | None:
    cols = list(columns)
    for name, expected in LAYOUTS.items():
        if cols == list(expected):
            return name
    return None


def sniff(path) -> bool:
    return sniff_csv(path, lambda columns: _layout(columns) is not None)


def _test_name(path: Path, layout: str) -> str:
    if layout == "ocv":
        return "C/22 OCV (discharge + charge)"
    if layout == "sequence":
        return "full sequence (1C, DST, US06, FUDS)"
    for t in ("DST", "US06", "FUDS"):
        if t.lower() in path.name.lower():
            return t
    return "drive cycle"


def load_calce(path) -> Profile:
    """Load one CALCE A123 CSV export as a :class:`Profile` (positive = discharge, SOC counted from full)."""
    path = Path(path)
    src = str(path)
    try:
        df = pd.read_csv(path, encoding="utf-8-sig")
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError, ValueError) as exc:
        raise DataError(f"cannot parse as CSV: {first_line(exc)}", file=src) from None
    df.columns = [str(c).strip() for c in df.columns]
    layout = _layout(df.columns)
    if layout is None:
        missing = [c for c in LAYOUTS["drive"] if c not in df.columns]
        raise DataError(
            "not a CALCE A123 export: expected columns " + " | ".join(", ".join(v) for v in LAYOUTS.values())
            + f"; got {', '.join(df.columns)}", file=src, column=missing[0] if missing else None)
    if len(df) == 0:
        raise DataError("no data rows", file=src)
    tcol = TIME_COLUMN[layout]
    t = numeric_column(df, tcol, src)
    i_raw = numeric_column(df, "Current_A", src)
    v = numeric_column(df, "Voltage_V", src)
    check_cell_units(v, i_raw, voltage_range=VOLTAGE_RANGE, max_abs_current=MAX_ABS_CURRENT, cell="1.1 Ah LFP cell",
                     src=src, voltage_column="Voltage_V", current_column="Current_A")
    dt = np.diff(t)
    back = dt < 0
    if back.any():
        k = int(np.argmax(back))
        raise DataError(f"time goes backwards ({t[k]:g} s then {t[k + 1]:g} s)", file=src, column=tcol, row=k + 2)
    dropped = 0
    if layout == "ocv" and (dt == 0).any():
        # the reconstructed clock repeats a stamp at each step boundary: keep the later record (ZOH: the earlier
        # one lasts zero seconds)
        keep = np.r_[dt > 0, True]
        dropped = int((~keep).sum())
        t, i_raw, v = t[keep], i_raw[keep], v[keep]
    current = -i_raw
    check_current_sign(t, current, v, src=src, column="Current_A", convention="CALCE convention: negative = discharge")
    soc, cap, info = soc_between_full_charges(
        t, current, v, capacity_ah=CAPACITY_AH, v_full=V_FULL,
        start_full=(layout == "drive" and abs(i_raw[0]) < 0.01 and v[0] >= V_REST_FULL))
    test = _test_name(path, layout)
    extra = {"test": test, "layout": layout, "ambient_temperature_c": 20.0, "duplicate_stamps_dropped": dropped,
             "dataset": "CALCE A123 LiFePO4 (University of Maryland), third-party CSV export",
             "nominal_capacity_ah": NOMINAL_CAPACITY_AH, **info,
             # the reference SOC is counted from full with this capacity (socbench.socaxis)
             **({"soc_ref_capacity_ah": float(cap)} if soc is not None else {})}
    meta = ProfileMeta(name=path.stem, source=src, capacity_ah=cap, n_series=1, chemistry=CHEMISTRY, extra=extra)
    # the chamber temperature is nominal (file names), not measured: no temperature column
    return Profile(t - t[0], current, v, None, soc, meta)


def ocv_branches(profile: Profile, current_a: float = OCV_CURRENT_A, tol: float = 0.3):
    """Boolean masks ``(discharge, charge)`` of the low-current OCV test's two branches.

    Each branch is the longest unbroken run of samples at ≈ ``current_a`` with one sign (+ = discharge, − = charge):
    the CV top-off also passes through 0.05 A on its taper, briefly, and is not a branch.
    """
    i = profile.current_a
    near = np.abs(np.abs(i) - current_a) <= tol * current_a

    def longest(mask):
        out = np.zeros_like(mask)
        runs = true_runs(mask)
        if runs:
            a, b = max(runs, key=lambda r: r[1] - r[0])  # the first of the longest, as argmax took it
            out[a:b] = True
        return out

    return longest(near & (i > 0)), longest(near & (i < 0))
