"""ORNL 2013 Nissan Leaf pouch cell (33.1 Ah rated): the cleaned Bitrode CSVs (HPPC, C/15 cycling, 1C/2C/3C).

Columns (PROVENANCE.md of ``nissan_leaf_ornl``): ``time_s, cycle, step, step_time_s, current_A, voltage_V, power_W,
capacity_Ah, energy_Wh, mode, flag``; ``current_A`` negative = discharge (flipped on the way in), ``mode`` one of
CHRG / DCHG / REST. The thermocouple files (``time_s_assumed, tc1_C...``) have no current and are not loadable here.

Reference SOC: the tester's ``capacity_Ah`` counter resets per cycle/step, so (as PROVENANCE says) the current is
counted instead (:mod:`.counting`; REST samples count as zero, as in the tester's own counter): SOC = 1 at the end of
each CC-CV charge to 4.2 V, ``C =`` :data:`CAPACITY_AH` = 33.1 Ah, the README's rated capacity. It is above every
discharge from full in these files (1C: ≈30.3 Ah, the HPPC down to 3.0 V: ≈32 Ah at 25-40 °C), so each discharge
ends a little above 0 (1C: ≈ 1 − 30.3/33.1 ≈ 0.085).
The ``mode`` column (CHRG/DCHG/REST) is checked against the current sign, so a flipped copy is refused.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import DataError, first_line
from ..profile import Profile, ProfileMeta
from ..socaxis import REFERENCE_CAPACITY_KEY
from .columns import numeric_column
from .counting import soc_between_full_charges
from .header import sniff_csv
from .units import check_cell_units

CAPACITY_AH = 33.1
CHEMISTRY = "LMO-LNO"
V_FULL = 4.19  # CC-CV limit 4.2 V
VOLTAGE_RANGE = (2.0, 4.5)
MAX_ABS_CURRENT = 200.0  # ~6C; the data peak at 91.8 A (3C)
COLUMNS = ("time_s", "cycle", "step", "step_time_s", "current_A", "voltage_V", "power_W", "capacity_Ah",
           "energy_Wh", "mode", "flag")
NUMERIC = ("time_s", "current_A", "voltage_V", "capacity_Ah")
MODES = {"CHRG", "DCHG", "REST"}


def sniff(path) -> bool:
    return sniff_csv(path, lambda columns: tuple(columns) == COLUMNS)


def _test(path: Path) -> tuple[str, float | None]:
    name = path.name.lower()
    m = re.search(r"hppc_(\d+)degc", name)
    if m:
        return "HPPC", float(m.group(1))
    if "cycling" in name:
        return "C/15 cycling (10/24/40 °C, mapping not stated)", None
    m = re.search(r"discharge_(\d)c", name)
    if m:
        return f"{m.group(1)}C discharge", None
    return "unknown", None


def load_nissan_leaf(path) -> Profile:
    """Load one ORNL Nissan Leaf cell CSV as a :class:`Profile` (positive = discharge, SOC counted from full)."""
    path = Path(path)
    src = str(path)
    try:
        df = pd.read_csv(path, encoding="utf-8-sig", dtype={"mode": str, "flag": str})
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError, ValueError) as exc:
        raise DataError(f"cannot parse as CSV: {first_line(exc)}", file=src) from None
    df.columns = [str(c).strip() for c in df.columns]
    for c in COLUMNS:
        if c not in df.columns:
            raise DataError("missing column (not an ORNL Nissan Leaf Bitrode file)", file=src, column=c)
    if len(df) == 0:
        raise DataError("no data rows", file=src)
    cols = {}
    for c in NUMERIC:
        cols[c] = numeric_column(df, c, src)
    t, i_raw, v = cols["time_s"], cols["current_A"], cols["voltage_V"]
    check_cell_units(v, i_raw, voltage_range=VOLTAGE_RANGE, max_abs_current=MAX_ABS_CURRENT, cell="33 Ah cell",
                     src=src, voltage_column="voltage_V", current_column="current_A")
    mode = df["mode"].astype(str).str.strip().to_numpy()
    bad = ~np.isin(mode, list(MODES))
    if bad.any():
        k = int(np.argmax(bad))
        raise DataError(f"unknown mode {mode[k]!r} (expected CHRG/DCHG/REST)", file=src, column="mode", row=k + 1)
    # sign check against the tester's own mode: a DCHG sample must carry a negative current in the file
    wrong = ((mode == "DCHG") & (i_raw > 0.5)) | ((mode == "CHRG") & (i_raw < -0.5))
    if wrong.any():
        k = int(np.argmax(wrong))
        raise DataError(f"current sign disagrees with mode {mode[k]} ({i_raw[k]:g} A; the file's convention is "
                        "negative = discharge)", file=src, column="current_A", row=k + 1)
    current = -i_raw
    # the tester logs its 0.01 A offset during REST while its own counter stands still: count REST as zero
    counted = np.where(mode == "REST", 0.0, current)
    soc, cap, info = soc_between_full_charges(t, counted, v, capacity_ah=CAPACITY_AH, v_full=V_FULL,
                                              i_threshold=0.05)
    test, ambient = _test(path)
    extra = {"test": test, "ambient_temperature_c": ambient,
             "dataset": "ORNL 2013 Nissan Leaf cell (Wiggins, Allu, Wang), batterysim/nissan-leaf-data", **info,
             # a count from full with this capacity: a model of another capacity reads it on its own axis (socaxis)
             **({REFERENCE_CAPACITY_KEY: float(cap)} if soc is not None else {})}
    meta = ProfileMeta(name=path.stem, source=src, capacity_ah=cap, n_series=1, chemistry=CHEMISTRY, extra=extra)
    # Profile checks time order / duplicates and names the column time_s
    return Profile(t, current, v, None, soc, meta)
