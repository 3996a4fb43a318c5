"""Segmented records: where a record restarts (a battery swap, a recharge) and the SOC each segment starts from.

A record may put several discharges back to back (the DJI M100 loader joins 144 pack discharges on one time axis,
separated by gaps). Counting charge through them from the first SOC, a model leaves [0, 1] after a few packs. A
**segment boundary** is a gap in the time stamps — a step longer than ``GAP_FACTOR`` × the median step and at least
``MIN_GAP_S`` — across which the pack's charge changed in a way the current column does not say:

* with a reference SOC: the reference after the gap is higher, by more than ``SOC_JUMP``, than the current counted
  over the gap leaves it (``Δz_ref + I_k·Δt/(3600 Q) > SOC_JUMP``, zero-order hold, ``Q`` the record's declared
  capacity, the reference's own scale). Charge came in from outside the record: a recharge, a fresh pack. A *fall*
  beyond the count is not a boundary: it is charge the same cell delivered while the logger was off (the Panasonic
  HPPC files omit the discharges between pulse sets), which the fit carries as SOC jumps
  (:func:`socbench.identify.hppc.unrecorded_charge`, ``soc_jumps`` of :meth:`Model.open_loop`), as before;
* without one (needs an OCV curve and a capacity): both sides of the gap at rest (``|I| ≤ REST_C_RATE·Q``) and the
  OCV inverse of the voltage after the gap above that before it (plus the counted change) by more than
  ``SOC_JUMP_VOLTAGE`` — larger than ``SOC_JUMP`` because a rest voltage read minutes after a load still relaxes.

**Restart.** Each segment after the first starts from rest: every state but SOC at rest (``Model.x0``), and SOC

* for a model (``simulate``, ``fit``, ``diagnose``): the reference SOC at the segment's first sample where the record
  has one — on the model's own SOC axis (:mod:`socbench.socaxis`: a reference counted from full with the record's
  capacity is converted to the model's, or a model of another capacity would start a segment that does not start
  full at the wrong charge) — else the SOC the model reads off its first voltage (``Model.soc_from_voltage``: the OCV
  inverse, corrected for the load's instantaneous drop when the segment starts under load), clipped to [0, 1];
* for an estimator: the same reading of its first voltage, with the initial covariance it started the record with —
  an estimator never reads the reference it is scored against, so a restart is a new start, like the record's first.

**The current over a boundary is not integrated.** The zero-order hold would carry the last sample's current across
the whole gap (16 A of flight current over a 10-minute battery swap: 2.7 Ah, half a pack); the restart SOC replaces
whatever happened in the gap. Gaps that are not boundaries keep the zero-order hold, as every model step does.

**What the hold does not know.** Across a step much longer than the record's own sampling (longer than
``GAP_FACTOR`` median steps: a logger pause, or a cycler that logs slowly while nothing changes) the current was not
measured. :func:`hold_var` gives the filters the variance of the mean current over such a step about the held sample,
the larger of two readings of the record:

* **the ends differ**: the current changed somewhere inside the step; as one change from ``I_k`` to ``I_{k+1}`` at a
  moment uniform over the step, the mean current is ``I_k + u·ΔI`` (``u ~ U(0, 1)``) and the hold's error ``u·ΔI``
  has second moment ``ΔI²/3``;
* **the load was varying on both sides**: the current's variance over ``HOLD_WINDOW_STEPS`` median steps (at least
  ``HOLD_WINDOW_S``) before the step and over as long after it, the smaller of the two; each window cut at the
  change nearest the step among those that stand out (more than ``DOMINANT_CHANGE`` times the window's third largest
  change), and only the part touching the step kept, so that one change of mode there (a constant-current discharge
  ending, a rest beginning) or one pulse (an HPPC's, whose two edges stand out together) does not count as a varying
  load, while a load that switches between levels, whose large changes are many and alike, keeps the whole window.
  A drive paused and resumed varies on both sides, so its pause is seen even where its two ends happen to read the
  same current; a load that starts or stops in the step, or a rest logged slowly, is steady on at least one side and
  is left to the first reading.

The filters add it to their process noise at that step, each state on its own (``Q_k = σ_I² B_k B_kᵀ +
σ_hold,k²·diag(B_k²)``, :mod:`socbench.estimators.noise`), so the SOC band widens by about
``σ_hold·Δt/(3600 Q)`` across the step instead of carrying the sensor's noise alone. A long step between equal,
steady currents keeps zero (the Panasonic files write a sample a minute at rest, ten a second under load); so do
sampled steps. What it leaves out: the hold's mean error ``ΔI/2`` over a slowly logged taper (a slope, not noise: it
stays in the count).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .profile import Profile
from .socaxis import soc_axis

#: a gap: a step longer than this many median steps ...
GAP_FACTOR = 5.0
#: ... and at least this long [s]
MIN_GAP_S = 30.0
#: reference-SOC rise beyond the counted charge that marks a restart (a BMS shows SOC in 1 % steps; a recharge or
#: a fresh pack adds tens of points)
SOC_JUMP = 0.05
#: the same from the OCV inverse of rest voltages (no reference)
SOC_JUMP_VOLTAGE = 0.10
#: the load's variance either side of a long step is read over this many median steps ...
HOLD_WINDOW_STEPS = 20
#: ... and at least this long [s]: long enough to hold several of a drive's or a flight's level changes (a 30 s
#: window read a load held at one level for tens of seconds as steady; pauses cut into measured drive currents:
#: ``python benchmarks/logger_pause.py --measured``, docs/logger_pauses.md)
HOLD_WINDOW_S = 120.0
#: a spread of the current below this [A] is the rounding of logged values, not a varying load
ROUNDING_A = 1e-9
#: a window is cut at a change of current that exceeds this many times its third largest change (one mode change or
#: one pulse stands out; a varying load's changes do not)
DOMINANT_CHANGE = 3.0
#: |I| ≤ this C-rate counts as rest for the voltage rule
REST_C_RATE = 0.2
#: restart rules
REFERENCE, OCV = "reference", "ocv"


@dataclass(frozen=True)
class Segments:
    """Where the segments of a record start (``starts[0] == 0``) and why each boundary is one."""

    starts: tuple
    n: int
    reasons: tuple = ()

    @classmethod
    def whole(cls, n: int) -> Segments:
        """The record as one segment."""
        return cls((0,), int(n))

    @property
    def count(self) -> int:
        return len(self.starts)

    def spans(self) -> list[tuple[int, int]]:
        """``[(start, stop), ...]`` sample ranges of the segments."""
        ends = list(self.starts[1:]) + [self.n]
        return list(zip(self.starts, ends))

    def to_dict(self, max_listed: int = 20) -> dict:
        """JSON form: the count and the first ``max_listed`` boundaries (first row, counted from 1) with reasons."""
        return {"count": self.count,
                "boundaries": [{"row": int(k) + 1, "reason": r}
                               for k, r in zip(self.starts[1:max_listed + 1], self.reasons[:max_listed])],
                **({"boundaries_not_listed": self.count - 1 - max_listed} if self.count - 1 > max_listed else {})}


def find_segments(profile: Profile, ocv=None, capacity_ah: float | None = None,
                  unrecorded_discharge: bool = False, soc_jump: float = SOC_JUMP) -> Segments:
    """The segments of ``profile`` (module docstring). ``ocv`` and ``capacity_ah`` (the model's) serve the rule
    without a reference SOC and stand in when the record declares no capacity. ``unrecorded_discharge``: a reference
    that *falls* by more than ``soc_jump`` beyond the counted charge over a gap is a boundary too (for a caller that
    carries no SOC jumps across gaps: the diagnosis' evaluation records,
    :func:`socbench.diagnose.data.split_at_gaps`); ``soc_jump`` is the reference rule's limit either way."""
    n = profile.n
    if n < 3:
        return Segments.whole(n)
    dt = np.diff(profile.time_s)
    gap = np.flatnonzero(gap_steps(dt) & (dt >= MIN_GAP_S))
    if gap.size == 0:
        return Segments.whole(n)
    q = profile.meta.capacity_ah or capacity_ah
    i_before = profile.current_a[..., gap]
    counted = -i_before * dt[gap] / (3600.0 * q) if q else np.zeros(np.shape(i_before))
    if profile.soc_ref is not None:
        rise = profile.soc_ref[..., gap + 1] - profile.soc_ref[..., gap] - counted
        what, limit = "reference SOC", soc_jump
    elif profile.voltage_v is not None and ocv is not None and q:
        rest = (np.abs(i_before) <= REST_C_RATE * q) & (np.abs(profile.current_a[..., gap + 1]) <= REST_C_RATE * q)
        z_before = ocv.inverse(profile.voltage_v[..., gap], temp=_temp(profile, gap))
        z_after = ocv.inverse(profile.voltage_v[..., gap + 1], temp=_temp(profile, gap + 1))
        rise = np.where(rest, z_after - z_before - counted, 0.0)
        what, limit = "rest-voltage SOC", SOC_JUMP_VOLTAGE
    else:
        return Segments.whole(n)
    rise = np.reshape(rise, (-1, gap.size))
    if unrecorded_discharge and what == "reference SOC":  # the largest move of any run, either way
        worst = rise[np.abs(rise).argmax(axis=0), np.arange(gap.size)]
        hit = np.abs(worst) > limit
    else:
        worst = rise.max(axis=0)  # a batch restarts where any run does
        hit = worst > limit
    reasons = tuple(f"{what} {worst[j]:+.2f} beyond the counted charge over a {dt[gap[j]]:.0f} s gap"
                    for j in np.flatnonzero(hit))
    return Segments((0,) + tuple(int(k) + 1 for k in gap[hit]), n, reasons)


def gap_steps(dt: np.ndarray) -> np.ndarray:
    """``(T − 1,)`` bool: the steps longer than ``GAP_FACTOR`` × the median step (where the current was not sampled)."""
    dt = np.asarray(dt, dtype=float)
    if dt.size == 0:
        return np.zeros(0, dtype=bool)
    return dt > GAP_FACTOR * float(np.median(dt))


def hold_var(profile: Profile, *, window_s: float = HOLD_WINDOW_S, dominant: float = DOMINANT_CHANGE) -> np.ndarray:
    """``(T − 1,)`` variance [A²] of the current the zero-order hold does not know over each step (module docstring):
    over the :func:`gap_steps`, the larger of ``(I_{k+1} − I_k)²/3`` and the smaller of the current's variances just
    before and just after the step (the largest over the runs); 0 elsewhere. ``window_s`` and ``dominant`` set the
    windows' least length and their cut (``dominant = 0``: always at the largest change, the first rule); the
    defaults are what the filters use, other values are for comparing rules (benchmarks/logger_pause.py)."""
    dt = profile.dt
    gaps = gap_steps(dt)
    out = np.zeros(gaps.size)
    if not gaps.any():
        return out
    cur = np.reshape(profile.current_a, (-1, profile.n))
    t = profile.time_s
    window = max(HOLD_WINDOW_STEPS * float(np.median(dt)), window_s)
    for k in np.flatnonzero(gaps):
        before = cur[:, np.searchsorted(t, t[k] - window):k + 1]
        after = cur[:, k + 1:np.searchsorted(t, t[k + 1] + window, side="right")]
        steady = np.minimum(_var_next_to_step(before[:, ::-1], dominant), _var_next_to_step(after, dominant))
        change = (cur[:, k + 1] - cur[:, k]) ** 2 / 3.0
        out[k] = float(np.max(np.maximum(change, steady)))
    return out


def pause_report(profile: Profile, capacity_ah: float, segments: Segments | None = None) -> dict:
    """What the hold's variance did on ``profile`` (a filter's metrics): ``{"steps": the steps inside a segment with a
    nonzero :func:`hold_var`, "soc_sd_max": the largest SOC SD one of them adds, ``σ_hold·Δt/(3600 Q)``, "gaps": how
    many of them are also gaps (at least ``MIN_GAP_S``), "longest_gap_s" and "longest_gap_row" (the row after it,
    from 1 as the data file counts; None without gaps)}``."""
    h = hold_var(profile)
    if segments is not None:  # a boundary's step is never filtered: the segment after it restarts
        h[[k - 1 for k in segments.starts[1:]]] = 0.0
    sd = np.sqrt(h) * profile.dt / (3600.0 * capacity_ah)
    gaps = np.flatnonzero((h > 0) & (profile.dt >= MIN_GAP_S))
    longest = int(gaps[np.argmax(profile.dt[gaps])]) if gaps.size else None
    return {"steps": int(np.count_nonzero(h)), "soc_sd_max": float(sd.max()) if sd.size else 0.0,
            "gaps": int(gaps.size), "longest_gap_s": None if longest is None else float(profile.dt[longest]),
            "longest_gap_row": None if longest is None else longest + 2}


def pause_message(report: dict, what: str, held: str) -> str | None:
    """One line for the user where :func:`pause_report` found gaps inside a segment across which the current changed
    or the load varied (``held``: what the command does there), else None: a gap is reported, never passed silently."""
    if not report.get("gaps"):
        return None
    return (f"{what}: {report['gaps']} gap(s) in the time stamps across which the current changed or the load varied "
            f"(longest {report['longest_gap_s']:.0f} s, before row {report['longest_gap_row']}) inside a segment, "
            f"not a restart: {held}")


def _var_next_to_step(current: np.ndarray, dominant: float) -> np.ndarray:
    """The variance of each row of ``current (R, m)`` (its first sample next to the step) up to the change nearest
    the step among those that stand out (module docstring), over the whole row where none does; 0 for fewer than 3
    samples. A change stands out when it exceeds ``dominant`` × the third largest: one change of mode (a CC
    discharge ending) or one pulse's two edges, not one of a varying load's many alike. ``dominant = 0``: every
    row cut at its largest change."""
    out = np.zeros(current.shape[0])
    if current.shape[1] < 3:
        return out
    change = np.abs(np.diff(current, axis=1))
    third = np.sort(change, axis=1)[:, -3] if change.shape[1] >= 3 else np.zeros(current.shape[0])
    for r in range(current.shape[0]):
        if dominant > 0:
            stand_out = np.flatnonzero(change[r] > dominant * third[r])
            cut = int(stand_out[0]) if stand_out.size else change.shape[1]
        else:
            cut = int(np.argmax(change[r]))
        part = current[r, :cut + 1]
        # a spread of a nanoampere is the rounding of a logged constant (the Leaf files' CC steps), not a load
        out[r] = part.var() if part.size >= 3 and np.ptp(part) > ROUNDING_A else 0.0
    return out


def _temp(profile: Profile, k):
    """The cell temperature at sample(s) ``k`` (None without a temperature column: the curve's reference)."""
    return None if profile.temperature_c is None else profile.temperature_c[..., k]


def resolve(segments, profile: Profile, ocv=None, capacity_ah: float | None = None) -> Segments:
    """``segments`` as given: None → :func:`find_segments`; False → the whole record; a :class:`Segments` as is."""
    if segments is None or segments is True:
        return find_segments(profile, ocv, capacity_ah)
    if segments is False:
        return Segments.whole(profile.n)
    if not isinstance(segments, Segments) or segments.n != profile.n:
        raise ValueError("segments must be None, False or the Segments of this profile")
    return segments


def restart_soc(profile: Profile, start: int, model, rule: str = REFERENCE) -> np.ndarray:
    """The SOC a segment (or the record, ``start = 0``) starting at sample ``start`` starts from (module docstring),
    shape like one sample of the current: the reference there on the model's axis (``rule="reference"`` and the record
    has one), else the SOC at which ``model`` at rest reads the voltage there with the current there flowing
    (:meth:`~socbench.models.base.Model.soc_from_voltage`: the OCV inverse, corrected for the load's instantaneous
    drop), clipped to [0, 1]; 1 when the record has neither."""
    ref = profile.get("soc_ref") if rule == REFERENCE else None  # a reference given but refused raises its error
    if ref is not None:
        axis = soc_axis(model, profile)
        z = ref[..., start] if axis.identity else axis.to_model(ref[..., start])
    elif profile.voltage_v is not None:
        z = model.soc_from_voltage(profile.voltage_v[..., start], profile.current_a[..., start],
                                   _temp(profile, start))
    else:
        z = np.ones(np.shape(profile.current_a[..., start]))
    return np.clip(np.asarray(z, dtype=float), 0.0, 1.0)
