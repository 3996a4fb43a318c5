"""Replay of the real DJI Matrice 100 flights (``$SOCBENCH_DATA_DIR/uav_dji_m100``) on the simulated pack.

The logs are event-driven (a battery record about every 12 s); the current is held between records (zero-order
hold, as everywhere in socbench) on a regular ``dt`` grid and scaled by C-rate from the DJI pack (5.5 Ah, see
``socbench.datasets.dji``) to the simulated pack: ``I_sim = I_dji · Q_sim / Q_dji``. Flight-mode events mark the
phases. The logged glitches are rejected and counted by the loader.

:func:`replay_dataset` replays every segment at once as a batch (one truth step per time step for all segments).
Without the data directory the ``dji-m100-replay`` scenario uses :func:`load_template`: a few C-rate segments derived
from the data by :func:`derive_template` (15 s bin means of the held current, rounded to 0.001 C) and shipped as
``socbench/data/dji_m100_template.csv`` — a derived summary, not a copy of the records.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from ..datasets.dji import CAPACITY_AH, DjiSegment, read_segments
from ..errors import DataError
from .truth import TruthCell, Z

DATA_FOLDER = "uav_dji_m100"
TEMPLATE_FILE = "dji_m100_template.csv"
TEMPLATE_BIN_S = 15.0
MIN_SAMPLES = 20


def data_folder() -> Path | None:
    """``$SOCBENCH_DATA_DIR/uav_dji_m100`` when it exists, else None."""
    d = os.environ.get("SOCBENCH_DATA_DIR")
    if not d:
        return None
    p = Path(d) / DATA_FOLDER
    return p if p.is_dir() else None


def held_current(segment: DjiSegment, dt: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """``(current (T,), phase (T,))`` on the grid ``k·dt`` from the first to the last record, held between records."""
    grid = np.arange(0.0, segment.time_s[-1] + dt / 2, dt)
    idx = np.searchsorted(segment.time_s, grid, side="right") - 1
    return segment.current_a[idx], segment.phases()[idx]


def to_c_rate(current_a, source_ah: float = CAPACITY_AH):
    return np.asarray(current_a, dtype=float) / source_ah


@dataclass
class DjiReplay:
    """Every segment replayed on the simulated pack as one batch on a common grid (zero current after the end)."""

    keys: list
    n_records: np.ndarray  # (S,) clean records per segment
    n_steps: np.ndarray  # (S,) grid samples per segment (first to last record)
    time_s: np.ndarray  # (T,)
    c_rate: np.ndarray  # (S, T) held DJI C-rate
    current_a: np.ndarray  # (S, T) scaled current applied to the truth pack (0 after the end or the UV stop)
    voltage_v: np.ndarray  # (S, T) truth terminal voltage
    soc: np.ndarray  # (S, T) truth SOC
    active: np.ndarray  # (S, T) bool: inside the segment and before the under-voltage stop
    dropped: dict  # glitch kind -> rows dropped

    @property
    def n_segments(self) -> int:
        return len(self.keys)


def replay_dataset(path=None, dt: float = 1.0, cell: TruthCell | None = None, capacity_ah: float | None = None,
                   min_samples: int = MIN_SAMPLES) -> DjiReplay:
    """Replay every segment with ``≥ min_samples`` logged records; each starts at rest at its first BMS SOC and
    temperature (ambient = that temperature) and stops at the under-voltage limit."""
    path = Path(path) if path is not None else data_folder()
    if path is None:
        raise DataError("no DJI data: set SOCBENCH_DATA_DIR (expects uav_dji_m100/ inside)")
    segments, dropped = read_segments(path, min_samples=min_samples)
    if not segments:
        raise DataError(f"no battery segment with >= {min_samples} records", file=str(path))
    cell = cell or TruthCell()
    q = capacity_ah or cell.params.capacity_ah
    held = [held_current(s, dt)[0] for s in segments]
    T = max(h.size for h in held)
    S = len(segments)
    c_rate = np.zeros((S, T))
    inside = np.zeros((S, T), dtype=bool)
    for j, h in enumerate(held):
        c_rate[j, :h.size] = to_c_rate(h)
        inside[j, :h.size] = True
    amps = c_rate * q
    z0 = np.array([s.soc_bms[0] for s in segments])
    temp0 = np.array([s.temperature_c[0] for s in segments])
    x = cell.initial_state(z0, temp0, hyst=1.0)
    volts, socs, applied = np.empty((S, T)), np.empty((S, T)), np.empty((S, T))
    active = inside.copy()
    stopped = np.zeros(S, dtype=bool)
    for k in range(T):
        i = np.where(stopped | ~inside[:, k], 0.0, amps[:, k])
        y = cell.voltage(x, i)
        stopped |= y < cell.uv_limit_v
        active[:, k] &= ~stopped
        volts[:, k], socs[:, k], applied[:, k] = y, x[:, Z], i
        x = cell.step(x, i, dt, temp0)
    return DjiReplay([s.key for s in segments], np.array([s.n for s in segments]), np.array([h.size for h in held]),
                     np.arange(T) * dt, c_rate,
                     applied, volts, socs, active, dropped)


# ------------------------------------------------------------------------------------------------ template
def derive_template(segments: list[DjiSegment], n: int = 3, bin_s: float = TEMPLATE_BIN_S,
                    max_ground_s: float = 30.0) -> pd.DataFrame:
    """A few representative C-rate segments: among the segments with a typical duration (inter-quartile range), the
    ones at the 25/50/75 % quantiles of mean in-flight C-rate; ground time before take-off trimmed to
    ``max_ground_s``; ``bin_s`` means of the held current, rounded to 0.001 C."""
    segs = [s for s in segments if s.n >= MIN_SAMPLES]
    dur = np.array([s.time_s[-1] for s in segs])
    lo, hi = np.percentile(dur, [25, 75])
    typical = [s for s, d in zip(segs, dur) if lo <= d <= hi]
    flight_c = np.array([to_c_rate(s.current_a[s.current_a > 5.0]).mean() for s in typical])
    order = np.argsort(flight_c)
    picks = [typical[order[int(round(qt * (len(typical) - 1)))]] for qt in np.linspace(0.25, 0.75, n)]
    rows = []
    for j, s in enumerate(picks):
        amps, phases = held_current(s, 1.0)
        airborne = np.nonzero(phases != "ground")[0]
        start = max(int(airborne[0]) - int(max_ground_s), 0) if airborne.size else 0
        amps, phases = amps[start:], phases[start:]
        nb = int(np.ceil(amps.size / bin_s))
        for b in range(nb):
            sl = slice(int(b * bin_s), int(min((b + 1) * bin_s, amps.size)))
            vals, counts = np.unique(phases[sl], return_counts=True)
            rows.append((j, b * bin_s, round(float(to_c_rate(amps[sl].mean())), 3), str(vals[np.argmax(counts)])))
    return pd.DataFrame(rows, columns=["segment", "t_s", "c_rate", "phase"])


def write_template(frame: pd.DataFrame, path) -> None:
    header = (
        "# Derived DJI Matrice 100 flight current template for socbench (dji-m100-replay without SOCBENCH_DATA_DIR).\n"
        "# Source: uav_dji_m100 (WADL survey flights, k2shah/wadl git history, GPL v3; Shah et al., Sci. Robot. 5,\n"
        "# eabc3000, 2020) - see $SOCBENCH_DATA_DIR/uav_dji_m100/PROVENANCE.md. Derived by\n"
        "# socbench.scenarios.replay.derive_template: 3 typical-duration segments at the 25/50/75 % quantiles of mean\n"
        "# in-flight C-rate, current held between records, 15 s bin means divided by the 5.5 Ah pack capacity.\n"
        "# Columns: segment (0..2), t_s (bin start, s), c_rate (1/h, positive = discharge), phase (majority in bin).\n"
    )
    Path(path).write_text(header + frame.to_csv(index=False))


@cache
def load_template() -> pd.DataFrame:
    """The shipped template (``socbench/data/dji_m100_template.csv``)."""
    with resources.files("socbench").joinpath("data", TEMPLATE_FILE).open() as fh:
        return pd.read_csv(fh, comment="#")


def template_pattern(dt: float = 1.0, bin_s: float = TEMPLATE_BIN_S) -> tuple[np.ndarray, list]:
    """The template's segments back to back as a C-rate sequence on the ``dt`` grid, and the phases."""
    df = load_template()
    rates, phases, t0 = [], [], 0.0
    reps = int(round(bin_s / dt))
    for _, g in df.groupby("segment", sort=True):
        r = np.repeat(g["c_rate"].to_numpy(dtype=float), reps)
        ph = np.repeat(g["phase"].to_numpy(), reps)
        change = np.r_[True, ph[1:] != ph[:-1]]
        phases += [(str(p), t0 + k * dt) for k, p in zip(np.nonzero(change)[0], ph[change])]
        rates.append(r)
        t0 += r.size * dt
    return np.concatenate(rates), phases


def data_pattern(keys: list, dt: float = 1.0, path=None) -> tuple[np.ndarray, list]:
    """Selected real segments (``"log_id#segment"``) back to back as a held C-rate sequence, and the phases."""
    path = Path(path) if path is not None else data_folder()
    if path is None:
        raise DataError("replay source 'data' needs SOCBENCH_DATA_DIR (with uav_dji_m100/ inside)")
    segments, _ = read_segments(path)
    by_key = {s.key: s for s in segments}
    rates, phases, t0 = [], [], 0.0
    for key in keys:
        if key not in by_key:
            raise DataError(f"no segment '{key}' in the DJI data", file=str(path))
        amps, ph = held_current(by_key[key], dt)
        change = np.r_[True, ph[1:] != ph[:-1]]
        phases += [(str(p), t0 + k * dt) for k, p in zip(np.nonzero(change)[0], ph[change])]
        rates.append(to_c_rate(amps))
        t0 += amps.size * dt
    return np.concatenate(rates), phases
