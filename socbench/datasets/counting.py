"""Reference SOC by amp-hour counting between full charges, for sources without a usable amp-hour counter.

A tester's own counter is best (Panasonic has one). CALCE's CSV exports have none and ORNL's Bitrode counter resets
per step, so for those the charge is counted here, ZOH on the current like :meth:`Profile.amp_hours`, and anchored:

* **full** (SOC = 1) is the end of a charge that reached the voltage limit (``v_full``) with its current tapered (the
  end of a CC-CV charge; not a constant-current regen pulse touching the limit, nor a CC-only charge);
* between two full charges the SOC counts forward from the first down to the lowest point (the discharge cut-off)
  and backward from the second after it. Counting never closes exactly (coulombic efficiency, current offset), so
  the reference steps by the mismatch at that lowest point; the largest step is reported, never hidden;
* before the first full charge the SOC counts backward from it; after the last it counts forward;
* with no full charge in the file, a file declared to start full (``start_full``) is anchored at its first sample.

``C`` is the source's capacity, raised to the largest charge counted between a full point and a lowest point when
the data hold more (so the reference stays in [0, 1]); which one was used is returned.
"""

from __future__ import annotations

import numpy as np


def charge_counter(time_s: np.ndarray, current_a: np.ndarray) -> np.ndarray:
    """Charge put *in* since the first sample [Ah] (current positive = discharge, zero-order hold)."""
    q = np.zeros_like(current_a, dtype=float)
    q[1:] = np.cumsum(-current_a[:-1] * np.diff(time_s)) / 3600.0
    return q


def full_charge_points(current_a: np.ndarray, voltage_v: np.ndarray, *, v_full: float, i_threshold: float,
                       taper: float = 0.5) -> list[int]:
    """Sample indices where a CC-CV charge ended (the first sample after the last charging sample).

    A charge run counts as a full charge when it ends at the voltage limit *and* its current has tapered below
    ``taper`` × its peak (the CV phase): a constant-current regen pulse touching the limit, or a CC-only charge,
    does not.
    """
    charging = current_a < -i_threshold
    n = charging.size
    edges = np.diff(np.r_[0, charging.astype(np.int8), 0])
    starts, stops = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0] - 1  # inclusive run bounds
    anchors: list[int] = []
    for s, e in zip(starts, stops):  # a handful of charge runs per file, not per row
        if e + 1 >= n or voltage_v[e] < v_full:
            continue
        peak = float(-current_a[s:e + 1].min())
        if -current_a[e] <= taper * peak:
            anchors.append(int(e + 1))
    return anchors


def soc_between_full_charges(time_s, current_a, voltage_v, *, capacity_ah: float, v_full: float,
                             i_threshold: float = 0.01, start_full: bool = False, offset_tolerance: float = 5e-4):
    """``(soc or None, C used, info dict)`` — see the module docstring."""
    q = charge_counter(time_s, current_a)
    anchors = full_charge_points(current_a, voltage_v, v_full=v_full, i_threshold=i_threshold)
    info: dict = {"full_charge_rows": [a + 1 for a in anchors]}
    if not anchors:
        if not start_full:
            info["soc_note"] = "no full charge found: no reference SOC"
            return None, capacity_ah, info
        anchors = [0]
        info["soc_note"] = "file starts full (declared by the source)"
    n = q.size
    # pieces: (start, stop inclusive, anchor index) counted from that anchor
    pieces = [(0, anchors[0], anchors[0])]
    steps_at = []
    for a, b in zip(anchors, anchors[1:]):
        m = a + int(np.argmin(q[a:b + 1]))
        pieces.append((a, m, a))
        if m < b:
            pieces.append((m + 1, b, b))
            steps_at.append(m)
    pieces.append((anchors[-1], n - 1, anchors[-1]))
    depth = max(float(q[ref] - q[lo:hi + 1].min()) for lo, hi, ref in pieces)
    c_used = max(capacity_ah, depth)
    info["capacity_source"] = "source capacity" if c_used == capacity_ah else "deepest counted discharge in the file"
    soc = np.empty(n)
    for lo, hi, ref in pieces:
        soc[lo:hi + 1] = 1.0 - (q[ref] - q[lo:hi + 1]) / c_used
    if steps_at:
        jumps = np.abs(soc[np.asarray(steps_at) + 1] - soc[np.asarray(steps_at)])
        info["soc_reanchor_max_step"] = float(jumps.max())
    # a rest after a full charge may still count the current sensor's offset (CALCE logs 0.2 mA at rest), pushing
    # the count past 1 by a few 1e-4: clip that much only; anything larger stays and the Profile reports it
    clipped = np.clip(soc, 0.0, 1.0)
    soc = np.where(np.abs(soc - clipped) <= offset_tolerance, clipped, soc)
    return soc, c_used, info
