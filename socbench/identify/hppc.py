"""HPPC analysis: rests, pulses, OCV points, the SOC axis and pulse resistances; OCV curves from a slow (C/20) test.

An HPPC record (ECM_SPEC §1; Panasonic 18650PF, Kollmeyer 2018, doi:10.17632/wykht8y7tg.1) is a sequence of pulse
*sets*, one per SOC level, separated by discharge steps (or, in the Panasonic files, by a gap in the record during which
the step happened) and long rests. The analysis

1. splits the record into **rests** (``|I| ≤ i_rest``) and **active intervals**; an active interval that starts from a
   rest and lasts at most ``max_pulse_s`` is a **pulse**, a longer one is a discharge step;
2. puts every sample on the **SOC axis** from the amp-hours: ``z = 1 − Ah/Q``, where ``Ah`` is the charge discharged
   since the first sample (the current integrated under zero-order hold or, when the record has gaps whose charge only
   the reference SOC knows, that reference; see :func:`discharged_ah`) and ``Q`` the capacity (default: the total
   discharged over the record, which runs from full to empty — ECM_SPEC §2 recommends the HPPC's own Ah);
3. groups pulses into **sets**: a new set starts whenever charge moved between two pulses other than by the pulses
   themselves (more than ``0.2 %`` of Q);
4. takes an **OCV point** at the end of the rest before each set (the last rest sample before its first pulse), plus
   the end of a final rest after a last discharge step;
5. estimates per pulse the **instantaneous resistance** ``r_inst = −ΔV/ΔI`` across the leading edge (one sample: under
   the ZOH convention ``y_k = h(x_k, I_k)`` this is exactly the model's ``R0(z)`` plus the decay of the RC states over
   one sample), the same across the trailing edge, the **pulse resistance** ``(V_before − V_end)/I`` at the end of
   the pulse, and the **relaxation time constant**: the time the voltage needs, in the rest after the pulse, to recover
   ``1 − 1/e`` of what it recovers by the end of that rest (after the instantaneous jump), and a slow one, a third of
   the time to recover 95 % (both equal τ for a single exponential).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import DataError
from ..ocv import OCVCurve, monotone_points
from ..profile import Profile

#: relative disagreement between the integrated current and the reference SOC above which the reference is used
AH_MISMATCH = 5e-3
#: a step moving more than this fraction of Q between two pulses starts a new pulse set
SET_SPLIT = 2e-3


@dataclass(frozen=True)
class Rest:
    start: int  # first rest sample
    stop: int  # one past the last rest sample
    duration_s: float
    soc_end: float
    v_end: float


@dataclass(frozen=True)
class Pulse:
    start: int  # first sample with the pulse current
    stop: int  # first rest sample after the pulse
    current_a: float  # charge-weighted mean current (A, positive = discharge)
    duration_s: float
    soc: float  # SOC at the pulse start
    level: int  # index of the pulse set
    r_inst: float  # leading edge  −ΔV/ΔI  [Ω]
    r_inst_off: float  # trailing edge −ΔV/ΔI [Ω]
    r_pulse: float  # (V_before − V_end)/I at the end of the pulse [Ω]
    tau_s: float  # relaxation time constant in the following rest [s] (nan if the rest is too short)
    tau_slow_s: float = float("nan")  # a third of the time to recover 95 % (the slow process) [s]


@dataclass(frozen=True, eq=False)
class HPPCAnalysis:
    """Result of :func:`analyze_hppc`. ``soc`` and ``ah`` are per sample of the analysed profile."""

    rests: tuple
    pulses: tuple
    ocv_soc: np.ndarray
    ocv_voltage: np.ndarray
    capacity_ah: float
    soc: np.ndarray
    ah: np.ndarray
    ah_source: str
    level_soc: np.ndarray
    notes: tuple = field(default_factory=tuple)

    def ocv(self, source: str = "") -> OCVCurve:
        """Monotone PCHIP through the OCV points (made monotone by isotonic regression first)."""
        z, v = monotone_points(self.ocv_soc, self.ocv_voltage)
        return OCVCurve(z, v, source or "HPPC rest points")

    def resistance_table(self) -> dict:
        """Per pulse set: SOC and the median pulse resistances ``{"soc", "r_inst", "r_pulse", "tau_s"}`` (arrays)."""
        lv = np.array([p.level for p in self.pulses])
        out = {"soc": [], "r_inst": [], "r_pulse": [], "tau_s": []}
        for j in np.unique(lv):
            ps = [p for p in self.pulses if p.level == j]
            out["soc"].append(ps[0].soc)
            out["r_inst"].append(float(np.median([p.r_inst for p in ps])))
            out["r_pulse"].append(float(np.median([p.r_pulse for p in ps])))
            taus = [p.tau_s for p in ps if np.isfinite(p.tau_s)]
            out["tau_s"].append(float(np.median(taus)) if taus else float("nan"))
        return {k: np.asarray(v) for k, v in out.items()}

    def medians(self) -> dict:
        """Record-wide medians used as fitting scales: ``r_inst``, ``r_pulse``, ``tau_s``, ``tau_slow_s``."""

        def med(xs):
            xs = [x for x in xs if np.isfinite(x)]
            return float(np.median(xs)) if xs else float("nan")

        return {
            "r_inst": med([p.r_inst for p in self.pulses]),
            "r_pulse": med([p.r_pulse for p in self.pulses]),
            "tau_s": med([p.tau_s for p in self.pulses]),
            "tau_slow_s": med([p.tau_slow_s for p in self.pulses]),
        }


# ------------------------------------------------------------------------------------------------ SOC axis
def discharged_ah(profile: Profile) -> tuple[np.ndarray, str]:
    """Charge discharged since the first sample [Ah] and where it came from (``"current"`` or ``"soc_ref"``).

    The integrated current (zero-order hold) is used unless the profile's reference SOC (with ``meta.capacity_ah``)
    disagrees with it by more than 0.5 % of the record's charge: then the record has gaps whose charge only the
    reference knows (the Panasonic HPPC files omit the discharges between pulse sets), and the reference is used.
    """
    ah = profile.amp_hours()
    if profile.soc_ref is not None and profile.meta.capacity_ah:
        ref = (profile.soc_ref[0] - profile.soc_ref) * float(profile.meta.capacity_ah)
        scale = max(float(np.max(np.abs(ref))), float(np.max(np.abs(ah))), 1e-12)
        if float(np.max(np.abs(ref - ah))) > AH_MISMATCH * scale:
            return ref, "soc_ref"
    return ah, "current"


def unrecorded_charge(profile: Profile, threshold_frac: float = 1e-3) -> np.ndarray:
    """Per sample, the charge [Ah] discharged in the step *into* the sample that the current column does not carry
    (0 where the column and the reference agree to ``threshold_frac`` of the record's charge)."""
    ah, src = discharged_ah(profile)
    out = np.zeros(profile.n)
    if src != "soc_ref":
        return out
    extra = np.diff(ah) - np.diff(profile.amp_hours())
    thr = threshold_frac * max(float(np.max(np.abs(ah))), 1e-12)
    out[1:] = np.where(np.abs(extra) > thr, extra, 0.0)
    return out


# ------------------------------------------------------------------------------------------------ structure
def _intervals(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` of the runs of True in ``mask``."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def _recovery_tau(t: np.ndarray, v: np.ndarray, level: float = 1.0 - np.exp(-1.0)) -> float:
    """Time for ``v − v[0]`` to reach ``level`` (default ``1 − 1/e``) of ``v[-1] − v[0]`` (linear interpolation)."""
    if v.size < 4:
        return float("nan")
    rec = v - v[0]
    final = rec[-1]
    if not np.isfinite(final) or abs(final) < 1e-9:
        return float("nan")
    frac = rec / final
    k = int(np.argmax(frac >= level))
    if k == 0:
        return float("nan")
    f0, f1 = frac[k - 1], frac[k]
    w = 0.0 if f1 == f0 else (level - f0) / (f1 - f0)
    return float(t[k - 1] + w * (t[k] - t[k - 1]) - t[0])


def analyze_hppc(profile: Profile, capacity_ah: float | None = None, i_rest: float | None = None,
                 max_pulse_s: float = 60.0, min_rest_s: float = 60.0) -> HPPCAnalysis:
    """Analyse an HPPC record (see the module docstring). Raises :class:`DataError` when it holds no pulse."""
    if profile.batched:
        raise DataError("analyze_hppc needs a plain profile", file=profile.meta.source or profile.name)
    profile.require("voltage_v")
    src = profile.meta.source or profile.name
    t, i, v = profile.time_s, profile.current_a, profile.voltage_v
    if i_rest is None:
        i_rest = 5e-3 * float(np.max(np.abs(i))) + 1e-6
    ah, ah_source = discharged_ah(profile)
    q = float(capacity_ah) if capacity_ah else float(np.max(ah))
    if not q > 0:
        raise DataError("the record discharges no charge: cannot place it on the SOC axis", file=src)
    soc = 1.0 - ah / q
    t_end = np.append(t[1:], t[-1])  # a sample's interval ends at the next time stamp

    rest_mask = np.abs(i) <= i_rest
    rests = []
    for a, b in _intervals(rest_mask):
        dur = float(t_end[b - 1] - t[a]) if b < t.size else float(t[b - 1] - t[a])
        rests.append(Rest(a, b, dur, float(soc[b - 1]), float(v[b - 1])))
    pulses = []
    level = -1
    last_stop_ah = None
    for a, b in _intervals(~rest_mask):
        if a == 0 or b >= t.size:  # must start from a rest and end in one
            continue
        dur = float(t[b] - t[a])
        if dur > max_pulse_s:
            continue
        if last_stop_ah is None or abs(ah[a - 1] - last_stop_ah) > SET_SPLIT * q:
            level += 1
        last_stop_ah = ah[b]
        dts = t[a + 1:b + 1] - t[a:b]
        cur = float(np.sum(i[a:b] * dts) / np.sum(dts))
        r_inst = float((v[a - 1] - v[a]) / (i[a] - i[a - 1]))
        r_off = float((v[b] - v[b - 1]) / (i[b - 1] - i[b]))
        r_pulse = float((v[a - 1] - v[b - 1]) / cur)
        nxt = next((r for r in rests if r.start == b), None)
        tau = tau_slow = float("nan")
        if nxt is not None and nxt.stop - nxt.start >= 4:
            tr, vr = t[nxt.start:nxt.stop], v[nxt.start:nxt.stop]
            tau = _recovery_tau(tr, vr)
            tau_slow = _recovery_tau(tr, vr, 0.95) / 3.0
        pulses.append(Pulse(a, b, cur, dur, float(soc[a - 1]), level, r_inst, r_off, r_pulse, tau, tau_slow))
    if not pulses:
        raise DataError(f"no pulse found (active intervals from rest to rest of at most {max_pulse_s:g} s)", file=src)

    # OCV points: end of the rest before each set's first pulse, and a final rest after a last step
    ocv_z, ocv_v, notes = [], [], []
    firsts = {}
    for p in pulses:
        firsts.setdefault(p.level, p)
    rest_by_stop = {r.stop: r for r in rests}
    for p in firsts.values():
        r = rest_by_stop.get(p.start)
        if r is not None and r.start == 0 and r.duration_s < min_rest_s:
            # the record starts at rest: the cell rested before the test began (HPPC protocol), keep the point
            notes.append(f"pulse set at z={p.soc:.3f}: OCV point from the record's initial rest ({r.duration_s:g} s)")
        elif r is None or r.duration_s < min_rest_s:
            notes.append(f"pulse set at z={p.soc:.3f}: rest before it shorter than {min_rest_s:g} s, no OCV point")
            continue
        ocv_z.append(r.soc_end)
        ocv_v.append(r.v_end)
    last = rests[-1] if rests else None
    if last is not None and last.stop == t.size and last.duration_s >= min_rest_s:
        if abs(ah[-1] - ah[pulses[-1].stop]) > SET_SPLIT * q:
            ocv_z.append(last.soc_end)
            ocv_v.append(last.v_end)
    if len(ocv_z) < 2:
        raise DataError(f"only {len(ocv_z)} OCV rest point(s) found; an OCV curve needs 2", file=src)
    level_soc = np.array([p.soc for p in firsts.values()])
    return HPPCAnalysis(tuple(rests), tuple(pulses), np.asarray(ocv_z), np.asarray(ocv_v), q, soc, ah, ah_source,
                        level_soc, tuple(notes))


def ocv_from_hppc(profile: Profile, capacity_ah: float | None = None, **options) -> OCVCurve:
    """The OCV curve through the HPPC rest points (:func:`analyze_hppc`), monotone PCHIP (ECM_SPEC §3.3)."""
    a = analyze_hppc(profile, capacity_ah=capacity_ah, **options)
    return a.ocv(source=f"HPPC rest points of {profile.meta.source or profile.name} ({a.ocv_soc.size} points, "
                        f"Q = {a.capacity_ah:.4g} Ah)")


# ------------------------------------------------------------------------------------------------ slow test
@dataclass(frozen=True, eq=False)
class SlowOCV:
    """OCV from a slow constant-current test: the discharge branch, the charge branch (None if the test has no
    charge) and their mean (None without a charge branch). ``capacity_ah`` is the discharged charge of the test."""

    discharge: OCVCurve
    charge: OCVCurve | None
    mean: OCVCurve | None
    capacity_ah: float

    @property
    def best(self) -> OCVCurve:
        """The mean of both branches when there are two, else the discharge branch."""
        return self.mean if self.mean is not None else self.discharge


def _binned(z: np.ndarray, v: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    edges = np.linspace(z.min(), z.max(), n_bins + 1)
    k = np.clip(np.searchsorted(edges, z, side="right") - 1, 0, n_bins - 1)
    cnt = np.bincount(k, minlength=n_bins)
    ok = cnt > 0
    zs = np.bincount(k, weights=z, minlength=n_bins)[ok] / cnt[ok]
    vs = np.bincount(k, weights=v, minlength=n_bins)[ok] / cnt[ok]
    return zs, vs


def ocv_from_slow_test(profile: Profile, capacity_ah: float | None = None, n_points: int = 101,
                       i_min: float | None = None) -> SlowOCV:
    """Pseudo-OCV branches of a slow (e.g. C/20) discharge and, when present, the following charge.

    SOC: the discharge branch runs from 1 (its start) to 0 (its end) over ``Q`` = its discharged charge (or
    ``capacity_ah``); the charge branch continues the same charge count, climbing with the charged Ah (coulombic
    efficiency 1). Each branch is averaged into ``n_points`` SOC bins and made monotone. The mean curve is
    the average of the branches where both exist; above the top of the charge branch (a charge that stops at the
    voltage limit before the full capacity) it is the discharge branch shifted by half the gap at the top of the
    overlap.
    """
    profile.require("voltage_v")
    src = profile.meta.source or profile.name
    i, v = profile.current_a, profile.voltage_v
    ah = profile.amp_hours()
    if i_min is None:
        i_min = 0.2 * float(np.max(np.abs(i)))
    dis = i > i_min
    if not dis.any():
        raise DataError("no discharge in the slow OCV test", file=src, column="current_a")
    runs = _intervals(dis)
    a, b = max(runs, key=lambda r: ah[r[1] - 1] - ah[r[0]])
    q_dis = float(ah[b - 1] - ah[a])
    q = float(capacity_ah) if capacity_ah else q_dis
    z_d = 1.0 - (ah[a:b] - ah[a]) / q
    zd, vd = monotone_points(*_binned(z_d, v[a:b], n_points))
    discharge = OCVCurve(zd, vd, f"C/20 discharge branch of {src}")
    chg = (i < -i_min) & (np.arange(i.size) >= b)
    charge = mean = None
    if chg.any():
        c0, c1 = max(_intervals(chg), key=lambda r: r[1] - r[0])
        z_c = 1.0 - (ah[c0:c1] - ah[a]) / q  # the same charge count as the discharge branch
        zc, vc = monotone_points(*_binned(z_c, v[c0:c1], n_points))
        charge = OCVCurve(zc, vc, f"C/20 charge branch of {src}")
        grid = zd
        top = zc.max()
        inside = grid <= top
        half_gap_top = 0.5 * (float(charge(top)) - float(discharge(top)))
        vm = np.where(inside, 0.5 * (discharge(grid) + charge(np.minimum(grid, top))), discharge(grid) + half_gap_top)
        zm, vm = monotone_points(grid, vm)
        mean = OCVCurve(zm, vm, f"mean of the C/20 branches of {src}")
    return SlowOCV(discharge, charge, mean, q)


def edge_resistance(profile: Profile, frac: float = 0.2) -> float:
    """Median ``−ΔV/ΔI`` over the sample-to-sample current steps larger than ``frac`` × the largest step: an
    instantaneous-resistance scale for any record (used when a record has no HPPC pulses)."""
    profile.require("voltage_v")
    di = np.diff(profile.current_a)
    dv = np.diff(profile.voltage_v)
    big = np.abs(di) >= frac * np.max(np.abs(di), initial=0.0)
    big &= np.abs(di) > 0
    if not big.any():
        raise DataError("the record has no current steps to estimate a resistance from",
                        file=profile.meta.source or profile.name)
    return float(np.median(-dv[big] / di[big]))
