"""The paper's lab schedule around a flight (ECM_SPEC §1): CC-CV charge → rest (OCV) → flight pattern until UV.

Every piece runs the truth cell and returns a :class:`Record` (true current, voltage and states on a time grid), so a
scenario can keep what the sensors should see (the end of the rest and the flight) and drop the rest.

CC-CV: constant current ``charge_c_rate`` × Q until the terminal voltage reaches ``cv_voltage_v``, then that voltage
is held (the current solved from the truth model each step) until the current falls below ``cutoff_c`` × Q. The stand-in
OCV curve of the paper pack ends at 24.62 V at z = 1 (ECM_SPEC §3.3), below the pack's 25.2 V maximum, so the CV
voltage defaults to the curve's top: charging to 25.2 V would push the true SOC above 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import require
from .truth import TEMP, TruthCell, Z


@dataclass(frozen=True)
class Schedule:
    """How the pack is prepared before the recorded part of a scenario."""

    charge: bool = True  # CC-CV from `start_soc`; False: the pack starts at rest at `start_soc`
    start_soc: float = 0.2
    charge_c_rate: float = 1.0
    cv_voltage_v: float | None = None  # default: the OCV curve's value at z = 1
    cutoff_c: float = 0.05
    rest_s: float = 1800.0
    rest_record_s: float = 60.0  # the last part of the rest that the sensors record before the load starts
    sim_dt: float = 10.0  # step of the unrecorded charge and rest (exact RC discretisation)
    ambient_c: float = 25.0  # during the recorded rest and the load
    charge_ambient_c: float | None = None  # during the charge and the unrecorded rest (default: ambient_c)
    start_temp_c: float | None = None  # pack temperature when the recording starts (default: as simulated)
    rest_after_s: float = 0.0  # recorded rest after the load ends

    def __post_init__(self):
        require(0 <= self.start_soc <= 1, "start_soc", f"must be in [0, 1], got {self.start_soc}")
        require(self.charge_c_rate > 0, "charge_c_rate", f"must be > 0, got {self.charge_c_rate}")
        require(self.cv_voltage_v is None or self.cv_voltage_v > 0, "cv_voltage_v", "must be > 0")
        require(0 < self.cutoff_c < self.charge_c_rate, "cutoff_c", "must be in (0, charge_c_rate)")
        require(self.rest_s >= 0, "rest_s", f"must be >= 0, got {self.rest_s}")
        require(0 <= self.rest_record_s <= self.rest_s or not self.charge, "rest_record_s",
                f"must be in [0, rest_s], got {self.rest_record_s}")
        require(self.rest_record_s >= 0, "rest_record_s", "must be >= 0")
        require(self.sim_dt > 0, "sim_dt", f"must be > 0, got {self.sim_dt}")
        for name in ("ambient_c", "charge_ambient_c", "start_temp_c"):
            v = getattr(self, name)
            require(v is None or -60 <= v <= 80, name, f"must be in [-60, 80] °C, got {v}")
        require(self.rest_after_s >= 0, "rest_after_s", "must be >= 0")


@dataclass
class Record:
    """True signals of a piece of schedule: ``time (T,)``, ``current, voltage (R, T)``, ``states (R, T, 6)``."""

    time: np.ndarray
    current: np.ndarray
    voltage: np.ndarray
    states: np.ndarray
    phases: list = field(default_factory=list)
    stop_reason: str = ""
    final: np.ndarray | None = None  # the state one step after the last sample (where a next piece starts)

    @property
    def last_state(self) -> np.ndarray:
        return self.states[..., -1, :] if self.final is None else self.final

    def shifted(self, t0: float) -> Record:
        return Record(self.time + t0, self.current, self.voltage, self.states,
                      [(n, t + t0) for n, t in self.phases], self.stop_reason, self.final)

    @staticmethod
    def concat(parts: list[Record]) -> Record:
        """Back to back: each part starts one step after the previous one ends."""
        parts = [p for p in parts if p.time.size]
        out, t_end = [], None
        for p in parts:
            step = p.time[1] - p.time[0] if p.time.size > 1 else 1.0
            t0 = 0.0 if t_end is None else t_end + step - p.time[0]
            out.append(p.shifted(t0))
            t_end = out[-1].time[-1]
        return Record(np.concatenate([p.time for p in out]), np.concatenate([p.current for p in out], axis=-1),
                      np.concatenate([p.voltage for p in out], axis=-1),
                      np.concatenate([p.states for p in out], axis=-2),
                      [ph for p in out for ph in p.phases], out[-1].stop_reason if out else "", out[-1].final)


def _stack(t, currents, volts, states, phases=None, reason="", final=None) -> Record:
    return Record(np.asarray(t, dtype=float), np.stack(currents, axis=-1), np.stack(volts, axis=-1),
                  np.stack(states, axis=-2), phases or [], reason, final)


def run_current(cell: TruthCell, x, current, dt: float, ambient_c: float, stop_uv: bool = False,
                reserve_soc: float = 0.0, phases=None) -> Record:
    """Apply a current sequence ``(T,)`` (zero-order hold, step ``dt``); optionally stop at UV / the reserve SOC.

    Runs of zero current are done in closed form (:meth:`TruthCell.rest`), the rest step by step."""
    x = np.array(x, dtype=float)
    current = np.asarray(current, dtype=float)
    cs, vs, ss = [], [], []
    reason = "end"
    k, n = 0, current.size
    while k < n:
        if current[k] == 0.0:
            m = k + int(np.argmax(current[k:] != 0.0)) if np.any(current[k:] != 0.0) else n
            states, y, x = cell.rest(x, m - k, dt, ambient_c)
            cs.append(np.zeros(y.shape))
            vs.append(y)
            ss.append(states)
            k = m
            if stop_uv and np.any(y < cell.uv_limit_v):  # a rest below UV: stop at its first sample
                j = int(np.argmax(np.any(y < cell.uv_limit_v, axis=tuple(range(y.ndim - 1)))))
                cs[-1], vs[-1], ss[-1] = cs[-1][..., : j + 1], vs[-1][..., : j + 1], ss[-1][..., : j + 1, :]
                reason = "under_voltage"
                break
            continue
        i = np.full(x.shape[:-1], current[k])
        y, x_next = cell.advance(x, i, dt, ambient_c)
        cs.append(i[..., None])
        vs.append(y[..., None])
        ss.append(x[..., None, :])
        k += 1
        if stop_uv and np.any(y < cell.uv_limit_v):
            reason = "under_voltage"
            x = x_next
            break
        if stop_uv and np.any(x[..., Z] < reserve_soc):
            reason = "reserve_soc"
            x = x_next
            break
        x = x_next
    current_out = np.concatenate(cs, axis=-1)
    return Record(np.arange(current_out.shape[-1]) * dt, current_out, np.concatenate(vs, axis=-1),
                  np.concatenate(ss, axis=-2), phases or [], reason, x)


def rest(cell: TruthCell, x, seconds: float, dt: float, ambient_c: float) -> Record:
    n = max(int(round(seconds / dt)), 1)
    return run_current(cell, x, np.zeros(n), dt, ambient_c, phases=[("rest", 0.0)])


def cc_cv_charge(cell: TruthCell, x, c_rate: float, v_cv: float, cutoff_c: float, dt: float, ambient_c: float,
                 max_s: float = 6 * 3600.0) -> Record:
    """CC at ``c_rate`` until ``y ≥ v_cv``, then CV at ``v_cv`` until ``|I| < cutoff_c`` × Q (currents negative)."""
    q = cell.params.capacity_ah
    x = np.array(x, dtype=float)
    cs, vs, ss, phases = [], [], [], [("cc_charge", 0.0)]
    cv = False
    for k in range(int(max_s / dt)):
        i = np.full(x.shape[:-1], -c_rate * q)
        if not cv and np.all(cell.voltage(x, i) >= v_cv):
            cv = True
            phases.append(("cv_charge", k * dt))
        if cv:
            i = np.maximum(cell.current_for_voltage(x, v_cv), -c_rate * q)
            if np.all(np.abs(i) < cutoff_c * q):
                break
        cs.append(i)
        vs.append(cell.voltage(x, i))
        ss.append(x)
        x = cell.step(x, i, dt, ambient_c)
    return _stack(np.arange(len(cs)) * dt, cs, vs, ss, phases, "cv_cutoff", final=x)


def prepare(cell: TruthCell, schedule: Schedule, batch: int = 1) -> tuple[np.ndarray, Record | None]:
    """Run the unrecorded part of the schedule: the state at the start of the recorded rest, and the charge record.

    Without a charge the pack starts relaxed at ``start_soc`` on the discharge branch at the ambient temperature."""
    amb = schedule.ambient_c if schedule.charge_ambient_c is None else schedule.charge_ambient_c
    x = cell.initial_state(schedule.start_soc, amb, hyst=-1.0, batch=batch)  # after a discharge
    charge = None
    if schedule.charge:
        v_cv = schedule.cv_voltage_v if schedule.cv_voltage_v is not None else float(cell.params.ocv(1.0))
        charge = cc_cv_charge(cell, x, schedule.charge_c_rate, v_cv, schedule.cutoff_c, schedule.sim_dt, amb)
        x = charge.last_state
        unrecorded = schedule.rest_s - schedule.rest_record_s
        if unrecorded > 0:
            x = rest(cell, x, unrecorded, schedule.sim_dt, amb).last_state
    x = np.array(x)
    if schedule.start_temp_c is not None:
        x[..., TEMP] = schedule.start_temp_c  # e.g. a pack charged in the lab and cold-soaked before the flight
    return x, charge


def lab_schedule(cell: TruthCell, schedule: Schedule, load, dt: float = 1.0, x0=None) -> Record:
    """The paper's schedule: CC-CV charge and rest (unrecorded), then at ``dt`` the recorded end of the rest
    (``rest_record_s``), the load until it stops (UV, reserve SOC or its end) and the recorded rest after.

    ``load(cell, x, dt, ambient_c) -> Record`` applies the flight pattern; ``x0`` is a state already prepared by
    :func:`prepare` (to reuse a cached charge)."""
    x = prepare(cell, schedule)[0] if x0 is None else np.array(x0, dtype=float)
    amb = schedule.ambient_c
    parts = []
    if schedule.rest_record_s > 0:
        parts.append(rest(cell, x, schedule.rest_record_s, dt, amb))
        x = parts[-1].last_state
    flight = load(cell, x, dt, amb)
    parts.append(flight)
    if schedule.rest_after_s > 0:
        after = rest(cell, flight.last_state, schedule.rest_after_s, dt, amb)
        after.stop_reason = flight.stop_reason
        parts.append(after)
    return Record.concat(parts)
