"""Preparing evaluation data for the diagnosis: charge-preserving averaging and the train / held-out split.

Averaging. A 10 Hz drive cycle costs ten model steps a second and its fits would take minutes; the diagnosis works on
bins of at least ``dt`` seconds. Within a bin the current is the charge-preserving mean ``Σ I·dt / Σ dt`` (so the Ah
counter, hence SOC, stays exact under the zero-order hold), voltage and temperature are bin means, the reference SOC is
taken at the bin start. A long step (a rest recorded sparsely, a gap) stays one step. For the ohmic term the bin mean
is exact (``mean(R0·I) = R0·mean(I)``); what is lost is the RC relaxation within one bin (τ ≫ 1 s here).

Folds. ``before``/``after`` must be measured on data not used to fit what they score (DESIGN.md). One cut (fit on the
first half, judge on the second) wastes half the data on each side and cannot find an effect that shows only in one
part of the record (hysteresis after the first recharge). So every evaluation record is cut into ``k`` contiguous
blocks of equal duration (blocked cross-validation): fold ``j`` fits the effect parameters on all samples outside
block ``j`` of every record and is scored on block ``j``; the held-out error is the sum over the folds, so every
sample is scored exactly once, by parameters that never saw it. Each record is simulated from its start (block ``j``'s
current drives the states through it; its voltage is not in the fit), so a held-out block starts from the state the
model reached, nothing re-fitted.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import DataError
from ..profile import Profile, gap_steps
from ..segments import find_segments

#: the fewest samples, and the shortest duration [s], of a piece :func:`split_at_gaps` keeps
MIN_PIECE_SAMPLES, MIN_PIECE_S = 10, 60.0
#: a reference SOC that moves across a gap by more than this beyond the counted charge cuts the record there
#: (:func:`split_at_gaps`). Lower than a simulation's restart rule (socbench.segments.SOC_JUMP, 5 points, made for a
#: BMS's 1 % steps): the diagnosis compares voltages, and one point of SOC is 5–15 mV on a sloped OCV, several times
#: the noise (a 10-minute pause in a 1C drive whose last sample's current held over it: 3 points off, 13.5 -> 22 mV)
GAP_SOC_JUMP = 0.01
#: each block of the blocked cross-validation holds at least this many samples (over the records): a fold with
#: nothing to score, or a handful, is no held-out test
MIN_BLOCK_SAMPLES = 10


def split_at_gaps(profiles, model) -> tuple[list, list]:
    """``(records, notes)``: every evaluation record cut at its segment boundaries
    (:func:`socbench.segments.find_segments` with ``model``'s OCV and capacity standing in), a reference SOC that
    falls across a gap beyond the counted charge included, the reference's limit :data:`GAP_SOC_JUMP`. The diagnosis
    simulates a record from its start with the current it holds: across a battery swap, a recharge, or a logger that
    paused while the cell was driven, the zero-order hold would carry the last current through the gap and leave the
    SOC wrong for the rest of the record, and the search would spend effects on that. Each piece starts again from its
    own reference SOC (or the SOC its first voltage reads, :func:`socbench.diagnose.search.initial_soc`); pieces
    shorter than :data:`MIN_PIECE_SAMPLES` samples or :data:`MIN_PIECE_S` are left out. A record without such a gap
    is kept whole (the same object)."""
    out, notes = [], []
    for p in profiles:
        seg = find_segments(p, model.ocv, model.capacity_ah, unrecorded_discharge=True, soc_jump=GAP_SOC_JUMP)
        if seg.count == 1:
            out.append(p)
            continue
        spans = [(a, b) for a, b in seg.spans()
                 if b - a >= MIN_PIECE_SAMPLES and p.time_s[b - 1] - p.time_s[a] >= MIN_PIECE_S]
        name = p.name
        if not spans:
            out.append(p)
            notes.append(f"{name}: {seg.count - 1} gap(s) the current does not bridge ({'; '.join(seg.reasons)}), "
                         f"but no piece between them of {MIN_PIECE_SAMPLES} samples and {MIN_PIECE_S:g} s: kept whole")
            continue
        for j, (a, b) in enumerate(spans):
            piece = p.slice(a, b)
            out.append(piece.with_(meta=replace(piece.meta, name=f"{name} [{j + 1}/{len(spans)}]")))
        notes.append(f"{name}: cut into {len(spans)} at {seg.count - 1} gap(s) the current does not bridge "
                     f"({'; '.join(seg.reasons)}); each piece starts from its own SOC"
                     + (f" ({seg.count - len(spans)} piece(s) too short left out)" if len(spans) < seg.count else ""))
    return out, notes


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
class Folds:
    """Blocked cross-validation over time (see the module docstring).

    ``records`` are the evaluation profiles; ``blocks[r]`` gives each sample of record ``r`` its block ``0 … k − 1``
    (contiguous, equal durations). Fold ``j`` fits on every sample outside block ``j`` (of every record) and is
    scored on block ``j``; each record is always simulated from its start.
    """

    records: list
    k: int
    blocks: list
    #: the blocks are of equal *recorded* duration, each gap in a record counted as one median step
    #: (:func:`make_folds`: a record with a long pause, where equal spans of clock time leave blocks empty)
    recorded_time: bool = False

    @property
    def n(self) -> int:
        return int(sum(p.n for p in self.records))

    def train_mask(self, r: int, j: int) -> np.ndarray:
        """Samples of record ``r`` that fold ``j`` fits on (``j = None``: every sample, the all-data fit)."""
        return np.ones(self.records[r].n, dtype=bool) if j is None else self.blocks[r] != j

    def held(self):
        """``[(record, block of every sample)]`` (the scoring view)."""
        return list(zip(self.records, self.blocks))

    def describe(self) -> dict:
        recs = []
        for p, b in zip(self.records, self.blocks):
            edges = [float(p.time_s[np.flatnonzero(b == j)[0]] - p.time_s[0]) for j in range(self.k) if np.any(b == j)]
            recs.append({"profile": p.name, "n": int(p.n), "duration_s": float(p.duration_s), "block_starts_s": edges})
        equal = "equal recorded duration (each gap counted as one median step)" if self.recorded_time else \
            "equal duration"
        return {"method": "blocked_cv", "folds": self.k, "records": recs,
                "note": f"each record cut into {self.k} contiguous blocks of {equal}; fold j fits the effect "
                        "parameters on every sample outside block j of every record and is scored on block j"}


def _blocks(profiles, k: int, recorded: bool) -> list:
    """Each record's samples' blocks ``0 … k − 1``: equal spans of its clock time, or (``recorded``) of its recorded
    time, every gap step (:func:`socbench.profile.gap_steps`) counted as one median step."""
    blocks = []
    for p in profiles:
        if recorded and p.n > 1:
            dt = np.diff(p.time_s)
            t = np.concatenate([[0.0], np.cumsum(np.where(gap_steps(dt), float(np.median(dt)), dt))])
            frac = t / max(float(t[-1]), 1e-12)
        else:
            frac = (p.time_s - p.time_s[0]) / max(p.duration_s, 1e-12)
        blocks.append(np.minimum((frac * k).astype(int), k - 1))
    return blocks


def _per_block(blocks, k: int) -> np.ndarray:
    return np.bincount(np.concatenate(blocks), minlength=k) if blocks else np.zeros(k, dtype=int)


def make_folds(profiles, k: int = 4) -> Folds:
    """Blocked folds over the evaluation profiles (module docstring): ``k`` equal-duration blocks per record. Where a
    block would hold fewer than :data:`MIN_BLOCK_SAMPLES` samples and the records have gaps (a logger off for a day
    at rest), the blocks span equal *recorded* time instead (:func:`_blocks`)."""
    profiles = list(profiles)
    if k < 2:
        raise ValueError("blocked cross-validation needs at least 2 folds")
    blocks = _blocks(profiles, k, recorded=False)
    per_block = _per_block(blocks, k)
    recorded = False
    if per_block.min() < MIN_BLOCK_SAMPLES and any(gap_steps(np.diff(p.time_s)).any() for p in profiles):
        blocks, recorded = _blocks(profiles, k, recorded=True), True
        per_block = _per_block(blocks, k)
    if per_block.min() < MIN_BLOCK_SAMPLES:
        names = ", ".join(p.meta.source or p.name for p in profiles)
        raise DataError(f"the evaluation data holds {int(per_block.sum())} samples as the diagnosis reads it (bins of "
                        f"--dt seconds); its {k} blocks of held-out time need at least {MIN_BLOCK_SAMPLES} each "
                        f"(fewest: {int(per_block.min())}): give a longer record or a smaller --dt", file=names)
    return Folds(profiles, int(k), blocks, recorded)
