"""A source file's numeric column, read the one way every source loader reads it: each cell a finite number, the
first that is not named by column and row (:func:`socbench.errors.shown` quotes it)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..errors import DataError, shown


def numeric_column(df: pd.DataFrame, column: str, src: str) -> np.ndarray:
    """``df[column]`` as floats; a :class:`DataError` at its first cell that is not a finite number."""
    values = pd.to_numeric(df[column], errors="coerce").to_numpy(dtype=float)
    bad = ~np.isfinite(values)
    if bad.any():
        row = int(np.argmax(bad)) + 1
        raise DataError(f"not a finite number ({shown(df[column].iloc[row - 1])})", file=src, column=column, row=row)
    return values
