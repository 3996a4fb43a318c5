"""Profile: the one time-series type of socbench.

A profile is a record sampled at times ``time_s`` (shape ``(T,)``, strictly increasing) with

* ``current_a``      A, positive = discharge, shape ``(T,)`` or ``(R, T)`` for a batch of R Monte Carlo runs;
* ``voltage_v``      V, terminal voltage (optional: a pure load profile has none);
* ``temperature_c``  °C (optional);
* ``soc_ref``        reference or true SOC as a fraction in [0, 1] (optional);

plus :class:`ProfileMeta` (capacity, cells in series, chemistry, name, source file).

Validation happens on construction, so a ``Profile`` that exists is clean: every problem raises a
:class:`~socbench.errors.DataError` naming the file, the column and the first bad row (rows count from 1).
Gaps are reported by :meth:`Profile.gaps`, never interpolated silently.

The reference SOC is the one column checked leniently, because a reference counted from a nominal capacity overshoots
[0, 1] by a few points all the time (DESIGN.md, Reliability) and most commands never read it:

* within :data:`SOC_WARN_MARGIN` (5 points) outside [0, 1]: the values are kept as they are and one
  :class:`~socbench.errors.SocbenchWarning` says so (profiles derived from it — slices, runs, copies — do not repeat
  it: ``soc_ref_checked`` carries the range already validated);
* further out (a percent column, a wrong capacity): ``soc_ref`` is ``None`` — for every caller the record simply has
  no reference — and the :class:`~socbench.errors.DataError` is kept in ``soc_ref_error``. It is raised, with its
  file, column and row, only where the reference is used: :meth:`Profile.require` and :meth:`Profile.get`.

The temperature has one leniency too, for a thermocouple that drops out for a moment (a loose junction, a logger that
skips a channel): a hole of NaN samples in a one-dimensional ``temperature_c`` spanning at most
:data:`TEMPERATURE_HOLE_S` (60 s, from the last reading before it to the first after it) is filled by linear
interpolation in time (held at the record's ends), with one :class:`~socbench.errors.SocbenchWarning` naming the first
row and the longest hole. A cell's heat capacity makes its temperature move over minutes, not seconds, so a minute's
interpolation stays close to what the sensor would have read; a longer hole is an error naming its row, as infinite
values are.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from .errors import DataError, SocbenchWarning

#: Tolerance on SOC bounds: below it an overshoot of [0, 1] is rounding, and nothing is said.
SOC_TOLERANCE = 1e-6
#: A reference SOC at most this far outside [0, 1] is kept with a warning; further out it is an error where used.
SOC_WARN_MARGIN = 0.05


#: a hole of NaN in the temperature column spanning at most this [s] is filled by interpolation (module docstring)
TEMPERATURE_HOLE_S = 60.0

#: a sample step longer than this many median steps is a gap in the record (a logger that paused), not a sample
GAP_FACTOR = 5.0


def true_runs(mask) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` of the runs of True in the boolean sample mask ``mask``."""
    edges = np.diff(np.concatenate([[False], np.asarray(mask, dtype=bool), [False]]).astype(np.int8))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def run_medians(values, runs) -> np.ndarray:
    """The median of ``values[a:b]`` for each non-empty run ``(a, b)`` of ``runs``, as ``np.median`` gives it (the
    mean of the two middle values of an even run), in one sort: a record that is no HPPC has tens of thousands of
    short runs, and a call of ``np.median`` per run cost seconds."""
    values = np.asarray(values, dtype=float)
    if not len(runs):
        return np.zeros(0)
    starts, stops = (np.asarray(x, dtype=np.intp) for x in zip(*runs))
    lengths = stops - starts
    first = np.concatenate([[0], np.cumsum(lengths)[:-1]])  # where each run begins in the concatenation
    owner = np.repeat(np.arange(lengths.size), lengths)
    taken = values[np.arange(int(lengths.sum())) - first[owner] + starts[owner]]
    ordered = taken[np.lexsort((taken, owner))]
    return (ordered[first + (lengths - 1) // 2] + ordered[first + lengths // 2]) / 2.0


def gap_steps(dt, factor: float = GAP_FACTOR) -> np.ndarray:
    """Which sample steps ``dt`` are gaps: longer than ``factor`` × the median step."""
    dt = np.asarray(dt, dtype=float)
    return dt > factor * float(np.median(dt)) if dt.size else np.zeros(0, dtype=bool)


@dataclass(frozen=True)
class ProfileMeta:
    """What a profile is: the cell or pack it was measured on and where it came from."""

    name: str = "profile"
    source: str = ""
    capacity_ah: float | None = None
    n_series: int = 1
    chemistry: str = ""
    extra: dict = field(default_factory=dict, compare=False)

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "source": self.source,
            "capacity_ah": self.capacity_ah,
            "n_series": self.n_series,
            "chemistry": self.chemistry,
            **({"extra": self.extra} if self.extra else {}),
        }


def samples_fingerprint(profile) -> str:
    """SHA-256 of a profile's samples and of the metadata that says what they measure (capacity, cells in series,
    chemistry; not its name or source): two records with this hash are the same test."""
    h = hashlib.sha256()
    for name in ("time_s", "current_a", "voltage_v", "temperature_c", "soc_ref"):
        arr = getattr(profile, name)
        h.update(name.encode())
        if arr is not None:
            arr = np.ascontiguousarray(arr, dtype=np.float64)
            h.update(str(arr.shape).encode())
            h.update(arr.tobytes())
    meta = profile.meta
    h.update(json.dumps([meta.capacity_ah, meta.n_series, meta.chemistry], default=str).encode())
    return h.hexdigest()


def _first_bad_row(mask: np.ndarray) -> int:
    """1-based time index of the first True in ``mask`` (any run)."""
    flat = mask.reshape(-1, mask.shape[-1]).any(axis=0)
    return int(np.argmax(flat)) + 1


def _fill_temperature_holes(temp: np.ndarray, t: np.ndarray, src: str) -> np.ndarray:
    """``temp`` with its NaN holes of at most :data:`TEMPERATURE_HOLE_S` filled (module docstring); a longer hole
    raises. A batched column, one with no reading at all or without NaN comes back as it is (the finite check
    follows)."""
    hole = np.isnan(temp)
    if temp.ndim != 1 or not hole.any() or hole.all():
        return temp
    edges = np.flatnonzero(np.diff(np.concatenate([[0], hole.astype(np.int8), [0]])))
    first, after = edges[::2], edges[1::2]  # each hole: samples first … after − 1
    # the time the sensor was silent: from the last reading before the hole to the first after it
    span = t[np.minimum(after, t.size - 1)] - t[np.maximum(first - 1, 0)]
    k = int(np.argmax(span))
    if span[k] > TEMPERATURE_HOLE_S:
        raise DataError(f"NaN for {span[k]:.4g} s (a temperature hole longer than {TEMPERATURE_HOLE_S:g} s is not "
                        "filled)", file=src, column="temperature_c", row=int(first[k]) + 1)
    filled = temp.copy()
    filled[hole] = np.interp(t[hole], t[~hole], temp[~hole])
    warnings.warn(f"{src}, column 'temperature_c', row {int(first[0]) + 1}: {int(hole.sum())} NaN sample(s) in "
                  f"{first.size} hole(s) of at most {span[k]:.4g} s, filled by linear interpolation in time",
                  SocbenchWarning, stacklevel=5)
    return filled


@dataclass(frozen=True, eq=False)
class Profile:
    """A validated battery time series (see the module docstring for units and shapes)."""

    time_s: np.ndarray
    current_a: np.ndarray
    voltage_v: np.ndarray | None = None
    temperature_c: np.ndarray | None = None
    soc_ref: np.ndarray | None = None
    meta: ProfileMeta = field(default_factory=ProfileMeta)
    #: the error of a reference SOC given but refused (then ``soc_ref`` is None); raised by ``require``/``get``
    soc_ref_error: DataError | None = field(default=None, compare=False, repr=False)
    #: ``(min, max)`` of the reference values already validated (and warned about): derived profiles skip both
    soc_ref_checked: tuple | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        src = self.meta.source or self.meta.name
        t = np.asarray(self.time_s, dtype=float)
        if t.ndim != 1:
            raise DataError(f"time must be one-dimensional, got shape {t.shape}", file=src, column="time_s")
        if t.size == 0:
            raise DataError("no samples (empty profile)", file=src, column="time_s")
        object.__setattr__(self, "time_s", t)
        self._check_finite(t, "time_s", src)
        if t.size > 1:
            dt = np.diff(t)
            if np.any(dt <= 0):
                k = int(np.argmax(dt <= 0))
                kind = "duplicate time stamp" if dt[k] == 0 else "time goes backwards"
                raise DataError(f"{kind} ({t[k]:g} s then {t[k + 1]:g} s)", file=src, column="time_s", row=k + 2)
        for name in ("current_a", "voltage_v", "temperature_c", "soc_ref"):
            value = getattr(self, name)
            if value is None:
                if name == "current_a":
                    raise DataError("missing column", file=src, column=name)
                continue
            arr = np.asarray(value, dtype=float)
            if arr.shape[-1:] != t.shape:
                raise DataError(
                    f"has {arr.shape[-1] if arr.ndim else 0} samples but time has {t.size}", file=src, column=name
                )
            if arr.ndim > 2:
                raise DataError(f"expected (T,) or (runs, T), got shape {arr.shape}", file=src, column=name)
            if name == "temperature_c":
                arr = _fill_temperature_holes(arr, t, src)
            self._check_finite(arr, name, src)
            object.__setattr__(self, name, arr)
        self._check_soc_ref(src)
        shapes = {a.shape[:-1] for a in self._signals() if a is not None and a.ndim == 2}
        if len(shapes) > 1:
            raise DataError(f"batched columns disagree on the number of runs: {sorted(shapes)}", file=src)

    def _check_soc_ref(self, src: str) -> None:
        """The lenient check of the reference SOC (module docstring)."""
        z = self.soc_ref
        if z is None:
            return
        object.__setattr__(self, "soc_ref_error", None)  # a (new) reference replaces a refused one
        lo, hi = float(z.min()), float(z.max())
        done = self.soc_ref_checked
        if done is not None and done[0] <= lo and hi <= done[1]:
            return  # a subset of values already validated (a slice, a run, a copy)
        object.__setattr__(self, "soc_ref_checked", (lo, hi))
        if lo >= -SOC_TOLERANCE and hi <= 1 + SOC_TOLERANCE:
            return
        far = (z < -SOC_WARN_MARGIN) | (z > 1 + SOC_WARN_MARGIN)
        if far.any():
            row = _first_bad_row(far)
            value = float(z[..., row - 1].ravel()[0])
            # percent when most of the column lies above 1 (a count that overshoots once is not in percent)
            percent = 1 + SOC_WARN_MARGIN < hi <= 100 and lo >= 0 and float(np.mean(z > 1 + SOC_WARN_MARGIN)) > 0.5
            hint = ("percent values must be divided by 100" if percent
                    else f"more than {100 * SOC_WARN_MARGIN:g} points outside [0, 1]")
            error = DataError(f"SOC must be a fraction in [0, 1] (got {value:g}; {hint})", file=src,
                              column="soc_ref", row=row)
            object.__setattr__(self, "soc_ref", None)
            object.__setattr__(self, "soc_ref_error", error)
            object.__setattr__(self, "soc_ref_checked", None)
            return
        worst = lo if -lo > hi - 1 else hi
        row = _first_bad_row(z == worst)  # where it is furthest out
        warnings.warn(f"{src}, column 'soc_ref', row {row}: reference SOC reaches {worst:.10g}, outside [0, 1] by "
                      f"less than {100 * SOC_WARN_MARGIN:g} points (as a count from a nominal capacity does): "
                      "kept as is",
                      SocbenchWarning, stacklevel=4)

    @staticmethod
    def _check_finite(arr: np.ndarray, name: str, src: str) -> None:
        bad = ~np.isfinite(arr)
        if bad.any():
            row = _first_bad_row(bad) if arr.ndim else 1
            raise DataError("NaN or infinite value", file=src, column=name, row=row)

    def _signals(self):
        return (self.current_a, self.voltage_v, self.temperature_c, self.soc_ref)

    # ------------------------------------------------------------------ views
    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.time_s.size)

    @property
    def n_runs(self) -> int:
        """Number of Monte Carlo runs carried (1 for a plain profile)."""
        for a in self._signals():
            if a is not None and a.ndim == 2:
                return int(a.shape[0])
        return 1

    @property
    def batched(self) -> bool:
        return any(a is not None and a.ndim == 2 for a in self._signals())

    @property
    def dt(self) -> np.ndarray:
        """Step lengths ``dt_k = t_{k+1} - t_k`` (length T-1)."""
        return np.diff(self.time_s)

    @property
    def duration_s(self) -> float:
        return float(self.time_s[-1] - self.time_s[0])

    @property
    def name(self) -> str:
        return self.meta.name

    def run(self, r: int) -> Profile:
        """Run ``r`` of a batched profile as a plain profile."""

        def pick(a):
            return None if a is None else (a[r] if a.ndim == 2 else a)

        return replace(
            self,
            current_a=pick(self.current_a),
            voltage_v=pick(self.voltage_v),
            temperature_c=pick(self.temperature_c),
            soc_ref=pick(self.soc_ref),
        )

    def slice(self, start: int, stop: int | None = None) -> Profile:
        """Samples ``start:stop`` (time kept as is)."""
        sl = slice(start, stop)

        def cut(a):
            return None if a is None else a[..., sl]

        return replace(
            self,
            time_s=self.time_s[sl],
            current_a=cut(self.current_a),
            voltage_v=cut(self.voltage_v),
            temperature_c=cut(self.temperature_c),
            soc_ref=cut(self.soc_ref),
        )

    def with_(self, **changes) -> Profile:
        """A validated copy with some fields replaced."""
        return replace(self, **changes)

    def require(self, *columns: str) -> None:
        """Raise a :class:`DataError` naming the first of ``columns`` the profile lacks (for a reference SOC that was
        given but refused: the error kept for it, with its row)."""
        for c in columns:
            if getattr(self, c) is None:
                if c == "soc_ref" and self.soc_ref_error is not None:
                    raise self.soc_ref_error
                raise DataError("missing column", file=self.meta.source or self.meta.name, column=c)

    def get(self, column: str) -> np.ndarray | None:
        """The values of an optional column, None when the record has none. Call it where the values are *used*: a
        reference SOC that was given but refused raises its kept :class:`DataError` here, rather than passing as
        "no reference"."""
        value = getattr(self, column)
        if value is None and column == "soc_ref" and self.soc_ref_error is not None:
            raise self.soc_ref_error
        return value

    def gaps(self, factor: float = GAP_FACTOR) -> list[tuple[int, float]]:
        """Sample gaps longer than ``factor`` × the median step: ``[(row, gap_s), ...]`` (rows from 1)."""
        if self.n < 3:
            return []
        dt = self.dt
        idx = np.nonzero(gap_steps(dt, factor))[0]
        return [(int(k) + 2, float(dt[k])) for k in idx]

    def amp_hours(self) -> np.ndarray:
        """Discharged charge since the first sample [Ah], zero-order hold on the current (shape like current)."""
        i = self.current_a
        dq = i[..., :-1] * self.dt / 3600.0
        out = np.zeros_like(i)
        out[..., 1:] = np.cumsum(dq, axis=-1)
        return out

    def to_frame(self):
        """A pandas DataFrame of a plain (non-batched) profile, canonical column names."""
        import pandas as pd

        if self.batched:
            raise ValueError("to_frame() needs a plain profile; use run(r) first")
        cols = {"time_s": self.time_s, "current_a": self.current_a}
        for c in ("voltage_v", "temperature_c", "soc_ref"):
            if getattr(self, c) is not None:
                cols[c] = getattr(self, c)
        return pd.DataFrame(cols)
