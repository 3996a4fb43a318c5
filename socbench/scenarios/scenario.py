"""A scenario: a load (synthetic mission, replayed flight or HPPC), a truth cell, a lab schedule and a sensor model.

``Scenario.realize(seeds)`` runs the truth once (it is the same cell and the same mission for every run; the result
is cached) and measures it with the sensors once per seed, batched: a :class:`~socbench.profile.Profile` with
``current_a, voltage_v, temperature_c`` of shape ``(R, T)``, ``soc_ref`` the true SOC ``(R, T)`` and
``meta.capacity_ah`` the *declared* capacity. ``characterisation(seed)`` is the HPPC test of the same truth cell,
measured by the same sensors without their timed faults (a lab test, at the HPPC ambient temperature).
"""

from __future__ import annotations

import zlib
from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache

import numpy as np

from .. import loads
from ..errors import ConfigError
from ..estimators.noise import SensorNoise
from ..profile import Profile, ProfileMeta
from .config import require
from .mission import Mission, Vehicle, fly
from .schedule import Record, Schedule, lab_schedule, prepare, rest, run_current
from .sensors import SensorSpec, apply_channel, initial_soc_guess, jitter_offsets
from .truth import TEMP, TruthCell, TruthParams, Z

#: step of the truth simulation of everything the sensors record [s]
TRUTH_DT = 1.0
KINDS = ("mission", "replay", "hppc", "measured")
#: how a measured scenario's models are fitted (socbench.scenarios.measured.Characterisation)
FIT_METHODS = ("hppc", "ocv+dynamic", "flights")
#: smallest white-noise SDs handed to the estimators (an ideal sensor still needs R > 0)
MIN_VOLTAGE_SD = 1e-3
MIN_CURRENT_SD = 1e-3


@dataclass(frozen=True)
class ReplaySpec:
    """Which flight current a ``replay`` scenario plays: the shipped template or selected real segments."""

    source: str = "template"  # "template" | "data" ($SOCBENCH_DATA_DIR/uav_dji_m100)
    segments: tuple = ()  # for "data": "log_id#segment" keys, played back to back
    reserve_soc: float = 0.0
    max_duration_s: float = 4 * 3600.0

    def __post_init__(self):
        require(self.source in ("template", "data"), "source", f"must be 'template' or 'data', got {self.source!r}")
        require(isinstance(self.segments, tuple) and all(isinstance(k, str) for k in self.segments), "segments",
                f"must be a list of \"log_id#segment\" strings, got {self.segments!r}")
        require(self.source != "data" or len(self.segments) > 0, "segments", "source 'data' needs segment keys")
        require(0 <= self.reserve_soc < 1, "reserve_soc", f"must be in [0, 1), got {self.reserve_soc}")
        require(self.max_duration_s > 0, "max_duration_s", "must be > 0")


@dataclass(frozen=True)
class HppcSpec:
    """The characterisation test (socbench.loads.hppc at 1 s): 1 C pulses, 10 % SOC steps, rests.

    Defaults keep it under 10 000 samples (9 900) so that fits are quick: 8.7 min rests leave ≈ 12 % of the slow RC
    branch (τ2 = 240 s), a few mV at the OCV points."""

    c_rate: float = 1.0
    pulse_s: float = 10.0
    rest_pulse_s: float = 20.0
    charge_ratio: float = 0.75
    rest_s: float = 520.0
    ambient_c: float = 25.0

    def __post_init__(self):
        for name in ("c_rate", "pulse_s", "rest_pulse_s", "rest_s"):
            require(getattr(self, name) > 0, name, f"must be > 0, got {getattr(self, name)}")
        require(0 <= self.charge_ratio <= 1, "charge_ratio", f"must be in [0, 1], got {self.charge_ratio}")
        require(-60 <= self.ambient_c <= 80, "ambient_c", f"must be in [-60, 80] °C, got {self.ambient_c}")


@dataclass(frozen=True)
class ValidationSpec:
    """Validation flights: the scenario's mission flown again by the same truth cell, in the same schedule and
    measured by the same lab sensors, with other payloads (and another gust realisation). They are the cell's
    "other loads" the noise recipe measures a fitted model's error on (:meth:`Scenario.noise_records`), as a measured
    scenario's validation drive cycles are; never the scored load."""

    payloads_kg: tuple = ()

    def __post_init__(self):
        require(isinstance(self.payloads_kg, tuple) and all(isinstance(m, (int, float)) and not isinstance(m, bool)
                                                            and m >= 0 for m in self.payloads_kg), "payloads_kg",
                f"must be a list of payloads >= 0 [kg], got {self.payloads_kg!r}")


@dataclass(frozen=True)
class MeasuredSpec:
    """Which measured record a ``measured`` scenario replays and what its models are fitted on
    (:mod:`socbench.scenarios.measured`)."""

    dataset: str = ""
    record: str = ""
    format: str = "auto"
    fit: str = "hppc"
    characterisation: tuple = ()
    ocv_test: str = ""
    validation: tuple = ()
    #: white-noise SDs of the recording instruments, declared for the filters' covariances [V], [A]
    voltage_sd: float = 1e-3
    current_sd: float = 0.01
    reference: str = ""  # how the record's reference SOC is defined, for the docs

    def __post_init__(self):
        for name in ("characterisation", "validation"):
            v = getattr(self, name)
            require(isinstance(v, tuple) and all(isinstance(x, str) for x in v), name,
                    f"must be a list of record names, got {v!r}")
        require(bool(self.dataset) and bool(self.record), "record", "a measured scenario needs dataset and record")
        require(self.fit in FIT_METHODS, "fit", f"must be one of {', '.join(FIT_METHODS)}, got {self.fit!r}")
        require(len(self.characterisation) > 0, "characterisation", "needs at least one identification record")
        require(self.record not in self.characterisation, "characterisation",
                "must not contain the scored record (models are fitted on characterisation tests only)")
        require(self.record not in self.validation, "validation", "must not contain the scored record")
        require(self.fit != "ocv+dynamic" or bool(self.ocv_test), "ocv_test", "fit 'ocv+dynamic' needs an ocv_test")
        require(self.voltage_sd > 0 and self.current_sd > 0, "voltage_sd", "instrument SDs must be > 0")


@dataclass(frozen=True)
class ScenarioSpec:
    name: str
    description: str = ""
    kind: str = "mission"
    truth: TruthParams = field(default_factory=TruthParams)
    schedule: Schedule = field(default_factory=Schedule)
    mission: Mission = field(default_factory=Mission)
    vehicle: Vehicle = field(default_factory=Vehicle)
    replay: ReplaySpec = field(default_factory=ReplaySpec)
    hppc: HppcSpec = field(default_factory=HppcSpec)
    validation: ValidationSpec = field(default_factory=ValidationSpec)
    sensors: SensorSpec = field(default_factory=SensorSpec)
    measured: MeasuredSpec | None = None
    group: str = ""
    file: str = ""

    def __post_init__(self):
        require(self.kind in KINDS, "kind", f"must be one of {', '.join(KINDS)}, got {self.kind!r}")
        require((self.kind == "measured") == (self.measured is not None), "measured",
                "a [measured] table is what a kind = \"measured\" scenario needs, and only it")
        require(self.kind != "measured" or not self.validation.payloads_kg, "validation",
                "a measured scenario names its validation records in [measured] validation")
        ratio = self.sensors.dt / TRUTH_DT
        require(self.kind == "measured" or (abs(ratio - round(ratio)) < 1e-9 and ratio >= 1), "sensors.dt",
                f"must be a multiple of the truth step {TRUTH_DT:g} s, got {self.sensors.dt}")


# ------------------------------------------------------------------------------------------------ truth (cached)
@lru_cache(maxsize=32)
def _prepared(truth: TruthParams, schedule: Schedule):
    x, _ = prepare(TruthCell(truth), schedule)
    return x


@lru_cache(maxsize=32)
def _load_record(kind: str, truth: TruthParams, schedule: Schedule, mission: Mission, vehicle: Vehicle,
                 replay: ReplaySpec) -> Record:
    """True signals of the recorded part of the lab schedule (the end of the rest, the load, the rest after)."""
    if kind == "mission":
        def load(cell, x, dt, amb):
            return fly(cell, x, mission, vehicle, dt, amb)
    else:
        def load(cell, x, dt, amb):
            return _replay(cell, x, replay, dt, amb)
    return lab_schedule(TruthCell(truth), schedule, load, TRUTH_DT, x0=_prepared(truth, schedule))


def _replay(cell: TruthCell, x, replay: ReplaySpec, dt: float, amb: float) -> Record:
    """The replayed flight current (at C-rate on the truth pack), repeated until UV, the reserve or the time limit."""
    from .replay import data_pattern, template_pattern

    rates, phases = template_pattern(dt) if replay.source == "template" else data_pattern(list(replay.segments), dt)
    period = rates.size * dt
    reps = max(int(np.ceil(replay.max_duration_s / period)), 1)
    current = np.tile(rates, reps)[: int(replay.max_duration_s / dt)] * cell.params.capacity_ah
    rec = run_current(cell, x, current, dt, amb, stop_uv=True, reserve_soc=replay.reserve_soc,
                      phases=[(n, t + r * period) for r in range(reps) for n, t in phases])
    rec.phases = [p for p in rec.phases if p[1] <= rec.time[-1]]
    return rec


@lru_cache(maxsize=8)
def _hppc_record(truth: TruthParams, hppc: HppcSpec) -> Record:
    """The HPPC of the truth cell from full (z = 1, on the charge branch after CC-CV, relaxed) at 1 s."""
    cell = TruthCell(truth)
    prof = loads.hppc(truth.capacity_ah, c_rate=hppc.c_rate, dt=TRUTH_DT, pulse_s=hppc.pulse_s,
                      rest_pulse_s=hppc.rest_pulse_s, charge_ratio=hppc.charge_ratio, rest_s=hppc.rest_s)
    x = cell.initial_state(1.0, hppc.ambient_c, hyst=1.0, batch=1)
    rec = run_current(cell, x, prof.current_a, TRUTH_DT, hppc.ambient_c, phases=[("hppc", 0.0)])
    rec.stop_reason = "end"
    return rec


@lru_cache(maxsize=8)
def _capacity_record(truth: TruthParams, hppc: HppcSpec) -> Record:
    """The capacity test of the truth cell at the HPPC ambient, 1 s: from full (relaxed, on the charge branch) a 1 C
    discharge to the under-voltage limit, then a 30 min rest."""
    cell = TruthCell(truth)
    x = cell.initial_state(1.0, hppc.ambient_c, hyst=1.0, batch=1)
    amps = np.full(int(1.05 * 3600.0 / TRUTH_DT), truth.capacity_ah)
    dis = run_current(cell, x, amps, TRUTH_DT, hppc.ambient_c, stop_uv=True, phases=[("1C", 0.0)])
    after = rest(cell, dis.last_state, 1800.0, TRUTH_DT, hppc.ambient_c)
    return Record.concat([dis, after])


def _key(name: str) -> int:
    return zlib.crc32(name.encode("utf-8"))


def _seeds(seeds) -> list[int]:
    if isinstance(seeds, (int, np.integer)):
        seeds = [int(seeds)]
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ConfigError("realize() needs at least one seed")
    if any(s < 0 for s in seeds):
        raise ConfigError(f"seeds must be non-negative integers, got {seeds}")
    return seeds


class Scenario:
    """One named scenario (see the module docstring). Build it with :func:`socbench.scenarios.load_scenario`."""

    def __init__(self, spec: ScenarioSpec):
        self.spec = spec

    # ------------------------------------------------------------------ description
    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def description(self) -> str:
        return self.spec.description

    @property
    def kind(self) -> str:
        return self.spec.kind

    @property
    def truth_cell(self) -> TruthCell:
        return TruthCell(self.spec.truth)

    @property
    def true_capacity_ah(self) -> float:
        return self.spec.truth.capacity_ah

    @property
    def declared_capacity_ah(self) -> float:
        return self.spec.truth.capacity_ah * (1.0 + self.spec.sensors.capacity_mismatch)

    @property
    def group(self) -> str:
        """The catalog group (``measured``: the measured-data scenarios; empty: none)."""
        return self.spec.group

    def missing(self) -> str | None:
        """Why the scenario cannot run here (None: it can; a simulated scenario always can)."""
        return None

    def available(self) -> bool:
        return self.missing() is None

    def noise_records(self) -> list:
        """Records with a known SOC on which the noise recipe measures a fitted model's error, never the scenario's
        load: the lab tests of the truth cell — the characterisation HPPC and the capacity test (:meth:`capacity_test`,
        a sustained discharge into the knee that the HPPC's short pulses do not show) — and the validation flights
        the scenario declares (:meth:`validation_flights`). The 1 C lab tests alone do not show the error of a model
        fitted on them under a flight's sustained 2–7 C (``docs/flight_consistency.md``); the flights alone show
        only that."""
        return [self.characterisation(), self.capacity_test()] + self.validation_flights()

    def noise_measured_on(self) -> str:
        """What :meth:`noise_records` are to a model fitted on the characterisation
        (:attr:`~socbench.estimators.model_error.ModelErrorStats.measured_on`): "validation" when the scenario declares
        validation flights (loads the model was not fitted on, pooled with its lab tests), else "identification"."""
        return "validation" if self.spec.validation.payloads_kg else "identification"

    def calibration_records(self) -> list:
        """The noise records that are loads the fitted model was not fitted on, with a known SOC: the filters' NIS
        on them calibrates the recipe (:mod:`socbench.estimators.nis_calibration`). The validation flights."""
        return self.validation_flights()

    def validation_flights(self, seed: int = 0) -> list:
        """The scenario's mission flown again with each payload of ``[validation] payloads_kg``
        (:class:`ValidationSpec`) by the same truth cell, from the same lab schedule, measured by the same sensors
        without their timed faults; each with a gust realisation of its own (not the scored flight's)."""
        s = self.spec
        out = []
        for j, payload in enumerate(s.validation.payloads_kg):
            mission = replace(s.mission, payload_kg=float(payload), gust_seed=s.mission.gust_seed + 1 + j)
            rec = _load_record("mission", s.truth, s.schedule, mission, s.vehicle, ReplaySpec())
            out.append(self._lab_test(rec, "validation", (s.truth, s.schedule, mission, s.vehicle), seed,
                                      f"validation-{payload:g}kg"))
        return out

    def capacity_test(self, seed: int = 0) -> Profile:
        """The 1 C capacity test of the same truth cell (to the under-voltage limit, then 30 min rest), measured like
        :meth:`characterisation`."""
        return self._lab_test(_capacity_record(self.spec.truth, self.spec.hppc), "capacity",
                              (self.spec.truth, self.spec.hppc), seed)

    def _lab_test(self, rec: Record, kind: str, identity: tuple, seed: int, label: str | None = None) -> Profile:
        """``rec`` measured by the scenario's sensors without their timed faults, as one run named
        ``<scenario>/<label>`` (default ``kind``). The noise stream is keyed by the kind of test and what it is
        (``identity``: cell, schedule, load) and the sensors, not by the scenario's name: scenarios that share a truth
        cell and lab sensors share one test (hence one set of fitted models, one measured model error)."""
        sensors = self.spec.sensors.without_faults()
        key = _key(kind + "/" + repr(identity + (sensors,)))
        return self._measure(rec, sensors, _seeds(seed), key, f"{self.name}/{label or kind}").run(0)

    @property
    def added_voltage_sd(self) -> float:
        """White voltage noise on the filtered record that no residual record carries (0: the characterisation
        test is measured by the same sensors)."""
        return 0.0

    def __repr__(self) -> str:
        return f"Scenario({self.name!r}, kind={self.kind!r})"

    def to_dict(self) -> dict:
        """Everything that defines the scenario's data, JSON-ready (studies fingerprint it to key their results)."""
        d = asdict(self.spec)
        d["truth"]["ocv"] = self.spec.truth.ocv.to_dict()
        d.pop("file", None)
        if self.kind == "replay" and self.spec.replay.source == "template":
            from .replay import load_template

            d["replay"]["template"] = load_template().to_csv(index=False)
        return d

    # ------------------------------------------------------------------ truth
    def truth_record(self) -> Record:
        """True signals at 1 s of what ``realize`` measures (cached across scenarios with the same truth and load)."""
        s = self.spec
        if s.kind == "hppc":
            return _hppc_record(s.truth, s.hppc)
        return _load_record(s.kind, s.truth, s.schedule, s.mission, s.vehicle, s.replay)

    # ------------------------------------------------------------------ measurement
    def _measure(self, rec: Record, sensors: SensorSpec, seeds: list, key: int, name: str) -> Profile:
        step = int(round(sensors.dt / TRUTH_DT))
        idx = np.arange(0, rec.time.size, step)
        t = rec.time[idx]
        R = len(seeds)
        delta = jitter_offsets(t, sensors, seeds, key)
        f = np.clip((t[None, :] + delta - rec.time[0]) / TRUTH_DT, 0.0, rec.time.size - 1.0)
        k0 = np.floor(f).astype(int)
        k1 = np.minimum(k0 + 1, rec.time.size - 1)
        w = f - k0
        v_true = rec.voltage[0]
        temp_true = rec.states[0, :, TEMP]
        i_true = rec.current[0]

        def lin(a):
            return a[k0] * (1.0 - w) + a[k1] * w

        truth = {"current_a": i_true[k0], "voltage_v": lin(v_true), "temperature_c": lin(temp_true)}
        measured, flags = {}, {}
        for j, (col, channel) in enumerate((("current_a", sensors.current), ("voltage_v", sensors.voltage),
                                            ("temperature_c", sensors.temperature))):
            measured[col], flags[col] = apply_channel(truth[col], t, channel, seeds, key, j)
        soc = np.clip(rec.states[0, idx, Z], 0.0, 1.0)
        extra = {
            "scenario": self.name, "kind": self.kind, "seeds": list(seeds), "true_capacity_ah": self.true_capacity_ah,
            "stop_reason": rec.stop_reason, "phases": list(rec.phases),
            "truth": {"current_a": i_true[idx], "voltage_v": v_true[idx], "temperature_c": temp_true[idx]},
            "dropouts": {c: m for c, m in flags.items() if m.any()},
        }
        meta = ProfileMeta(name=name, source=f"scenario:{self.name}" + (f" ({self.spec.file})" if self.spec.file
                                                                         else ""),
                           capacity_ah=self.declared_capacity_ah, n_series=self.spec.truth.n_series,
                           chemistry="LiPo (truth: ESC-like 2RC + hysteresis + thermal + Butler-Volmer)", extra=extra)
        return Profile(t - t[0], measured["current_a"], measured["voltage_v"], measured["temperature_c"],
                       np.repeat(soc[None, :], R, axis=0), meta=meta)

    def realize(self, seeds) -> Profile:
        """The measured batch for ``seeds`` (an int or a sequence of ints): arrays ``(R, T)``, true SOC attached."""
        seeds = _seeds(seeds)
        return self._measure(self.truth_record(), self.spec.sensors, seeds, _key(self.name), self.name)

    def characterisation(self, seed: int = 0) -> Profile:
        """The HPPC test of the same truth cell (1 s, at the HPPC ambient), measured by the same sensors without
        their timed faults; a plain (one-run) profile."""
        return self._lab_test(_hppc_record(self.spec.truth, self.spec.hppc), "hppc", (self.spec.truth, self.spec.hppc),
                              seed)

    def initial_soc(self, seeds) -> np.ndarray:
        """SOC handed to the estimators ``(R,)``: the true SOC at the first sample plus the initial-SOC error."""
        z0 = float(self.truth_record().states[0, 0, Z])
        return initial_soc_guess(z0, self.spec.sensors, _seeds(seeds), _key(self.name))

    def sensor_noise(self) -> SensorNoise:
        """White-noise SDs (noise and quantisation) of the voltage and current readings, for the filter covariances.

        ``current_bias_sd`` is the sensor's steady offset (its datasheet figure); timed faults are not announced.
        """
        s = self.spec.sensors
        return SensorNoise(voltage_sd=max(s.voltage.white_sd, MIN_VOLTAGE_SD),
                           current_sd=max(s.current.white_sd, MIN_CURRENT_SD), dt=s.dt,
                           current_bias_sd=abs(s.current.offset))

    def summary(self) -> str:
        """One line for listings."""
        return f"{self.name:<16} {self.kind:<8} {self.description}"

    def with_sensors(self, **changes) -> Scenario:
        """The same scenario with some sensor fields replaced (a convenience for studies and tests)."""
        return Scenario(replace(self.spec, sensors=replace(self.spec.sensors, **changes)))
