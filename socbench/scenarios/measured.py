"""Measured-data scenarios: a recorded drive cycle or flight replayed with its own current, voltage and temperature.

A ``kind = "measured"`` scenario names a record of a dataset under ``$SOCBENCH_DATA_DIR`` (:class:`MeasuredSpec`):

* ``record``: the record that is scored (a file of the dataset folder; for the DJI flights ``"log_id#segment"``);
* ``characterisation`` (+ ``ocv_test``): the identification records the models are fitted on, never a scored
  record and never a drive cycle's own data (:class:`Characterisation`, ``fit`` says how):

  - ``"hppc"``: one HPPC per temperature, the temperature-aware fit of :mod:`socbench.identify.temperature`;
  - ``"ocv+dynamic"``: the OCV from a slow (C/20) test's discharge branch (the scored records are discharges from
    full), the dynamics fitted on one *other* dynamic record of the same cell;
  - ``"flights"``: other flights of the fleet: the OCV regressed from them (``v = U(z) − R·I`` at the counted SOC,
    linear least squares, made monotone), then the model fitted on them back to back (charge between flights added
    from their references);
* ``validation``: records on which the noise recipe (:mod:`socbench.estimators.model_error`) measures the fitted
  model's error (never the scored record); empty: the identification records. They also choose **how** each model
  is fitted: every setting of :data:`~socbench.identify.FIT_SETTINGS` (SOC form × sample weighting; over several
  temperatures also a setting per temperature and the charge-transfer term) is fitted on the characterisation and the
  one that predicts the validation records best is kept (:func:`~socbench.identify.select_temperature_fit`,
  :func:`~socbench.identify.select_fit`), whatever fit mode the study names for its synthetic scenarios: a model
  fitted in the paper's mode on the five Panasonic HPPCs misses the −20 °C US06 by far more than the mode that
  validates best, and a leaderboard would then rank the fit setting, not the filters.

Reference SOC: the loader's (Panasonic: counted from full with the capacity measured at that temperature; CALCE:
counted between full charges; DJI flights: counted from the pack's own SOC at take-off with 5.5 Ah, the pack's own SOC
kept beside it as ``meta.extra["bms_soc"]``). ``realize(seeds)`` repeats the record per seed; the ``[sensors]``
channels optionally add noise (and any other impairment) on top, and ``soc0_error``/``soc0_error_sd`` perturb the
initial SOC guess per seed. Without the data the scenario is *unavailable* (:meth:`MeasuredScenario.available`): it
is listed as such and skipped, never an error.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DataError
from ..estimators.noise import SensorNoise
from ..profile import Profile, ProfileMeta
from .scenario import FIT_METHODS, MIN_CURRENT_SD, MIN_VOLTAGE_SD, MeasuredSpec, Scenario, _key, _seeds
from .sensors import apply_channel, initial_soc_guess

__all__ = ["FIT_METHODS", "MeasuredSpec", "MeasuredScenario", "Characterisation", "data_root", "load_record",
           "dji_flights", "flight_ocv"]

DJI_DATASET = "uav_dji_m100"


def data_root() -> Path | None:
    d = os.environ.get("SOCBENCH_DATA_DIR")
    return Path(d) if d else None


def _path(dataset: str, name: str) -> Path | None:
    root = data_root()
    return None if root is None else root / dataset / name


# ------------------------------------------------------------------------------------------------ loading
@lru_cache(maxsize=48)
def _load_cached(dataset: str, name: str, fmt: str, stamp: tuple) -> Profile:
    if dataset == DJI_DATASET:
        return dji_flights([name])
    from ..datasets import load

    return load(_path(dataset, name), fmt)


def load_record(dataset: str, name: str, fmt: str = "auto") -> Profile:
    """One record of a dataset under ``$SOCBENCH_DATA_DIR`` (cached per process; DJI: a ``log_id#segment``)."""
    p = _path(dataset, DJI_TELEMETRY if dataset == DJI_DATASET else name)
    if p is None:
        raise DataError(f"SOCBENCH_DATA_DIR is not set: the measured record {dataset}/{name} is unavailable")
    if not p.exists():
        raise DataError("file not found (SOCBENCH_DATA_DIR)", file=str(p))
    st = p.stat()
    return _load_cached(dataset, name, fmt, (str(p), st.st_size, st.st_mtime_ns))


DJI_TELEMETRY = "battery_telemetry_all_flights.csv"


def dji_flights(keys) -> Profile:
    """DJI flights (``"log_id#segment"``) as one profile, back to back: the reference SOC of each counted from the
    pack's own SOC at its first record with :data:`~socbench.datasets.dji.CAPACITY_AH`; between flights one rest
    sample (zero current), the charge put back in the pack known only to the reference. ``meta.extra["bms_soc"]`` is
    the pack's own SOC estimate."""
    from ..datasets.counting import charge_counter
    from ..datasets.dji import CAPACITY_AH, N_SERIES, read_segments

    folder = _path(DJI_DATASET, "")
    segments, _ = read_segments(folder)
    by_key = {s.key: s for s in segments}
    parts = {k: [] for k in ("t", "i", "v", "T", "z", "bms")}
    t_next = 0.0
    for key in keys:
        if key not in by_key:
            raise DataError(f"no flight '{key}' in the DJI data", file=str(folder / DJI_TELEMETRY))
        s = by_key[key]
        # held current between the event-driven records (ZOH), counted from the pack's own SOC at the first record
        z = s.soc_bms[0] + charge_counter(s.time_s, s.current_a) / CAPACITY_AH
        t = s.time_s + t_next
        i = s.current_a.copy()
        if parts["t"]:  # a rest sample ends the previous flight: no phantom current over the gap
            parts["i"][-1][-1] = 0.0
        for k, a in zip(("t", "i", "v", "T", "z", "bms"), (t, i, s.voltage_v, s.temperature_c, z, s.soc_bms)):
            parts[k].append(np.asarray(a, dtype=float))
        t_next = float(t[-1]) + 600.0
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    meta = ProfileMeta(name="+".join(keys) if len(keys) < 3 else f"{len(keys)} DJI flights",
                       source=str(folder / DJI_TELEMETRY), capacity_ah=CAPACITY_AH, n_series=N_SERIES,
                       chemistry="LiHV 6S (DJI TB48D, inferred)",
                       extra={"soc_ref_capacity_ah": CAPACITY_AH, "bms_soc": cat["bms"], "flights": list(keys),
                              "reference": "counted from the pack's own SOC at take-off with 5.5 Ah"})
    return Profile(cat["t"], cat["i"], cat["v"], cat["T"], np.clip(cat["z"], 0.0, 1.0), meta)


# ------------------------------------------------------------------------------------------------ characterisation
@dataclass(frozen=True, eq=False)
class Characterisation:
    """What a measured scenario's models are fitted on, and how (``method`` ∈ :data:`FIT_METHODS`)."""

    method: str
    records: tuple
    ocv_test: Profile | None = None
    name: str = ""
    #: records that choose the fit setting (the scenario's validation records; empty: the ``mode`` given is used)
    validation: tuple = ()

    def fingerprint(self) -> str:
        """SHA-256 over the method and every record's samples (identification and validation): equal fingerprints,
        equal fits."""
        from ..study.grid import profile_fingerprint

        h = hashlib.sha256((self.method + ("/validated" if self.validation else "")).encode())
        for p in self.records + ((self.ocv_test,) if self.ocv_test is not None else ()) + self.validation:
            h.update(profile_fingerprint(p).encode())
        return h.hexdigest()

    def fit(self, model: str, mode: str = "paper", **kw):
        """Fit ``model``: a result with ``params``, ``rmse_v`` and ``warnings``. With validation records the setting
        (``mode`` included) is chosen on them (module docstring; ``kw`` then reaches only a single-record fit); else
        ``mode``."""
        from ..identify import FIT_SETTINGS, fit_model, select_fit, select_temperature_fit
        from ..identify.hppc import ocv_from_slow_test
        from ..identify.temperature import fit_temperatures

        if self.method == "hppc":
            if self.validation:
                return select_temperature_fit(model, self.records, self.validation)
            return fit_temperatures(model, self.records, mode=mode, **kw)
        if self.method == "ocv+dynamic":
            cur = np.abs(self.ocv_test.current_a)
            moving = cur[cur > 1e-3 * float(cur.max())]
            # the branches are the runs at the test's typical (median) current, whatever a CV top-off did before
            slow = ocv_from_slow_test(self.ocv_test, i_min=0.5 * float(np.median(moving)))
            # the scored records are discharges from full: the discharge branch is the OCV they follow
            kw = {"ocv": slow.discharge, "capacity_ah": slow.capacity_ah, **kw}
        else:
            kw = {"ocv": flight_ocv(self.records[0]), "capacity_ah": self.records[0].meta.capacity_ah, **kw}
        if self.validation:
            return select_fit(model, self.records[0], self.validation, candidates=FIT_SETTINGS, **kw).fit
        return fit_model(model, self.records[0], mode=mode, **kw)


def flight_ocv(profile: Profile, step: float = 0.05):
    """OCV from flights at their counted SOC: ``v_k = U(z_k) − R·I_k`` with ``U`` piecewise linear on knots every
    ``step`` over the SOC range covered and one resistance ``R``, by linear least squares; made monotone."""
    from ..ocv import OCVCurve, monotone_points

    z, i, v = profile.soc_ref, profile.current_a, profile.voltage_v
    lo, hi = float(np.floor(z.min() / step) * step), float(np.ceil(z.max() / step) * step)
    knots = np.arange(lo, hi + step / 2, step)
    A = np.zeros((z.size, knots.size + 1))
    j = np.clip(np.searchsorted(knots, z, side="right") - 1, 0, knots.size - 2)
    w = (z - knots[j]) / step
    A[np.arange(z.size), j] = 1.0 - w
    A[np.arange(z.size), j + 1] = w
    A[:, -1] = -i
    sol, *_ = np.linalg.lstsq(A, v, rcond=None)
    used = np.bincount(j, minlength=knots.size) + np.bincount(j + 1, minlength=knots.size)
    keep = used[: knots.size] > 0
    zk, uk = monotone_points(knots[keep], sol[:-1][keep])
    return OCVCurve(zk, uk, f"regressed from {profile.name} (v = U(z) − R·I, R = {1000 * sol[-1]:.1f} mΩ)")


# ------------------------------------------------------------------------------------------------ the scenario
class MeasuredScenario(Scenario):
    """A scenario of kind ``measured`` (module docstring)."""

    @property
    def measured(self) -> MeasuredSpec:
        return self.spec.measured

    # ------------------------------------------------------------------ availability
    def missing(self) -> str | None:
        """Why the scenario cannot run (None: it can)."""
        m = self.measured
        root = data_root()
        if root is None:
            return "needs SOCBENCH_DATA_DIR"
        folder = root / m.dataset
        if not folder.is_dir():
            return f"no {m.dataset} under SOCBENCH_DATA_DIR"
        if m.dataset == DJI_DATASET:
            return None if (folder / DJI_TELEMETRY).exists() else f"no {DJI_TELEMETRY} in {folder}"
        for name in (m.record,) + m.characterisation + m.validation + ((m.ocv_test,) if m.ocv_test else ()):
            if not (folder / name).exists():
                return f"missing {m.dataset}/{name}"
        return None

    def available(self) -> bool:
        return self.missing() is None

    def _require(self):
        why = self.missing()
        if why is not None:
            raise DataError(f"scenario {self.name} is unavailable: {why}")

    # ------------------------------------------------------------------ description
    @property
    def true_capacity_ah(self) -> float:
        return float(self.record().meta.capacity_ah)

    @property
    def declared_capacity_ah(self) -> float:
        return self.true_capacity_ah

    def summary(self) -> str:
        why = self.missing()
        return f"{self.name:<16} {self.kind:<8} {self.description}" + (f"  [unavailable: {why}]" if why else "")

    def to_dict(self) -> dict:
        """The spec plus the identity (size, mtime) of the data files it reads (a changed file changes the key)."""
        d = asdict(self.spec)
        d["truth"]["ocv"] = self.spec.truth.ocv.to_dict()
        d.pop("file", None)
        m = self.measured
        files = {}
        for name in sorted(set((m.record,) + m.characterisation + m.validation + ((m.ocv_test,) if m.ocv_test
                                                                                  else ()))):
            p = _path(m.dataset, DJI_TELEMETRY if m.dataset == DJI_DATASET else name)
            if p is not None and p.exists():
                st = p.stat()
                files[name] = [st.st_size, st.st_mtime_ns]
        d["data_files"] = files
        return d

    # ------------------------------------------------------------------ data
    def _load(self, name: str) -> Profile:
        m = self.measured
        return load_record(m.dataset, name, m.format)

    def record(self) -> Profile:
        """The scored record as loaded (one run)."""
        self._require()
        return self._load(self.measured.record)

    def truth_record(self):
        raise ConfigError(f"scenario {self.name} replays a measured record: it has no simulated truth")

    def realize(self, seeds) -> Profile:
        """The record once per seed ``(R, T)``, the ``[sensors]`` channel impairments (default none) on top."""
        seeds = _seeds(seeds)
        rec = self.record()
        s = self.spec.sensors
        key = _key(self.name)
        cols = {}
        for j, (col, channel) in enumerate((("current_a", s.current), ("voltage_v", s.voltage),
                                            ("temperature_c", s.temperature))):
            x = getattr(rec, col)
            if x is None:
                cols[col] = None
                continue
            cols[col] = apply_channel(x, rec.time_s, channel, seeds, key, j)[0]
        R = len(seeds)
        extra = {**rec.meta.extra, "scenario": self.name, "kind": self.kind, "seeds": list(seeds),
                 "record": self.measured.record}
        meta = ProfileMeta(name=self.name, source=f"scenario:{self.name} ({rec.meta.source})",
                           capacity_ah=rec.meta.capacity_ah, n_series=rec.meta.n_series,
                           chemistry=rec.meta.chemistry, extra=extra)
        soc = None if rec.soc_ref is None else np.repeat(rec.soc_ref[None, :], R, axis=0)
        return Profile(rec.time_s, cols["current_a"], cols["voltage_v"], cols["temperature_c"], soc, meta)

    def characterisation(self, seed: int = 0) -> Characterisation:
        """The identification records and how the models are fitted on them (the same for every seed)."""
        self._require()
        m = self.measured
        if m.fit == "flights":
            records = (dji_flights(list(m.characterisation)),)
        else:
            records = tuple(self._load(n) for n in m.characterisation)
        ocv = self._load(m.ocv_test) if m.ocv_test else None
        validation = tuple(self.noise_records()) if m.validation else ()
        return Characterisation(m.fit, records, ocv, name=f"{self.name}/characterisation", validation=validation)

    def noise_records(self) -> list:
        """Records the noise recipe measures the model error on: the validation records, else the identification
        records (never the scored one)."""
        self._require()
        m = self.measured
        if m.validation:
            if m.dataset == DJI_DATASET:
                return [dji_flights([k]) for k in m.validation]
            return [self._load(n) for n in m.validation]
        return [r for r in self.characterisation().records if r.soc_ref is not None]

    def calibration_records(self) -> list:
        """The records the filters' NIS calibrates the recipe on (:mod:`socbench.estimators.nis_calibration`): the
        validation records, none without them (the identification records taught the model what it knows)."""
        return self.noise_records() if self.measured.validation else []

    def noise_measured_on(self) -> str:
        """What :meth:`noise_records` are (:attr:`~socbench.estimators.model_error.ModelErrorStats.measured_on`):
        "validation" with validation records, else "identification"."""
        return "validation" if self.measured.validation else "identification"

    def initial_soc(self, seeds) -> np.ndarray:
        """Initial SOC guesses ``(R,)`` on the record's own SOC axis: its reference at the start plus the error."""
        rec = self.record()
        return initial_soc_guess(float(rec.soc_ref[0]), self.spec.sensors, _seeds(seeds), _key(self.name))

    def sensor_noise(self) -> SensorNoise:
        """The recording instruments' declared SDs plus the white noise the ``[sensors]`` channels add."""
        s, m = self.spec.sensors, self.measured
        return SensorNoise(voltage_sd=max(float(np.hypot(m.voltage_sd, s.voltage.white_sd)), MIN_VOLTAGE_SD),
                           current_sd=max(float(np.hypot(m.current_sd, s.current.white_sd)), MIN_CURRENT_SD),
                           dt=float(np.median(np.diff(self.record().time_s))),
                           current_bias_sd=abs(s.current.offset))

    @property
    def added_voltage_sd(self) -> float:
        """White voltage noise added on top of the record (not in any residual the recipe measured)."""
        return float(self.spec.sensors.voltage.white_sd)
