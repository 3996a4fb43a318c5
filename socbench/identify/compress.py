"""Profile compression for fitting: merge zero-order-hold steps of (nearly) constant current into longer steps.

Every model in socbench holds the current over a step (ECM_SPEC §2). Over ``K`` consecutive samples of the same
current ``I``, ``K`` steps of lengths ``dt_1 … dt_K`` and one step of length ``Σ dt`` give the same state at the end:
the SOC counter is linear in ``dt``, an RC branch ``U⁺ = a U + R(1 − a) I`` composes exactly
(``a(dt_1)·a(dt_2) = a(dt_1 + dt_2)``), and so do the integrator and the low-pass current. What changes is only where
SOC-dependent parameters are evaluated (once per step, at its start); over a merged step SOC moves by
``I·Σdt/(3600 Q)`` — 0.2 % of SOC for a 10 s pulse at 2 C — so the difference is second order.

A merged step carries the charge-preserving mean current (``Σ I dt / Σ dt``), so the Ah counter stays exact even
where the measured current wobbles within the tolerance. The voltage is kept at the kept samples only: compression
subsamples the residual. Within a run of constant current the kept samples are spaced geometrically from the run's
start (``first_step_s``, then doubling up to ``max_step_s``), so the fast relaxation right after every edge keeps its
resolution and a 20-minute rest costs a few dozen points instead of a thousand.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..profile import Profile
from .hppc import rest_level

#: samples whose current differs from the previous one by less than this many standard deviations of the difference
#: of two noisy readings (√2 σ, σ the sensor noise measured on the rests) belong to the same step
NOISE_TOL_K = 5.0


@dataclass(frozen=True)
class Compression:
    """A compressed profile and the original sample index of each of its samples."""

    profile: Profile
    index: np.ndarray

    @property
    def ratio(self) -> float:
        return float(self.index[-1] + 1) / self.index.size if self.index.size else 1.0


def _targets(max_len: float, first_step_s: float, growth: float, max_step_s: float) -> np.ndarray:
    """Kept times after a run start: 0, d0, d0·g, d0·g², … with spacing capped at ``max_step_s``, up to ``max_len``."""
    out = [0.0]
    spacing = first_step_s
    t = first_step_s
    while t <= max_len + max_step_s:
        out.append(t)
        spacing = min(spacing * growth, max_step_s) if len(out) > 2 else spacing
        t += spacing
    return np.asarray(out)


def compress_profile(profile: Profile, max_step_s: float = 60.0, first_step_s: float = 1.0, growth: float = 2.0,
                     i_tol: float | None = None, max_ah: float | None = None) -> Compression:
    """Merge samples of constant current (within ``i_tol`` A of the previous sample) into longer ZOH steps.

    ``i_tol`` defaults to 0.1 % of the largest |I| (plus 1 µA), well above a lab tester's current noise and far below
    any load step, or, for a noisier sensor, ``NOISE_TOL_K·√2·σ`` with ``σ`` the current noise measured on the
    record's rests (:func:`~socbench.identify.hppc.rest_level`): white noise alone then splits a step once in
    ~10⁶ samples instead of at every sample. A quantised reading's error holds its ADC step ``q`` too,
    ``σ² + q²/12``: dithered by noise under a step, it flips between two levels, and its robust σ reads 0 (a
    600 000-sample HPPC whose current an ADC read in steps of 0.25 % of the peak kept every other sample: its fit took
    75 s instead of 1.3 s, the diagnosis 72 s). ``max_ah`` caps the charge moved by one merged step (SOC-dependent
    parameters are frozen over a step, so a long discharge step is cut into pieces of at most ``max_ah`` Ah;
    ``fit_parameters`` uses 0.5 % of the model's capacity). The first and last samples are always kept. Works on
    plain (non-batched) profiles.
    """
    if profile.batched:
        raise ValueError("compress_profile needs a plain profile; use profile.run(r)")
    t = profile.time_s
    i = profile.current_a
    n = t.size
    if n < 3:
        return Compression(profile, np.arange(n))
    if i_tol is None:
        lev = rest_level(i)
        i_tol = max(1e-3 * float(np.max(np.abs(i))) + 1e-6,
                    NOISE_TOL_K * np.sqrt(2.0) * np.hypot(lev.noise_a, lev.step_a / np.sqrt(12.0)))
    di = np.abs(np.diff(i))
    new_run = np.ones(n, dtype=bool)
    new_run[1:] = di > i_tol
    run_id = np.cumsum(new_run) - 1
    run_start_t = t[new_run][run_id]
    elapsed = t - run_start_t
    targets = _targets(float(elapsed.max()), first_step_s, growth, max_step_s)
    slot = np.searchsorted(targets, elapsed + 1e-9, side="right")
    keep = new_run.copy()
    keep[1:] |= slot[1:] != slot[:-1]
    if max_ah is not None and max_ah > 0:
        ah = profile.amp_hours()
        ah_slot = np.floor(np.abs(ah - ah[new_run][run_id]) / max_ah)
        keep[1:] |= ah_slot[1:] != ah_slot[:-1]
    keep[-1] = True
    idx = np.flatnonzero(keep)
    dt = np.diff(t)
    # charge-preserving mean current over each kept step [idx_j, idx_{j+1})
    charge = np.add.reduceat(i[:-1] * dt, idx[:-1]) if idx.size > 1 else np.zeros(0)
    span = np.add.reduceat(dt, idx[:-1]) if idx.size > 1 else np.zeros(0)
    cur = np.empty(idx.size)
    cur[:-1] = charge / span
    cur[-1] = i[-1]

    def pick(a):
        return None if a is None else a[idx]

    prof = replace(profile, time_s=t[idx], current_a=cur, voltage_v=pick(profile.voltage_v),
                   temperature_c=pick(profile.temperature_c), soc_ref=pick(profile.soc_ref))
    return Compression(prof, idx)
