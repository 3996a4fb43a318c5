"""Unit plausibility of a single cell's voltage and current, shared by the source loaders.

A voltage outside the chemistry's range is millivolts (far above) or a current column in its place (far below); a
current beyond a generous C-rate is milliamps written as amps. The error names the column and the first bad row.
"""

from __future__ import annotations

import numpy as np

from ..errors import DataError


def check_cell_units(voltage, current, *, voltage_range: tuple[float, float], max_abs_current: float, cell: str,
                     src: str, voltage_column: str, current_column: str) -> None:
    """Raise a :class:`DataError` at the first voltage outside ``voltage_range`` or current over ``max_abs_current``."""
    v = np.asarray(voltage, dtype=float)
    lo, hi = voltage_range
    bad = (v < lo) | (v > hi)
    if bad.any():
        k = int(np.argmax(bad))
        hint = " (millivolts?)" if v[k] > 1000 * lo else (" (is this a current column?)" if v[k] < lo else "")
        raise DataError(f"voltage {v[k]:g} V outside the {cell}'s range {lo}-{hi} V{hint}", file=src,
                        column=voltage_column, row=k + 1)
    i = np.asarray(current, dtype=float)
    bad = np.abs(i) > max_abs_current
    if bad.any():
        k = int(np.argmax(bad))
        raise DataError(f"current {i[k]:g} A beyond ±{max_abs_current:g} A for a {cell} (milliamps?)", file=src,
                        column=current_column, row=k + 1)
