"""Channel skew: how many samples the voltage reading lags the current reading, measured at current steps.

Every model in socbench has direct feed-through: a current step ``ΔI`` between samples ``k`` and ``k + 1`` moves the
predicted voltage by ``−R0·ΔI`` *at* sample ``k + 1`` (ECM_SPEC §2). A logger that samples the voltage channel later
than the current channel (a multiplexed ADC, a filter in one channel) shows that jump one or more samples later. The
skew is a property of the record, not of the cell, and it costs a model a spike of ``R0·ΔI`` at every edge.

Measurement. At every current step larger than ``min_step`` the instantaneous resistance seen ``L`` samples late::

    r_L = median_k  −(v[k+1+L] − v[k+L]) / (i[k+1] − i[k])          L = 0 … max_lag

Without skew nearly all of the ohmic jump lands at ``L = 0`` and ``r_0`` dominates; a skew of one sample moves it to
``r_1``. The lag is the ``L`` with the largest ``r_L``. On the Panasonic 18650PF records (Kollmeyer 2018) this gives 0
for the 1 Hz HPPC (the jump fits inside one sample) and 1 for the 10 Hz drive cycles, where the edge resistance is
5 mΩ at ``L = 0`` and 17 mΩ at ``L = 1``.

:func:`align_voltage` removes a lag by pairing ``i[k]`` with ``v[k + L]`` and dropping the last ``L`` samples. It is a
correction of the data, applied explicitly and reported, never silently by a loader.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import DataError
from ..profile import Profile

#: current steps smaller than this fraction of the largest |I| are ignored (noise, slow ramps)
MIN_STEP_FRACTION = 0.1
#: fewer edges than this: the lag is not measured (0 is returned with ``n_edges`` saying why)
MIN_EDGES = 5


@dataclass(frozen=True)
class VoltageLag:
    """Measured skew: ``lag`` samples, the edge resistance ``r_by_lag[L]`` seen ``L`` samples late, edges used."""

    lag: int
    r_by_lag: tuple
    n_edges: int

    def describe(self) -> str:
        rs = ", ".join(f"L={k}: {1000 * r:.1f} mΩ" for k, r in enumerate(self.r_by_lag))
        return f"voltage lags current by {self.lag} sample(s) ({self.n_edges} current steps; edge resistance {rs})"


def voltage_lag(profile: Profile, max_lag: int = 3, min_step: float | None = None) -> VoltageLag:
    """Measure the voltage channel's lag behind the current channel (see the module docstring)."""
    if profile.batched:
        raise DataError("voltage_lag needs a plain profile (one run)", file=profile.meta.source or profile.name)
    profile.require("voltage_v")
    i, v = profile.current_a, profile.voltage_v
    di = np.diff(i)
    if min_step is None:
        min_step = MIN_STEP_FRACTION * float(np.max(np.abs(i)))
    edges = np.flatnonzero(np.abs(di) > min_step)
    edges = edges[edges + 1 + max_lag < i.size]
    if edges.size < MIN_EDGES:
        return VoltageLag(0, (), int(edges.size))
    r = tuple(float(np.median(-(v[edges + 1 + L] - v[edges + L]) / di[edges])) for L in range(max_lag + 1))
    return VoltageLag(int(np.argmax(r)), r, int(edges.size))


def align_voltage(profile: Profile, lag: int) -> Profile:
    """``profile`` with ``v[k + lag]`` paired with ``i[k]``; the last ``lag`` samples are dropped."""
    if lag < 0:
        raise ValueError("lag must be >= 0")
    if lag == 0:
        return profile
    n = profile.n - lag

    def head(a):
        return None if a is None else a[..., :n]

    return replace(profile, time_s=profile.time_s[:n], current_a=head(profile.current_a),
                   voltage_v=profile.voltage_v[..., lag:], temperature_c=head(profile.temperature_c),
                   soc_ref=head(profile.soc_ref))
