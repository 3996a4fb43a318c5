"""Canonical CSV/Parquet: columns ``time_s, current_a, voltage_v[, temperature_c][, soc_ref]``, positive = discharge.

An optional JSON sidecar with the same stem (``run.csv`` + ``run.json``) holds the metadata
(``name, capacity_ah, n_series, chemistry, source``).

The loader trusts nothing: besides what :class:`Profile` checks (NaN/inf, time order, duplicate stamps, SOC range)
it refuses, with a :class:`DataError` naming the file, the column and the first bad row,

* columns labelled in other units (``current_ma``, ``voltage_mv``, ``soc_pct``...);
* currents no cell carries: beyond :data:`MAX_C_RATE` × the declared capacity (or :data:`MAX_CURRENT_NO_CAPACITY`
  without one) — milliamps written as amps;
* voltages outside :data:`CELL_VOLTAGE_RANGE` per cell in series: millivolts, or a current column in its place;
* a flipped current sign, seen two independent ways: the reference SOC moving against the counted charge, or the
  voltage jumping *up* when the discharge current steps up (the ohmic drop has one sign for every cell).
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import DataError, first_line, shown
from ..profile import Profile, ProfileMeta, gap_steps
from .header import header_columns

REQUIRED = ("time_s", "current_a", "voltage_v")
OPTIONAL = ("temperature_c", "soc_ref")
#: column names that say the values are in other units than the canonical ones
WRONG_UNIT_NAMES = {
    "current_ma": "current in mA: convert to A and name it current_a",
    "voltage_mv": "voltage in mV: convert to V and name it voltage_v",
    "soc_pct": "SOC in %: divide by 100 and name it soc_ref",
    "soc_percent": "SOC in %: divide by 100 and name it soc_ref",
    "soc_ref_pct": "SOC in %: divide by 100 and name it soc_ref",
    "time_ms": "time in ms: convert to s and name it time_s",
    "temperature_k": "temperature in K: convert to °C and name it temperature_c",
}
MAX_C_RATE = 30.0
MAX_CURRENT_NO_CAPACITY = 1000.0  # A per string, when no capacity is declared
CELL_VOLTAGE_RANGE = (1.0, 5.0)
TEMPERATURE_RANGE = (-60.0, 150.0)
#: sign checks need this much evidence before they speak
MIN_SOC_SWING = 0.02
MIN_STEPS = 5
CC_STRETCH_S = 600.0


def sniff(path) -> bool:
    path = Path(path)
    if path.suffix.lower() == ".parquet":
        return True
    if path.suffix.lower() != ".csv":
        return False
    try:
        cols = {c.lower() for c in header_columns(path)}
    except OSError:
        return False
    # the unit variants (time_ms, current_ma) are the canonical loader's too: it names the unit to convert; names in
    # any case (TIME_S, Current_A): a header a specific format knows exactly (the Leaf files' time_s … current_A)
    # goes to that format (socbench.datasets.detect_format)
    return ({"time_s", "time_ms"} & cols) != set() and ({"current_a", "current_ma"} & cols) != set()


def _read_meta(path: Path) -> dict:
    side = path.with_suffix(".json")
    if not side.exists():
        return {}
    try:
        d = json.loads(side.read_text(encoding="utf-8-sig"))  # an editor on Windows writes a BOM
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"sidecar is not valid JSON ({getattr(exc, 'msg', exc)})", file=str(side)) from None
    if not isinstance(d, dict):
        raise DataError("sidecar must be a JSON object", file=str(side))
    return d


def _meta(path: Path) -> ProfileMeta:
    meta = _read_meta(path)
    side = str(path.with_suffix(".json"))
    cap = meta.get("capacity_ah")
    if cap is not None:
        try:
            cap = float(cap)
        except (TypeError, ValueError):
            raise DataError(f"capacity_ah must be a number, got {cap!r}", file=side) from None
        if not (math.isfinite(cap) and cap > 0):
            raise DataError(f"capacity_ah must be positive, got {cap!r}", file=side)
    n_series = meta.get("n_series", 1)
    if isinstance(n_series, float) and n_series.is_integer():  # a tool that writes every number as a float: 1.0
        n_series = int(n_series)
    if isinstance(n_series, bool) or not isinstance(n_series, int) or n_series < 1:
        raise DataError(f"n_series must be a positive integer, got {n_series!r}", file=side)
    return ProfileMeta(
        name=str(meta.get("name", path.stem)),
        source=str(path),
        capacity_ah=cap,
        n_series=n_series,
        chemistry=str(meta.get("chemistry", "")),
        extra={k: v for k, v in meta.items() if k not in ("name", "source", "capacity_ah", "n_series", "chemistry")},
    )


def _read_frame(path: Path) -> pd.DataFrame:
    src = str(path)
    try:
        if path.stat().st_size == 0:
            raise DataError("empty file", file=src)
        if path.suffix.lower() == ".parquet":
            df = pd.read_parquet(path)
        else:
            # everything as text first: numbers are parsed column by column below, so a stray word is reported
            df = pd.read_csv(path, dtype=str, keep_default_na=False, skipinitialspace=True,
                             encoding="utf-8-sig")
    except DataError:
        raise
    except Exception as exc:  # pandas/pyarrow raise many types on junk input; at this boundary all mean "unreadable"
        raise DataError(f"cannot parse: {first_line(exc)}", file=src) from None
    df.columns = [str(c).strip() for c in df.columns]
    if path.suffix.lower() != ".parquet":  # pandas renames a repeated name ('voltage_v.1'): read the header itself
        names = [c.lower() for c in header_columns(path)]
        twice = next((c for c in REQUIRED + OPTIONAL if names.count(c) > 1), None)
        if twice:
            raise DataError("column appears more than once", file=src, column=twice)
    return df


#: what a logger writes for a reading it did not take (the temperature column only: see :mod:`socbench.profile`)
MISSING_TEXT = ("", "nan", "na", "n/a", "null", "none")


def _numeric(df: pd.DataFrame, c: str, src: str) -> np.ndarray:
    col = df[c]
    if isinstance(col, pd.DataFrame):
        raise DataError("column appears more than once", file=src, column=c)
    values = pd.to_numeric(col, errors="coerce").to_numpy(dtype=float, na_value=np.nan)
    bad = ~np.isfinite(values)
    if c == "temperature_c" and bad.any():  # empty cells are a sensor's holes: the Profile fills short ones or refuses
        bad &= ~col.isna().to_numpy() & ~col.astype(str).str.strip().str.lower().isin(MISSING_TEXT).to_numpy()
    if bad.any():
        row = int(np.argmax(bad)) + 1
        text = col.iloc[row - 1]
        if c == "time_s" and _is_date_time(text):
            raise DataError(f"a date and time ({text!r}), not seconds: write the seconds since the record's start",
                            file=src, column=c, row=row)
        raise DataError(f"not a finite number ({shown(text)})", file=src, column=c, row=row)
    return values


def _is_date_time(text) -> bool:
    """Whether ``text`` reads as a calendar date and time (a logger's stamp written where seconds belong)."""
    if not isinstance(text, str) or not any(ch in text for ch in "-/:T"):
        return False
    try:
        with warnings.catch_warnings():  # pandas warns when it guesses a format: only the yes/no matters here
            warnings.simplefilter("ignore")
            return not pd.isna(pd.to_datetime(text, errors="coerce"))
    except (ValueError, TypeError, OverflowError):
        return False


def _check_units(cols: dict, meta: ProfileMeta, src: str) -> None:
    i = cols["current_a"]
    limit = MAX_C_RATE * meta.capacity_ah if meta.capacity_ah else MAX_CURRENT_NO_CAPACITY
    bad = np.abs(i) > limit
    if bad.any():
        k = int(np.argmax(bad))
        basis = f"{MAX_C_RATE:g}C of {meta.capacity_ah:g} Ah" if meta.capacity_ah else "any plausible cell current"
        raise DataError(f"current {i[k]:g} A is beyond {basis} (milliamps written as amps?)", file=src,
                        column="current_a", row=k + 1)
    v = cols["voltage_v"] / meta.n_series
    lo, hi = CELL_VOLTAGE_RANGE
    bad = (v < lo) | (v > hi)
    if bad.any():
        k = int(np.argmax(bad))
        if v[k] > hi:
            hint = "millivolts written as volts?" if v[k] > 100 * lo else "wrong n_series in the sidecar?"
        else:
            hint = "current and voltage columns swapped?" if np.any(v < 0) or np.ptp(v) > 1.0 else "not a cell voltage"
        raise DataError(f"{v[k]:g} V per cell is outside {lo:g}-{hi:g} V ({hint})", file=src, column="voltage_v",
                        row=k + 1)
    if "temperature_c" in cols:
        t = cols["temperature_c"]
        lo, hi = TEMPERATURE_RANGE
        bad = (t < lo) | (t > hi)
        if bad.any():
            k = int(np.argmax(bad))
            raise DataError(f"temperature {t[k]:g} °C outside {lo:g}..{hi:g} °C (kelvin or °F?)", file=src,
                            column="temperature_c", row=k + 1)
    # soc_ref: its range is the Profile's to judge (a few points out: a warning; far out: an error where it is used)


def check_current_sign(t, i, v, soc=None, *, src: str, column: str = "current_a", n_series: int = 1,
                       convention: str = "canonical convention: positive = discharge") -> None:
    """Raise a :class:`DataError` when the current (positive = discharge) looks flipped. Three independent tells:

    * the reference SOC moves against the counted charge (``Δsoc ≈ −∫i dt / C`` must have a positive ``1/C``);
    * the voltage jumps *up* when the discharge current steps up (the ohmic drop), at most large current steps;
    * the voltage *rises* over long constant-current stretches the current calls discharge (and falls under charge).

    Each needs enough evidence (a SOC swing, :data:`MIN_STEPS` steps or stretches) and a clear majority before it
    speaks, so a clean record is never refused on noise. Time must already be strictly increasing.
    """
    def flipped(why, k):
        raise DataError(f"current sign looks flipped: {why} ({convention})", file=src, column=column, row=k + 1)

    dt = np.diff(t)
    if t.size < 3 or np.any(dt <= 0):
        return  # the Profile reports the time problem itself
    if soc is not None:
        # counted only over sampled steps: across a gap (a logger that paused while the cell was discharged, as in
        # the Panasonic HPPCs) the last current held is not the charge that moved, but the reference saw it move
        sampled = ~gap_steps(dt)
        q = np.r_[0.0, np.cumsum(np.where(sampled, -i[:-1] * dt, 0.0))] / 3600.0  # charge in [Ah]
        ds = np.r_[0.0, np.cumsum(np.where(sampled, np.diff(soc), 0.0))]
        if np.ptp(ds) >= MIN_SOC_SWING and np.dot(q, q) > 0 and np.dot(q, ds) < 0:  # Δsoc ≈ q/C needs C > 0
            wrong = (np.sign(q) == -np.sign(ds)) & (q != 0) & (np.abs(ds) >= MIN_SOC_SWING / 2)
            flipped("the reference SOC rises while the current says discharge", int(np.argmax(wrong)))
    di, dv = np.diff(i), np.diff(v)
    big = (np.abs(di) > 0.2 * max(float(np.max(np.abs(i))), 1e-9)) & (dv != 0)
    if big.sum() >= MIN_STEPS:
        agree = np.sign(di[big]) == -np.sign(dv[big])  # more discharge -> lower voltage
        if agree.mean() < 0.2:
            k = int(np.nonzero(big)[0][np.argmax(~agree)])
            flipped(f"the voltage jumps up when the discharge current steps up at {int((~agree).sum())} of "
                    f"{int(big.sum())} current steps", k + 1)
    # constant-current stretches: |Δi| within 2 % of the level, level above 5 % of the peak, 10 min or longer
    level = np.abs(i[:-1])
    same = (np.abs(di) <= 0.02 * np.maximum(level, 1e-12)) & (level > 0.05 * np.max(np.abs(i)))
    edges = np.diff(np.r_[0, same.astype(np.int8), 0])
    starts, stops = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]  # samples starts..stops (inclusive)
    long = (t[stops] - t[starts]) >= CC_STRETCH_S
    votes = []
    for a, b in zip(starts[long], stops[long]):  # a few long stretches per record
        rise = (v[b] - v[a]) / n_series
        if abs(rise) >= 0.02:
            votes.append((a, np.sign(rise) == -np.sign(i[a])))
    if len(votes) >= 1 and not any(ok for _, ok in votes) and (len(votes) >= 2 or soc is None):
        flipped(f"the voltage moves the wrong way over {len(votes)} long constant-current stretch(es)", votes[0][0])


def load_canonical(path) -> Profile:
    path = Path(path)
    src = str(path)
    df = _read_frame(path)
    cols_lower = {c.lower(): c for c in df.columns}
    for name, why in WRONG_UNIT_NAMES.items():
        if name in cols_lower:
            raise DataError(why, file=src, column=cols_lower[name])
    # the canonical names in any case (TIME_S, Current_A): a column named twice in two cases is refused below
    df.columns = [c.lower() if c.lower() in REQUIRED + OPTIONAL else c for c in df.columns]
    for c in REQUIRED:
        if c not in df.columns:
            if len(df.columns) == 1 and (sep := next((s for s in ";\t|" if s in df.columns[0]), None)):
                raise DataError(f"the columns are separated by {sep!r}; a canonical CSV is comma-separated",
                                file=src)
            raise DataError("missing column", file=src, column=c)
    if len(df) == 0:
        raise DataError("no data rows", file=src)
    cols = {c: _numeric(df, c, src) for c in REQUIRED + OPTIONAL if c in df.columns and c != "soc_ref"}
    soc_error = None
    if "soc_ref" in df.columns:
        # a reference SOC with a hole is kept as its error, raised where the reference is used (Profile.get): a
        # command that does not use it runs (the temperature is read by every temperature-aware model: refused here)
        try:
            cols["soc_ref"] = _numeric(df, "soc_ref", src)
        except DataError as exc:
            soc_error = exc
    meta = _meta(path)
    _check_units(cols, meta, src)
    check_current_sign(cols["time_s"], cols["current_a"], cols["voltage_v"], cols.get("soc_ref"), src=src,
                       n_series=meta.n_series)
    return Profile(
        cols["time_s"], cols["current_a"], cols["voltage_v"], cols.get("temperature_c"), cols.get("soc_ref"), meta,
        soc_ref_error=soc_error,
    )
