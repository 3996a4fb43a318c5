"""DJI Matrice 100 flight logs (``uav_dji_m100``: WADL survey flights, Cape Crozier 2019–20; see its PROVENANCE.md).

``battery_telemetry_all_flights.csv`` holds event-driven battery records (≈ every 12 s) of 128 app logs; a
``battery_segment`` is one pack discharge within a log. Columns used: ``t_s_since_first_battery_record`` (s),
``voltage_V`` (V), ``current_A`` (A, positive = discharge as logged, so no sign flip), ``temperature_C`` (°C) and
``remain_percent_bms`` (the smart battery's own SOC estimate, %, divided by 100 here — a reference, not ground truth).
The sibling ``flight_mode_events_all_flights.csv`` (``onFlightMode change: A -> B``) marks the flight phases.

Logged glitches are rejected row by row and counted (PROVENANCE.md, "What was extracted"):

* ``soc_zero_at_high_voltage``: 0 % SOC while the pack reads more than 21.0 V (3.5 V per cell, far above an empty 6S
  pack). PROVENANCE says "35 records show 0 % while V > 22 V"; in the file 32 of them are above 22.0 V and all 35 are
  above 21.6 V, so the threshold here is 21.0 V and all 35 are dropped;
* ``temperature_zero``: temperature exactly 0.0 °C (9 records);
* ``duplicate_time``: repeated time stamps within a segment (none in the published file).

``load_dji(path)`` returns every segment on one time axis (segments back to back, separated by a
``SEGMENT_GAP_S`` gap that :meth:`Profile.gaps` reports); ``meta.extra["segments"]`` lists the row range, log id and
phases of each. :func:`read_segments` gives the segments one by one (the replay uses it).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import DataError, SocbenchWarning, first_line
from ..profile import Profile, ProfileMeta
from .columns import numeric_column
from .header import header_columns

TELEMETRY = "battery_telemetry_all_flights.csv"
EVENTS = "flight_mode_events_all_flights.csv"
COLUMNS = ("log_id", "battery_segment", "t_s_since_first_battery_record", "voltage_V", "current_A",
           "remain_percent_bms", "temperature_C")
#: capacity implied by ∫I dt / ΔSOC over 135 segments (PROVENANCE: median 5.52 Ah; TB48D is rated 5.7 Ah)
CAPACITY_AH = 5.5
N_SERIES = 6
SOC0_GLITCH_MIN_V = 21.0
SEGMENT_GAP_S = 3600.0
#: below this current [A] the aircraft is on the ground (PROVENANCE: 0.7–0.9 A on the ground, 15–32 A in flight)
GROUND_CURRENT_A = 5.0
#: flight mode -> phase
MODE_PHASE = {"AUTO_TAKEOFF": "takeoff", "ASSISTED_TAKEOFF": "takeoff", "GPS_WAYPOINT": "cruise",
              "AUTO_LANDING": "landing", "GO_HOME": "return", "GPS_ATTI": "manual", "ATTI": "manual"}


@dataclass
class DjiSegment:
    """One pack discharge: samples from the segment's first record (``time_s`` starts at 0)."""

    log_id: str
    segment: int
    serial: str
    time_s: np.ndarray
    current_a: np.ndarray
    voltage_v: np.ndarray
    temperature_c: np.ndarray
    soc_bms: np.ndarray
    modes: list = field(default_factory=list)  # [(t_s, flight mode)] relative to time_s, from the events file
    raw_n: int = 0  # records as logged, glitches included

    @property
    def key(self) -> str:
        return f"{self.log_id}#{self.segment}"

    @property
    def n(self) -> int:
        return int(self.time_s.size)

    def phases(self) -> np.ndarray:
        """Phase label per sample: 'ground' below GROUND_CURRENT_A, else the phase of the current flight mode."""
        labels = np.full(self.n, "manual", dtype=object)
        for t, mode in sorted(self.modes, key=lambda m: m[0]):
            labels[self.time_s >= t] = MODE_PHASE.get(mode, "manual")
        labels[self.current_a < GROUND_CURRENT_A] = "ground"
        return labels


def sniff(path) -> bool:
    path = Path(path)
    if path.suffix.lower() != ".csv":
        return False
    return {"voltage_V", "current_A", "remain_percent_bms"} <= set(header_columns(path))


def _telemetry_path(path) -> Path:
    path = Path(path)
    return path / TELEMETRY if path.is_dir() else path


def read_telemetry(path) -> tuple[pd.DataFrame, dict]:
    """The telemetry table with the logged glitches removed, and ``{glitch kind: rows dropped}``."""
    path = _telemetry_path(path)
    if not path.exists():
        raise DataError("file not found", file=str(path))
    try:
        df = pd.read_csv(path)
    except (pd.errors.EmptyDataError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot parse: {str(exc).splitlines()[0]}", file=str(path)) from None
    for c in COLUMNS:
        if c not in df.columns:
            raise DataError("missing column", file=str(path), column=c)
    if len(df) == 0:
        raise DataError("no data rows", file=str(path))
    for c in COLUMNS[2:]:
        df[c] = numeric_column(df, c, str(path))
    if (df["current_A"] < -1.0).mean() > 0.5:
        raise DataError("current is mostly negative: expected positive = discharge", file=str(path), column="current_A")
    soc_glitch = (df["remain_percent_bms"] == 0) & (df["voltage_V"] > SOC0_GLITCH_MIN_V)
    temp_glitch = (df["temperature_C"] == 0.0) & ~soc_glitch
    dup = df.duplicated(["log_id", "battery_segment", "t_s_since_first_battery_record"]) & ~soc_glitch & ~temp_glitch
    dropped = {"soc_zero_at_high_voltage": int(soc_glitch.sum()), "temperature_zero": int(temp_glitch.sum()),
               "duplicate_time": int(dup.sum())}
    if dup.any():  # none in the published file: a file that has them was written by something else; say so
        first = int(np.flatnonzero(dup.to_numpy())[0])
        warnings.warn(f"{path}, column 't_s_since_first_battery_record', row {first + 2}: {int(dup.sum())} record(s) "
                      f"repeat a time stamp of their battery segment; each repeat is dropped (the first kept)",
                      SocbenchWarning, stacklevel=2)
    clean = df[~(soc_glitch | temp_glitch | dup)].copy()
    clean.attrs["source"] = str(path)
    clean.attrs["raw_counts"] = df.groupby(["log_id", "battery_segment"], sort=False).size().to_dict()
    return clean, dropped


#: the columns of the flight-mode events file :func:`_read_events` reads
EVENT_COLUMNS = ("log_id", "t_s_since_first_battery_record", "to_mode")


def _read_events(telemetry_path: Path) -> dict:
    path = telemetry_path.with_name(EVENTS)
    if not path.exists():
        return {}
    try:
        ev = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise DataError(f"cannot parse the flight-mode events beside the telemetry: {first_line(exc)}",
                        file=str(path)) from None
    for column in EVENT_COLUMNS:
        if column not in ev.columns:
            raise DataError("missing column of the flight-mode events beside the telemetry", file=str(path),
                            column=column)
    out: dict = {}
    for log_id, g in ev.groupby("log_id", sort=False):
        t = pd.to_numeric(g["t_s_since_first_battery_record"], errors="coerce").fillna(-np.inf).to_numpy()
        out[log_id] = list(zip(t, g["to_mode"].astype(str)))
    return out


def read_segments(path, min_samples: int = 1) -> tuple[list[DjiSegment], dict]:
    """Every battery segment with at least ``min_samples`` logged records, glitches removed, and the glitch counts.

    The size rule counts the records as logged (PROVENANCE: 144 segments with ≥ 20 samples), so removing a glitch
    never drops a segment from the replay. Parsed once per file version (cached on path, size and mtime); treat
    the returned arrays as read-only."""
    path = _telemetry_path(path)
    if not path.exists():
        raise DataError("file not found", file=str(path))
    st = path.stat()
    segments, dropped = _read_segments(str(path.resolve()), st.st_size, st.st_mtime_ns)
    return [s for s in segments if s.raw_n >= min_samples], dict(dropped)


@lru_cache(maxsize=4)
def _read_segments(path: str, size: int, mtime_ns: int) -> tuple[list[DjiSegment], dict]:
    path = Path(path)
    df, dropped = read_telemetry(path)
    events = _read_events(path)
    segments = []
    for (log_id, seg), g in df.groupby(["log_id", "battery_segment"], sort=False):
        if not g["t_s_since_first_battery_record"].is_monotonic_increasing:  # the published file is in time order
            warnings.warn(f"{path}, column 't_s_since_first_battery_record': the records of log {log_id} segment "
                          f"{seg} are not in time order; they are sorted by time", SocbenchWarning, stacklevel=2)
        g = g.sort_values("t_s_since_first_battery_record", kind="stable")
        t_abs = g["t_s_since_first_battery_record"].to_numpy()
        t0 = t_abs[0]
        modes = [(t - t0, m) for t, m in events.get(log_id, []) if t <= t_abs[-1]]
        segments.append(DjiSegment(
            log_id=str(log_id), segment=int(seg), serial=str(g["aircraft_serial"].iloc[0]) if "aircraft_serial" in g
            else "", time_s=t_abs - t0, current_a=g["current_A"].to_numpy(), voltage_v=g["voltage_V"].to_numpy(),
            temperature_c=g["temperature_C"].to_numpy(), soc_bms=g["remain_percent_bms"].to_numpy() / 100.0,
            modes=modes, raw_n=int(df.attrs["raw_counts"].get((log_id, seg), len(g)))))
    return segments, dropped


def load_dji(path) -> Profile:
    """All segments of a telemetry file (or of the ``uav_dji_m100`` folder) as one profile, glitches removed."""
    path = _telemetry_path(path)
    segments, dropped = read_segments(path)
    if not segments:
        raise DataError("no battery records left after removing glitches", file=str(path))
    times, cols, info = [], {k: [] for k in ("i", "v", "t", "z")}, []
    t_next, row = 0.0, 0
    for s in segments:
        times.append(s.time_s + t_next)
        cols["i"].append(s.current_a)
        cols["v"].append(s.voltage_v)
        cols["t"].append(s.temperature_c)
        cols["z"].append(s.soc_bms)
        phases = s.phases()
        change = np.r_[True, phases[1:] != phases[:-1]]
        info.append({"log_id": s.log_id, "segment": s.segment, "rows": [row + 1, row + s.n],
                     "t_start_s": float(t_next),
                     "phases": [(str(p), float(t + t_next)) for p, t in zip(phases[change], s.time_s[change])]})
        t_next = float(times[-1][-1]) + SEGMENT_GAP_S
        row += s.n
    meta = ProfileMeta(name=path.stem, source=str(path), capacity_ah=CAPACITY_AH, n_series=N_SERIES,
                       chemistry="LiHV 6S (DJI TB48D, inferred)",
                       extra={"segments": info, "dropped": dropped, "soc_ref": "smart-battery estimate (BMS %)"})
    return Profile(np.concatenate(times), np.concatenate(cols["i"]), np.concatenate(cols["v"]),
                   np.concatenate(cols["t"]), np.concatenate(cols["z"]), meta=meta)
