"""Elementary load profiles (current only): constant-current discharge and the paper's HPPC pattern.

The HPPC pattern follows Jung & Tullu §III (1 C pulses, discharge and charge pulses, SOC from 100 % to 0 % in 10 %
steps, 11 OCV rest points). The paper gives pulse and rest durations only in its Fig. 2, so the durations here are the
usual PNGV/USABC ones: 10 s discharge pulse, 40 s rest, 10 s charge pulse (0.75 × the discharge amplitude), 40 s rest,
then a 1 C discharge of 10 % SOC and a 1 h rest.
"""

from __future__ import annotations

import numpy as np

from .profile import Profile, ProfileMeta


def _profile(segments, dt: float, name: str, capacity_ah: float, n_series: int) -> Profile:
    currents = []
    for amps, seconds in segments:
        n = int(round(seconds / dt))
        currents.append(np.full(n, float(amps)))
    i = np.concatenate(currents)
    t = np.arange(i.size) * dt
    meta = ProfileMeta(name=name, source="socbench.loads", capacity_ah=capacity_ah, n_series=n_series)
    return Profile(t, i, meta=meta)


def constant_current(capacity_ah: float, c_rate: float = 1.0, dt: float = 1.0, soc_span: float = 1.0,
                     rest_s: float = 0.0, n_series: int = 1) -> Profile:
    """A ``c_rate`` discharge of ``soc_span`` of the capacity, optionally followed by a rest."""
    amps = c_rate * capacity_ah
    seconds = 3600.0 * soc_span / c_rate
    segs = [(amps, seconds)] + ([(0.0, rest_s)] if rest_s > 0 else [])
    return _profile(segs, dt, f"{c_rate:g}C discharge", capacity_ah, n_series)


def hppc(capacity_ah: float, c_rate: float = 1.0, dt: float = 1.0, pulse_s: float = 10.0, rest_pulse_s: float = 40.0,
         charge_ratio: float = 0.75, rest_s: float = 3600.0, step: float = 0.1, n_series: int = 1) -> Profile:
    """HPPC: at each SOC level a discharge pulse, a rest, a charge pulse, a rest; then a ``step`` discharge and a rest.

    The first pulse set is at full charge (after ``rest_s``), the last at ``step`` above empty; the profile ends with
    the final discharge to empty and a rest, so rests are taken at 1.0, 0.9, …, 0.0.
    """
    amps = c_rate * capacity_ah
    levels = int(round(1.0 / step))
    segs = [(0.0, rest_s)]
    for _ in range(levels):
        segs += [(amps, pulse_s), (0.0, rest_pulse_s), (-charge_ratio * amps, pulse_s), (0.0, rest_pulse_s)]
        # the pulses' net charge is taken off the step discharge, so each level removes exactly `step` of the capacity
        net_pulse_as = amps * pulse_s * (1.0 - charge_ratio)
        step_s = np.floor((3600.0 * step * capacity_ah - net_pulse_as) / amps / dt) * dt  # never past empty
        segs += [(amps, step_s), (0.0, rest_s)]
    return _profile(segs, dt, f"HPPC {c_rate:g}C", capacity_ah, n_series)
