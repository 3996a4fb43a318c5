"""A record gap simulated as the step that moved its charge.

An HPPC logger that pauses during the step discharges (the Panasonic HPPC files; the randomized benchmark's
:func:`~socbench.diagnose.randomized.gapped_fit_test`) leaves each step's charge only in the reference SOC. The fit
takes it as a jump of the SOC at the first sample after the gap (``soc_jumps``,
:func:`~socbench.identify.hppc.unrecorded_charge`): the SOC is right, but the model's RC branches never see the step.
After the gap the model rests from a relaxed state, while the cell relaxes from a step of minutes at up to 1C, its
slow branch still holding much of the step's drop (on tests/hppc_records.py's gapped HPPCs, 0.5-6 mV RMS over the
first 2 min after the gaps in 10 of 16 two-branch draws). A fit spends its branches on that mismatch.

Where the record shows its steps elsewhere (a held discharge longer than the longest pulse, in the file:
:attr:`~socbench.identify.hppc.HPPCAnalysis.step_current_a`), each discharge gap is filled with one. With ``t_a`` the
last sample before the gap, ``t_b`` the first after it, ``I_a`` the current the zero-order hold carries across it,
``ΔQ`` the charge of the gap's jump and ``I_s`` the step current, the samples added make the current::

    I_a                  from t_a to t_a + δ               δ = min(1 s, 1 % of the gap)
    I_a + I_s            for T_s = ΔQ / I_s
    I_a                  from t_a + δ + T_s to t_b

so the count moves as before plus exactly ``ΔQ`` (the jump is dropped), and the branches see a step of the record's
own current from the gap's start: the HPPC steps after its pulses' rest, where the logger paused. The samples added
measure nothing (they hold the voltage of the sample after the gap: a profile admits no NaN): a fit gives them weight
0, and a simulation reports the record's own samples only. A gap too short for its charge at ``I_s``, a charge, or a
record that holds no step of its own (the Panasonic files) keeps its jump: how that charge moved is not known.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..profile import Profile

#: the added step starts this long after the last sample before the gap [s] (at most 1 % of the gap)
LEAD_S = 1.0


@dataclass(frozen=True, eq=False)
class GapSteps:
    """The discharge gaps of a record to fill: the first sample after each (``sample``, into the record the jumps are
    on), the time of the last sample before it (``start_s``), the SOC jump there (``soc``, < 0: a discharge) and the
    step current [A]."""

    sample: np.ndarray
    start_s: np.ndarray
    soc: np.ndarray
    current_a: float

    def fitting(self, profile: Profile, capacity_ah: float) -> int:
        """How many of the gaps of the record ``profile`` (its own samples) hold their step at :attr:`current_a`, on
        the SOC axis of ``capacity_ah`` (:func:`fill_gaps` keeps the jump of any other)."""
        jumps = np.zeros(profile.n)
        jumps[self.sample] = self.soc
        return fill_gaps(profile, jumps, capacity_ah, self).added // 2

    def on(self, index: np.ndarray) -> np.ndarray:
        """Each gap's position in a view of the record whose samples are the record's ``index`` (sorted): the first
        view sample at or after the sample after the gap, where the view's jumps land."""
        return np.searchsorted(index, self.sample)


def gap_steps(profile: Profile, unrecorded_ah: np.ndarray | None, capacity_ah: float,
              step_current_a: float) -> GapSteps | None:
    """The :class:`GapSteps` of ``profile``: its samples where ``unrecorded_ah`` (charge the current column does not
    carry, :func:`~socbench.identify.hppc.unrecorded_charge`) is a discharge, that charge as SOC on the axis of
    ``capacity_ah`` (the one its ``soc_jumps`` are on), and the record's step current; None where there is none to
    fill or no step current."""
    if unrecorded_ah is None or not (np.isfinite(step_current_a) and step_current_a > 0):
        return None
    ah = np.asarray(unrecorded_ah, dtype=float)
    k = np.flatnonzero(ah > 0.0)
    k = k[k > 0]
    if k.size == 0:
        return None
    return GapSteps(k, profile.time_s[k - 1].astype(float), -ah[k] / capacity_ah, float(step_current_a))


def step_duration_s(soc_jump, capacity_ah: float, current_a: float):
    """How long [s] a step of ``current_a`` takes to move the charge of an SOC jump on the axis of ``capacity_ah``."""
    return -np.asarray(soc_jump) * capacity_ah * 3600.0 / current_a


@dataclass(frozen=True, eq=False)
class Filled:
    """A record with its gaps filled: the profile, its SOC jumps (those not filled), and which of its samples are the
    record's own (``measured``; the added ones measure nothing)."""

    profile: Profile
    jumps: np.ndarray | None
    measured: np.ndarray

    @property
    def added(self) -> int:
        """How many samples the filling added (two per gap filled)."""
        return int(np.count_nonzero(~self.measured))


def fill_gaps(profile: Profile, jumps: np.ndarray | None, capacity_ah: float, steps: GapSteps | None,
              at: np.ndarray | None = None) -> Filled:
    """``profile`` (with the SOC ``jumps`` on its samples) with each gap of ``steps`` filled by a step (module
    docstring). ``at``: each gap's sample in ``profile`` (default ``steps.sample``: the record itself; a compressed view
    passes :meth:`GapSteps.on` of its index). The model's ``capacity_ah`` turns a jump into its charge. A plain
    profile (one run: a fit's record)."""
    n = profile.n
    if steps is None or jumps is None:
        return Filled(profile, jumps, np.ones(n, dtype=bool))
    if profile.batched:
        raise ConfigError("fill_gaps needs a plain profile (one run)")
    at = steps.sample if at is None else np.asarray(at)
    t, i = profile.time_s, profile.current_a
    jumps = np.array(jumps, dtype=float)
    where, times, amps = [], [], []
    for k, t0, dz in zip(at, steps.start_s, steps.soc):
        if not (0 < k < n) or dz >= 0.0 or not (t[k - 1] <= t0 < t[k]):
            continue
        lead = min(LEAD_S, 0.01 * (t[k] - t0))
        dur = float(step_duration_s(dz, capacity_ah, steps.current_a))
        if t0 + lead + dur >= t[k]:
            continue  # the charge does not fit in the gap at the step current
        hold = float(i[k - 1])
        where += [k, k]
        times += [t0 + lead, t0 + lead + dur]
        amps += [hold + steps.current_a, hold]
        jumps[k] -= dz
    if not where:
        return Filled(profile, jumps, np.ones(n, dtype=bool))
    where = np.asarray(where)

    def put(col, values):
        return None if col is None else np.insert(col, where, values)

    before = where - 1  # an added sample takes the temperature and reference of the sample before the gap
    filled = profile.with_(
        time_s=put(t, times), current_a=put(i, amps),
        voltage_v=put(profile.voltage_v, None if profile.voltage_v is None else profile.voltage_v[where]),
        temperature_c=put(profile.temperature_c, None if profile.temperature_c is None
                          else profile.temperature_c[before]),
        soc_ref=put(profile.soc_ref, None if profile.soc_ref is None else profile.soc_ref[before]))
    measured = np.ones(n + where.size, dtype=bool)
    measured[where + np.arange(where.size)] = False
    return Filled(filled, np.insert(jumps, where, 0.0), measured)
