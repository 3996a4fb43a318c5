"""Realistic HPPC (and drive-cycle) records for the tests: a known cell measured by an imperfect instrument.

This generator is deliberately independent of the code it tests (no socbench model, load or sensor code runs here):

* **truth** — a cell ``v = U_oc(z) − R0·I − Σ_k U_k`` with one or two RC branches of constant parameters, solved
  *exactly in continuous time* on a piecewise-constant true current (``U_k`` relaxes as ``e^{−t/τ_k}`` inside every
  segment, ``dz/dt = −I/(3600 Q)``), so samples can be taken at any instants, not on a simulation grid;
* **OCV shapes** — three hand-drawn curves (NMC-like, NCA-like, a flat LFP-like one), not the project's curves;
* **instrument** — the samples are taken at a random phase with period ``dt`` (0.1–10 s; below 1 s only around the
  pulses and edges and 1 s elsewhere, the way cyclers log), the current sensor adds white noise, an offset and ADC
  quantisation, the voltage sensor white noise and quantisation;
* **layouts** — discharge-only, discharge + charge, three discharge pulses of rising amplitude; 10/18/30 s pulses;
  rests before each pulse set of 5 min to 2 h; SOC steps of 5–10 %; optionally the Panasonic-style gaps (the step
  discharges and part of the following rest are missing from the record, the charge only in the reference SOC), and
  the ORNL-Leaf style charge pulse that runs straight into the step discharge.

:func:`issue_record` is the exact record of issue 13 (1 Hz, 1 h rests, 1C 10 s discharge pulse, 40 s rest, 0.75C 10 s
charge pulse, 40 s rest, 1C discharge to the next 10 % step, ten times, final 1 h rest, 10 mA current noise).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from socbench.ocv import OCVCurve
from socbench.profile import Profile, ProfileMeta

#: hand-drawn OCV shapes (SOC, V): an NMC-like, an NCA-like (steeper at the bottom) and a flat LFP-like cell
OCV_SHAPES = {
    "nmc": ([0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0],
            [3.00, 3.36, 3.47, 3.56, 3.62, 3.66, 3.71, 3.79, 3.88, 3.97, 4.07, 4.19]),
    "nca": ([0.0, 0.05, 0.1, 0.15, 0.25, 0.4, 0.55, 0.7, 0.85, 0.95, 1.0],
            [2.95, 3.30, 3.39, 3.45, 3.54, 3.63, 3.74, 3.88, 4.02, 4.11, 4.18]),
    "lfp": ([0.0, 0.03, 0.08, 0.15, 0.3, 0.5, 0.65, 0.7, 0.9, 0.97, 1.0],
            [2.90, 3.12, 3.21, 3.25, 3.28, 3.295, 3.305, 3.325, 3.335, 3.37, 3.48]),
}


@dataclass(frozen=True)
class Cell:
    """The truth: capacity [Ah], OCV shape, R0 [Ω] and RC branches ``((R [Ω], τ [s]), ...)``."""

    capacity_ah: float
    ocv_shape: str
    r0: float
    branches: tuple

    @property
    def ocv(self) -> OCVCurve:
        z, v = OCV_SHAPES[self.ocv_shape]
        return OCVCurve(z, v, f"hppc_records {self.ocv_shape}")


@dataclass(frozen=True)
class Layout:
    """One HPPC protocol. ``pulses_c``: the pulse currents of a set in C (positive = discharge)."""

    pulses_c: tuple = (1.0, -0.75)
    pulse_s: float = 10.0
    #: the charge pulses' length [s] (None: ``pulse_s``, as the discharge pulses)
    charge_pulse_s: float | None = None
    inner_rest_s: float = 40.0
    rest_s: float = 3600.0
    step: float = 0.1
    step_c: float = 1.0
    gaps: bool = False  # the step discharges (and part of the rest after them) are missing from the record
    straight_into_step: bool = False  # the last (charge) pulse runs straight into the step, no rest between
    #: ORNL Leaf style: the record starts at this SOC (rested for 10 min) and charges to full at ``precharge_c``
    #: before the test's first rest (None: it starts full)
    precharge_from: float | None = None
    precharge_c: float = 0.3
    #: share of the pre-charge the cell does not store (coulombic loss): the tester counts it, the SOC does not
    precharge_loss: float = 0.0
    #: a cycler script that charges the cell back to full at ``precharge_c`` after the test's final rest, and rests
    recharge_after: bool = False
    #: the test in the charge direction: from ``ASCENDING_FROM`` up, each level reached by a charge step at ``step_c``,
    #: the last one charging to full before a final rest
    ascending: bool = False
    #: the SOC the last step discharges to (0: empty; many protocols stop at 10–30 %, or at a voltage limit above empty)
    stop_soc: float = 0.0
    #: the test stops where its last step reaches ``stop_soc``, under load, with no rest after it (the ORNL Leaf HPPC
    #: ends at the cut-off voltage during its last step)
    stop_under_load: bool = False
    #: the first set (at full) has no charge pulse: a cycler cannot charge a full cell (the USABC HPPC at 100 % SOC
    #: has no regen pulse)
    skip_charge_at_full: bool = False


@dataclass(frozen=True)
class Instrument:
    """Sampling and sensor errors. Currents in fractions of 1C, voltages in V."""

    dt: float = 1.0
    i_noise_c: float = 0.0
    i_offset_c: float = 0.0
    i_lsb_c: float = 0.0
    v_noise: float = 0.0
    v_lsb: float = 0.0
    phase: float | None = None  # first sample time in [0, dt) (None: random)


@dataclass
class Record:
    """A generated record and what the truth says about it."""

    profile: Profile
    cell: Cell
    soc_true: np.ndarray  # true SOC at the samples
    v_clean: np.ndarray  # noise-free terminal voltage at the samples
    polarisation: np.ndarray  # Σ U_k at the samples (V)
    current_true: np.ndarray | None = None  # the true current at the samples (A)
    schedule: tuple | None = None  # (segment start times [s], segment currents [A]) of the true current
    n_sets: int = 0
    ocv_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))  # last rest sample before each set
    layout: Layout | None = None
    instrument: Instrument | None = None


# ------------------------------------------------------------------------------------------------ the truth
def _solve(cell: Cell, seg_i: np.ndarray, seg_t0: np.ndarray, t: np.ndarray, soc0: float = 1.0):
    """Exact continuous-time solution at times ``t`` of the cell on the piecewise-constant current (segment ``j``
    carries ``seg_i[j]`` from ``seg_t0[j]`` to ``seg_t0[j+1]``). Returns ``(current, soc, polarisation, voltage)``."""
    q_as = 3600.0 * cell.capacity_ah
    dur = np.diff(np.append(seg_t0, np.inf))
    n = seg_i.size
    z0 = soc0 - np.concatenate([[0.0], np.cumsum(seg_i[:-1] * dur[:-1])]) / q_as  # SOC at each segment start
    u0 = np.zeros((len(cell.branches), n))
    for k, (r, tau) in enumerate(cell.branches):
        for j in range(1, n):
            a = np.exp(-dur[j - 1] / tau)
            u0[k, j] = u0[k, j - 1] * a + r * seg_i[j - 1] * (1.0 - a)
    j = np.clip(np.searchsorted(seg_t0, t, side="right") - 1, 0, n - 1)
    s = t - seg_t0[j]
    cur = seg_i[j]
    soc = z0[j] - cur * s / q_as
    pol = np.zeros_like(t)
    for k, (r, tau) in enumerate(cell.branches):
        a = np.exp(-s / tau)
        pol += u0[k, j] * a + r * cur * (1.0 - a)
    v = cell.ocv(soc) - cell.r0 * cur - pol
    return cur, soc, pol, v


def _pulse_s(lay: Layout, c: float) -> float:
    """The length [s] of a pulse of ``c`` C in ``lay``."""
    return lay.charge_pulse_s if c < 0 and lay.charge_pulse_s is not None else lay.pulse_s


def _schedule(cell: Cell, lay: Layout):
    """Segments ``[(current A, seconds, kind), ...]`` of the HPPC and the number of pulse sets. As in the USABC
    protocol, pulse set ``j`` is at ``z = 1 − j·step`` and the step after it discharges to the next level (the pulses'
    net charge counts); the last set is at the lowest level ≥ ``stop_soc + step`` and the last step runs to
    ``stop_soc`` (default empty, z = 0)."""
    q = cell.capacity_ah
    if lay.ascending:
        return _ascending_schedule(cell, lay)
    n_levels = int(np.floor((1.0 - lay.stop_soc) / lay.step + 1e-9))
    segs = []
    if lay.precharge_from is not None:  # the stored charge: the current the SOC sees (the loss is added when measured)
        segs += [(0.0, 600.0, "pre"), (-lay.precharge_c * q, 3600.0 * (1.0 - lay.precharge_from) / lay.precharge_c,
                                       "charge")]
    segs += [(0.0, lay.rest_s, "rest")]
    z = 1.0
    for j in range(n_levels):
        pulses = [c for c in lay.pulses_c if not (j == 0 and lay.skip_charge_at_full and c < 0)]
        for m, c in enumerate(pulses):
            segs.append((c * q, _pulse_s(lay, c), "pulse"))
            z -= c * _pulse_s(lay, c) / 3600.0  # C·h = fraction of Q
            if not (m == len(pulses) - 1 and lay.straight_into_step):
                segs.append((0.0, lay.inner_rest_s, "inner"))
        z_next = 1.0 - (j + 1) * lay.step if j < n_levels - 1 else lay.stop_soc
        segs.append((lay.step_c * q, 3600.0 * (z - z_next) / lay.step_c, "step"))
        if not (lay.stop_under_load and j == n_levels - 1):
            segs.append((0.0, lay.rest_s, "rest"))
        z = z_next
    if lay.recharge_after:
        segs += [(-lay.precharge_c * q, 3600.0 / lay.precharge_c, "charge"), (0.0, lay.rest_s, "post")]
    return segs, n_levels


#: where a test in the charge direction starts (rested)
ASCENDING_FROM = 0.05


def _ascending_schedule(cell: Cell, lay: Layout):
    """The charge-direction HPPC, the mirror of the USABC one: pulse set ``j`` at ``z = ASCENDING_FROM + j·step``,
    a charge step to the next level (the pulses' net charge counts) and a rest after each; the last set is at the
    highest level at most ``1 − step`` and the last step charges to full."""
    q = cell.capacity_ah
    n_levels = int(np.floor((1.0 - ASCENDING_FROM) / lay.step + 1e-9))
    segs = [(0.0, lay.rest_s, "rest")]
    z = ASCENDING_FROM
    for j in range(n_levels):
        for m, c in enumerate(lay.pulses_c):
            segs.append((c * q, _pulse_s(lay, c), "pulse"))
            z -= c * _pulse_s(lay, c) / 3600.0
            if not (m == len(lay.pulses_c) - 1 and lay.straight_into_step):
                segs.append((0.0, lay.inner_rest_s, "inner"))
        z_next = ASCENDING_FROM + (j + 1) * lay.step if j < n_levels - 1 else 1.0
        segs.append((-lay.step_c * q, 3600.0 * (z_next - z) / lay.step_c, "step"))
        segs.append((0.0, lay.rest_s, "rest"))
        z = z_next
    return segs, n_levels


def _sample_times(seg_t0: np.ndarray, kinds, t_end: float, ins: Instrument, rng) -> np.ndarray:
    """Sample instants: period ``dt`` (random phase); when ``dt`` < 1 s, 1 s away from the pulses and edges."""
    phase = rng.uniform(0.0, ins.dt) if ins.phase is None else ins.phase
    if ins.dt >= 1.0:
        return np.arange(phase, t_end, ins.dt)
    slow = np.arange(phase, t_end, 1.0)
    dense_zones = []
    for j, kind in enumerate(kinds):
        a = seg_t0[j]
        b = seg_t0[j + 1] if j + 1 < len(kinds) else t_end
        if kind in ("pulse", "inner"):
            dense_zones.append((a - 2.0, b + 2.0))
        else:
            dense_zones.append((a - 2.0, min(a + 60.0, b)))  # the first minute after every edge
    fast = [np.arange(a + phase, b, ins.dt) for a, b in dense_zones]
    t = np.unique(np.concatenate([slow] + fast))
    t = t[(t >= 0) & (t < t_end)]
    return t[np.concatenate([[True], np.diff(t) > 1e-6])]


def _measure(t, cur, v, ins: Instrument, q: float, rng):
    i = cur + ins.i_offset_c * q + (rng.normal(0.0, ins.i_noise_c * q, t.size) if ins.i_noise_c > 0 else 0.0)
    if ins.i_lsb_c > 0:
        lsb = ins.i_lsb_c * q
        i = np.round(i / lsb) * lsb
    vm = v + (rng.normal(0.0, ins.v_noise, t.size) if ins.v_noise > 0 else 0.0)
    if ins.v_lsb > 0:
        vm = np.round(vm / ins.v_lsb) * ins.v_lsb
    return i, vm


def hppc_record(cell: Cell, lay: Layout, ins: Instrument, seed: int = 0, with_soc_ref: bool = True,
                name: str = "generated-hppc") -> Record:
    """An HPPC record of ``cell`` in ``lay``out measured by ``ins`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    segs, n_levels = _schedule(cell, lay)
    seg_i = np.array([s[0] for s in segs])
    kinds = [s[2] for s in segs]
    seg_t0 = np.concatenate([[0.0], np.cumsum([s[1] for s in segs])[:-1]])
    t_end = seg_t0[-1] + segs[-1][1]
    t = _sample_times(seg_t0, kinds, t_end, ins, rng)
    if lay.gaps:  # Panasonic: the steps and a random share of the rest after each (all but 2 min) are not in the file
        keep = np.ones(t.size, dtype=bool)
        for j, kind in enumerate(kinds):
            if kind == "step" and j + 1 < len(kinds) and j < len(kinds) - 2:  # the last step stays (final rest)
                share = rng.uniform(0.25, max(0.25, 1.0 - 120.0 / segs[j + 1][1]))
                a, b = seg_t0[j], seg_t0[j + 1] + share * segs[j + 1][1]
                keep &= ~((t >= a) & (t < b))
        t = t[keep]
    soc0 = ASCENDING_FROM if lay.ascending else 1.0 if lay.precharge_from is None else lay.precharge_from
    cur, soc, pol, v = _solve(cell, seg_i, seg_t0, t, soc0)
    if lay.precharge_loss:  # the tester counts charge the cell loses to side reactions
        charging = np.isin(np.clip(np.searchsorted(seg_t0, t, side="right") - 1, 0, len(kinds) - 1),
                           [j for j, k in enumerate(kinds) if k == "charge"])
        cur = np.where(charging, cur / (1.0 - lay.precharge_loss), cur)
    i_meas, v_meas = _measure(t, cur, v, ins, cell.capacity_ah, rng)
    # expected OCV rows: the last sample before the first pulse of every set, and the last sample of the record
    first_pulse = [seg_t0[j] for j, k in enumerate(kinds) if k == "pulse" and kinds[j - 1] == "rest"]
    # (with a charge back to full after the test: the last sample before it)
    last = (int(np.searchsorted(t, seg_t0[kinds.index("post") - 1], side="left")) - 1 if "post" in kinds
            else t.size - 1)
    rows = np.array([int(np.searchsorted(t, tp, side="left")) - 1 for tp in first_pulse] + [last])
    meta = ProfileMeta(name=name, source=name, capacity_ah=cell.capacity_ah)
    prof = Profile(t - t[0], i_meas, voltage_v=v_meas, soc_ref=np.clip(soc, 0.0, 1.0) if with_soc_ref else None,
                   meta=meta)
    return Record(prof, cell, soc, v, pol, cur, (seg_t0 - t[0], seg_i), n_levels, rows, lay, ins)


# ------------------------------------------------------------------------------------------------ random draws
def random_cell(rng) -> Cell:
    q = float(np.exp(rng.uniform(np.log(1.0), np.log(50.0))))
    r0 = rng.uniform(0.03, 0.12) / q  # Ω·Ah / Ah: a bigger cell has a smaller resistance
    branches = [(rng.uniform(0.3, 1.0) * r0, float(np.exp(rng.uniform(np.log(5.0), np.log(60.0)))))]
    if rng.random() < 0.5:
        branches.append((rng.uniform(0.2, 0.8) * r0, float(np.exp(rng.uniform(np.log(100.0), np.log(800.0))))))
    return Cell(q, str(rng.choice(list(OCV_SHAPES))), r0, tuple(branches))


def random_layout(rng) -> Layout:
    kind = rng.choice(["discharge", "discharge+charge", "three"])
    pulse_s = 10.0 if kind == "three" else float(rng.choice([10.0, 18.0, 30.0]))
    amp = min(rng.uniform(0.5, 2.0), 36.0 / pulse_s)  # a pulse moves at most 1 % of Q (HPPC pulses are short)
    pulses = {"discharge": (amp,), "discharge+charge": (amp, -rng.uniform(0.5, 1.0) * amp),
              "three": (0.5 * amp, amp, 1.5 * amp)}[str(kind)]
    inner = float(np.exp(rng.uniform(np.log(20.0), np.log(600.0))))
    gaps = bool(rng.random() < 0.25)  # a logger that pauses during the steps resumes in a rest (Panasonic)
    return Layout(pulses_c=tuple(float(c) for c in pulses), pulse_s=pulse_s,
                  inner_rest_s=inner, rest_s=float(np.exp(rng.uniform(np.log(300.0), np.log(7200.0)))),
                  step=float(rng.uniform(0.05, 0.10)), step_c=float(rng.uniform(0.3, 1.0)),
                  gaps=gaps, straight_into_step=bool(kind == "discharge+charge" and not gaps and rng.random() < 0.3))


def random_instrument(rng) -> Instrument:
    dt = float(np.exp(rng.uniform(np.log(0.1), np.log(10.0))))
    lsb = float(np.exp(rng.uniform(np.log(1e-4), np.log(2e-3)))) if rng.random() < 0.5 else 0.0
    return Instrument(dt=dt, i_noise_c=float(rng.uniform(0.0, 0.01)), i_offset_c=float(rng.uniform(-0.005, 0.005)),
                      i_lsb_c=lsb, v_noise=float(rng.uniform(0.5e-3, 5e-3)),
                      v_lsb=float(rng.choice([0.0, 1e-4, 1e-3])))


def random_setup(seed: int):
    """``(rng, cell, layout, instrument)`` of one randomised draw (the generator left where a caller may draw more)."""
    rng = np.random.default_rng(seed)
    return rng, random_cell(rng), random_layout(rng), random_instrument(rng)


def random_hppc(seed: int) -> Record:
    """One randomised draw: cell, layout, instrument (gap layouts always carry the reference SOC)."""
    rng, cell, lay, ins = random_setup(seed)
    return hppc_record(cell, lay, ins, seed=seed + 1, with_soc_ref=lay.gaps or rng.random() < 0.5)


# ------------------------------------------------------------------------------------------------ fixed records
#: the cell of the issue-13 record: 3.3 Ah (10 mA = 0.3 % of 1C), NMC-like, two RC branches
ISSUE_CELL = Cell(3.3, "nmc", 0.022, ((0.012, 25.0), (0.010, 400.0)))


def issue_record(seed: int = 0, v_noise: float = 1e-3, soc_ref_capacity_ratio: float | None = None) -> Record:
    """The record of issue 13: 1 Hz, 1 h rest, 1C 10 s discharge, 40 s rest, 0.75C 10 s charge, 40 s rest, 1C to
    the next 10 % step, ten times, final 1 h rest; 10 mA current white noise.

    ``soc_ref_capacity_ratio``: add a reference SOC counted from the measured current with a nominal capacity of
    this ratio × the true one (0.993 makes it end at about −0.7 %, as counted references do)."""
    ins = Instrument(dt=1.0, i_noise_c=0.010 / ISSUE_CELL.capacity_ah, v_noise=v_noise, phase=0.0)
    rec = hppc_record(ISSUE_CELL, Layout(), ins, seed=seed, with_soc_ref=False, name="issue13-hppc")
    if soc_ref_capacity_ratio is not None:
        p = rec.profile
        counted = 1.0 - p.amp_hours() / (soc_ref_capacity_ratio * ISSUE_CELL.capacity_ah)
        rec.profile = Profile(p.time_s, p.current_a, p.voltage_v, soc_ref=counted, meta=p.meta)
    return rec


def drive_record(cell: Cell, ins: Instrument, seed: int = 0, duration_s: float = 5400.0, soc0: float = 0.95,
                 stops: bool = True, name: str = "generated-drive") -> Record:
    """A drive-cycle-like record of the same cell: a current that changes every second (mean ~0.6 C, bursts to
    2.5 C, regenerative charge), with stops of 20–90 s when ``stops``."""
    rng = np.random.default_rng(seed)
    q = cell.capacity_ah
    n = int(duration_s)
    x = np.zeros(n)
    for k in range(1, n):  # an AR(1) "power demand" with bursts
        x[k] = 0.97 * x[k - 1] + rng.normal(0.0, 0.25)
    amps = q * np.clip(0.6 + 0.8 * x + 0.8 * (rng.random(n) < 0.02), -1.0, 2.5)
    if stops:
        k = int(rng.integers(60, 300))
        while k < n:
            length = int(rng.integers(20, 90))
            amps[k:k + length] = 0.0
            k += length + int(rng.integers(120, 600))
    seg_t0 = np.arange(n, dtype=float)
    t = np.arange(0.0, n, max(ins.dt, 1.0))
    cur, soc, pol, v = _solve(cell, amps, seg_t0, t, soc0=soc0)
    i_meas, v_meas = _measure(t, cur, v, ins, q, rng)
    meta = ProfileMeta(name=name, source=name, capacity_ah=q)
    prof = Profile(t, i_meas, voltage_v=v_meas, soc_ref=np.clip(soc, 0.0, 1.0), meta=meta)
    return Record(prof, cell, soc, v, pol, cur, (seg_t0, amps), layout=None, instrument=ins)


def write_canonical(profile: Profile, path) -> Path:
    """Canonical CSV (time_s, current_a, voltage_v[, soc_ref]) and its JSON sidecar (capacity, name)."""
    path = Path(path)
    frame = profile.to_frame()
    values = frame.to_numpy(dtype=float)
    if np.isfinite(values).all():  # 17 digits: exact; numpy writes them twice as fast as pandas' float formatting
        np.savetxt(path, values, fmt="%.17g", delimiter=",", header=",".join(frame.columns), comments="")
    else:  # pandas writes a missing value as an empty field
        frame.to_csv(path, index=False)
    path.with_suffix(".json").write_text(json.dumps({"capacity_ah": profile.meta.capacity_ah, "n_series": 1,
                                                     "name": profile.name}))
    return path


# ------------------------------------------------------------------------------------------------ rates
def ocv_point_errors(rec: Record, analysis) -> tuple[np.ndarray, np.ndarray]:
    """Per OCV point of an analysis of ``rec`` (in time order): the SOC error against the truth, and the voltage
    error against the true OCV beyond what the truth itself still holds as polarisation at that moment [V]."""
    order = np.argsort(-analysis.ocv_soc)  # the points come at falling SOC
    z_true = rec.soc_true[rec.ocv_rows]
    dz = analysis.ocv_soc[order] - z_true
    dv = np.abs(analysis.ocv_voltage[order] - rec.cell.ocv(z_true)) - np.abs(rec.polarisation[rec.ocv_rows])
    return dz, dv


def analysis_rates(seeds) -> list:
    """The HPPC analysis on ``random_hppc(seed)`` for every seed: per draw the sample period, whether the structure
    (sets, OCV points) is the truth's, the offset error [fraction of 1C], the largest SOC error of an OCV point, the
    largest OCV voltage error beyond the truth's polarisation and 1.5 σ of the voltage noise [V], the median r_inst
    against R0 (relative), and the number of warnings emitted."""
    import warnings

    from socbench.identify import analyze_hppc

    rows = []
    for seed in seeds:
        rec = random_hppc(seed)
        q = rec.cell.capacity_ah
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            a = analyze_hppc(rec.profile, capacity_ah=q)
        ok = len({p.level for p in a.pulses}) == rec.n_sets and a.ocv_soc.size == rec.ocv_rows.size
        dz, dv = ocv_point_errors(rec, a) if ok else (np.array([np.nan]), np.array([np.nan]))
        rows.append({"seed": seed, "dt": rec.instrument.dt, "structure_ok": ok,
                     "offset_err": abs(a.current_offset_a / q - rec.instrument.i_offset_c),
                     "soc_err": float(np.max(np.abs(dz))), "v_excess": float(np.max(dv)) - 1.5 * rec.instrument.v_noise,
                     "r_inst_rel": a.medians()["r_inst"] / rec.cell.r0 - 1.0, "warnings": len(caught)})
    return rows


if __name__ == "__main__":  # python tests/hppc_records.py [N] [FIRST_SEED]: the rates the tests assert, measured
    import sys

    n, first = (int(sys.argv[1]) if len(sys.argv) > 1 else 300), (int(sys.argv[2]) if len(sys.argv) > 2 else 0)
    rows = analysis_rates(range(first, first + n))
    col = {k: np.array([r[k] for r in rows], dtype=float) for k in rows[0]}
    print(f"{n} draws (seeds {first}..{first + n - 1}): structure right {100 * col['structure_ok'].mean():.1f} %, "
          f"warnings {int(col['warnings'].sum())}, offset error q95 {100 * np.quantile(col['offset_err'], 0.95):.3f} "
          f"% of 1C (max {100 * col['offset_err'].max():.3f} %)")
    for lo, hi in ((0.1, 0.5), (0.5, 2.0), (2.0, 10.0)):
        m = (col["dt"] >= lo) & (col["dt"] < hi)
        r, z, v = np.abs(col["r_inst_rel"][m]), col["soc_err"][m], col["v_excess"][m]
        print(f"  dt {lo:g}-{hi:g} s (n={int(m.sum())}): OCV SOC error q95 {100 * np.nanquantile(z, 0.95):.2f} points "
              f"(max {100 * np.nanmax(z):.2f}); OCV voltage beyond polarisation + 1.5 sigma in "
              f"{100 * np.nanmean(v > 0):.0f} % of draws (max {1000 * np.nanmax(v):+.1f} mV); r_inst vs R0 median "
              f"{100 * np.nanmedian(r):.1f} %, q90 {100 * np.nanquantile(r, 0.9):.1f} %, not measured in "
              f"{100 * np.mean(np.isnan(r)):.0f} %")
