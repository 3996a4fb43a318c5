"""Preparing evaluation data for the diagnosis: charge-preserving averaging and the train / held-out split.

Averaging. A 10 Hz drive cycle costs ten model steps a second and its fits would take minutes; the diagnosis works on
bins of at least ``dt`` seconds. Within a bin the current is the charge-preserving mean ``Σ I·dt / Σ dt`` (so the Ah
counter, hence SOC, stays exact under the zero-order hold), voltage and temperature are bin means, the reference SOC is
taken at the bin start. A long step (a rest recorded sparsely, a gap) stays one step. For the ohmic term the bin mean
is exact (``mean(R0·I) = R0·mean(I)``); what is lost is the RC relaxation within one bin (τ ≫ 1 s here).

Split. ``before``/``after`` must be measured on data not used to fit what they score (DESIGN.md):

* two or more evaluation profiles: the effect parameters are fitted on the first, judged on all the others;
* one profile: fitted on its first ``train_fraction`` of time, judged on the rest (the simulation runs through the
  whole profile from its start, so the held-out part starts from the state the model reached, nothing re-fitted).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..profile import Profile


def bin_average(profile: Profile, dt: float = 1.0) -> Profile:
    """``profile`` on bins of at least ``dt`` s (see the module docstring); unchanged if it is already that coarse."""
    if profile.n < 3 or dt <= 0 or float(np.median(profile.dt)) >= dt:
        return profile
    t = profile.time_s
    bins = np.floor((t - t[0]) / dt + 1e-9).astype(np.int64)
    start = np.ones(t.size, dtype=bool)
    start[1:] = bins[1:] != bins[:-1]
    idx = np.flatnonzero(start)
    step = np.append(np.diff(t), 0.0)  # ZOH: sample k lasts until k+1 (the last sample weighs 0)
    w = np.add.reduceat(step, idx)
    n_in = np.add.reduceat(np.ones(t.size), idx)

    def mean_of(a, weighted):
        if a is None:
            return None
        if weighted:
            s = np.add.reduceat(a * step, idx)
            plain = np.add.reduceat(a, idx) / n_in
            return np.where(w > 0, s / np.where(w > 0, w, 1.0), plain)
        return np.add.reduceat(a, idx) / n_in

    return replace(
        profile,
        time_s=t[idx],
        current_a=mean_of(profile.current_a, True),
        voltage_v=mean_of(profile.voltage_v, False),
        temperature_c=mean_of(profile.temperature_c, False),
        soc_ref=None if profile.soc_ref is None else profile.soc_ref[idx],
    )


@dataclass(frozen=True, eq=False)
class Split:
    """What the effect parameters are fitted on (``train``) and what they are judged on (``held``).

    ``held`` is a list of ``(profile, first_index)``: each profile is simulated from its start and scored from
    ``first_index`` on.
    """

    train: Profile
    held: list
    method: str
    train_fraction: float | None = None

    def describe(self) -> dict:
        d = {
            "method": self.method,
            "train": {"profile": self.train.name, "n": self.train.n, "duration_s": self.train.duration_s},
            "held_out": [{"profile": p.name, "first_index": int(k), "n": int(p.n - k),
                          "duration_s": float(p.time_s[-1] - p.time_s[k])} for p, k in self.held],
        }
        if self.train_fraction is not None:
            d["train_fraction"] = self.train_fraction
        return d


def make_split(profiles, train_fraction: float = 0.5) -> Split:
    """The split of the evaluation profiles (module docstring)."""
    profiles = list(profiles)
    if len(profiles) >= 2:
        return Split(profiles[0], [(p, 0) for p in profiles[1:]], "by_profile")
    p = profiles[0]
    t_cut = p.time_s[0] + train_fraction * p.duration_s
    k = int(np.searchsorted(p.time_s, t_cut))
    k = min(max(k, 2), p.n - 2)
    return Split(p.slice(0, k), [(p, k)], "by_time", train_fraction)
