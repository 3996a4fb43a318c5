"""Canonical CSV/Parquet: columns ``time_s, current_a, voltage_v[, temperature_c][, soc_ref]``, positive = discharge.

An optional JSON sidecar with the same stem (``run.csv`` + ``run.json``) holds the metadata
(``name, capacity_ah, n_series, chemistry, source``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import DataError
from ..profile import Profile, ProfileMeta

REQUIRED = ("time_s", "current_a", "voltage_v")
OPTIONAL = ("temperature_c", "soc_ref")


def sniff(path) -> bool:
    path = Path(path)
    if path.suffix.lower() == ".parquet":
        return True
    if path.suffix.lower() != ".csv":
        return False
    with open(path, encoding="utf-8", errors="replace") as fh:
        header = fh.readline()
    cols = {c.strip() for c in header.split(",")}
    return {"time_s", "current_a"} <= cols


def _read_meta(path: Path) -> dict:
    side = path.with_suffix(".json")
    if not side.exists():
        return {}
    try:
        d = json.loads(side.read_text())
    except json.JSONDecodeError as exc:
        raise DataError(f"sidecar is not valid JSON ({exc.msg})", file=str(side)) from None
    if not isinstance(d, dict):
        raise DataError("sidecar must be a JSON object", file=str(side))
    return d


def load_canonical(path) -> Profile:
    path = Path(path)
    try:
        if path.suffix.lower() == ".parquet":
            df = pd.read_parquet(path)
        else:
            df = pd.read_csv(path)
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot parse: {str(exc).splitlines()[0]}", file=str(path)) from None
    df.columns = [str(c).strip() for c in df.columns]
    for c in REQUIRED:
        if c not in df.columns:
            raise DataError("missing column", file=str(path), column=c)
    if len(df) == 0:
        raise DataError("no data rows", file=str(path))
    cols = {}
    for c in REQUIRED + OPTIONAL:
        if c not in df.columns:
            continue
        values = pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=float)
        bad = ~np.isfinite(values)
        if bad.any():
            row = int(np.argmax(bad)) + 1
            raise DataError(f"not a finite number ({df[c].iloc[row - 1]!r})", file=str(path), column=c, row=row)
        cols[c] = values
    meta = _read_meta(path)
    pm = ProfileMeta(
        name=str(meta.get("name", path.stem)),
        source=str(path),
        capacity_ah=float(meta["capacity_ah"]) if meta.get("capacity_ah") is not None else None,
        n_series=int(meta.get("n_series", 1)),
        chemistry=str(meta.get("chemistry", "")),
    )
    return Profile(
        cols["time_s"], cols["current_a"], cols["voltage_v"], cols.get("temperature_c"), cols.get("soc_ref"), pm
    )
