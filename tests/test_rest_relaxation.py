"""The time constants an HPPC's rests show (socbench.identify.rest_relaxation), and the fit test's branch they name.

The records are draws of ``tests/hppc_records.py`` (its own truth: cells of one or two RC branches solved exactly in
continuous time, its own hand-drawn OCV shapes, random layouts with and without charge pulses and Panasonic-style gaps,
0.1–10 s sampling, noisy, offset and quantised sensors; rests of 15 min–2 h here). The base is Thevenin (one branch),
fitted in constant mode on the rest-point OCV, whose error between the points dominates the whole record's residual
(the hand-drawn curves bend between them): the case the rests are read for.

* on cells with a second branch (τ₂ 150–1500 s) the rests show it (:func:`~socbench.identify.fit_test_effect.
  _rests_refuse` passes) in most draws (9 of 12 measured), at a time constant within ×2 of the truth's, and more
  often than the whole record's RMSE falls by the fit test's ``FIT_GAIN`` with the branch fitted on it;
* on cells with one branch they show none (0 of 12);
* the rests' fit does not see the OCV at all: a bump in the curve between the rest points changes the whole record's
  error by millivolts and the rests' fit by nothing;
* end to end, the diagnosis names the branch the rests show as its first step, found on the fit test, on draws whose
  drive record alone would not ask for it; and none on one-branch cells.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from socbench.diagnose import diagnose
from socbench.identify import fit_model
from socbench.identify.fit_test_effect import FIT_GAIN, _rests_refuse, _starts
from socbench.identify.rest_relaxation import _Rests, fit_rests, rest_evidence, rest_windows
from socbench.identify.select import validation_rmse
from socbench.ocv import OCVCurve
from tests.hppc_records import Cell, Instrument, drive_record, hppc_record, random_instrument, random_layout

DRAWS = 12
#: the log10 τ range of the extra branch (socbench.models.effects.ExtraRC.bounds)
TAU_RANGE = (0.5, 4.0)


def _cell(rng, two_branches: bool) -> Cell:
    q = float(np.exp(rng.uniform(np.log(1.0), np.log(50.0))))
    r0 = rng.uniform(0.03, 0.12) / q
    branches = [(rng.uniform(0.3, 1.0) * r0, float(np.exp(rng.uniform(np.log(5.0), np.log(40.0)))))]
    if two_branches:
        branches.append((rng.uniform(0.3, 0.8) * r0, float(np.exp(rng.uniform(np.log(150.0), np.log(1500.0))))))
    return Cell(q, str(rng.choice(["nmc", "nca", "lfp"])), r0, tuple(branches))


def _record(seed: int, two_branches: bool):
    """``(HPPC profile, cell)`` of one draw."""
    rng = np.random.default_rng([seed, 13])
    cell = _cell(rng, two_branches)
    lay = replace(random_layout(rng), rest_s=float(np.exp(rng.uniform(np.log(900.0), np.log(7200.0)))))
    rec = hppc_record(cell, lay, random_instrument(rng), seed=seed, with_soc_ref=lay.gaps)
    return rec.profile, cell


def _shown(ev, profile) -> bool:
    return ev is not None and _rests_refuse(ev, profile.duration_s, 3.0, TAU_RANGE) is None


def test_the_rests_show_a_branch_the_structure_lacks():
    shown, near, whole = 0, 0, 0
    for seed in range(DRAWS):
        prof, cell = _record(seed, True)
        plain = fit_model("thevenin", prof, mode="constant")
        ev = rest_evidence(plain, prof)
        if _shown(ev, prof):
            shown += 1
            near += abs(ev["log10_tau"] - np.log10(cell.branches[1][1])) <= np.log10(2.0)
        fits = [fit_model("thevenin", prof, mode="constant", ocv=plain.params.ocv,
                          capacity_ah=plain.params.capacity_ah, effects=[s]) for s in _starts("extra_rc", plain, {})]
        best = min(fits, key=lambda r: r.rmse_v)
        whole += best.rmse_v <= (1.0 - FIT_GAIN) * plain.rmse_v
    assert shown >= 2 * DRAWS // 3, shown  # measured: 9 of 12, every one within ×2 of the truth's τ₂
    assert near >= shown - 1, (near, shown)
    assert whole < shown, (whole, shown)  # the whole record's gain alone misses branches the rests show


def test_the_rests_show_no_branch_a_cell_does_not_have():
    shown = []
    for seed in range(DRAWS):
        prof, _ = _record(seed, False)
        ev = rest_evidence(fit_model("thevenin", prof, mode="constant"), prof)
        if _shown(ev, prof):
            shown.append((seed, ev))
    assert not shown, shown


def test_the_rests_fit_does_not_see_the_ocv():
    prof, _ = _record(3, True)
    plain = fit_model("thevenin", prof, mode="constant")
    ocv = plain.params.ocv
    z = np.linspace(0.0, 1.0, 201)
    # a bend the rest points miss, rising everywhere (the curve stays monotone): +0.02·(z + sin(6πz)/(6π))
    bumped = OCVCurve(z, ocv.value(z) + 0.02 * (z + np.sin(6.0 * np.pi * z) / (6.0 * np.pi)), "bent between points")
    other = replace(plain, params=plain.params.replace(ocv=bumped))
    windows = rest_windows(prof)
    x = np.zeros((1, 2))  # the fitted set's own branch (R1, C1 unscaled)
    ra, rb = _Rests(plain, prof, windows).residual(x, False), _Rests(other, prof, windows).residual(x, False)
    # equal but for the SOC the rests' measured current (its noise, after the offset) moves: µV against mV
    assert ra.size > 100 and np.max(np.abs(ra - rb)) <= 1e-5
    a, b = fit_rests(plain, prof, extra=True), fit_rests(other, prof, extra=True)
    assert a.n == b.n and a.n_rests >= 2
    assert a.rms_v == pytest.approx(b.rms_v, rel=1e-3)  # the same fit, to the optimiser's tolerance
    assert abs(validation_rmse(other, prof) - validation_rmse(plain, prof)) > 1e-3  # the whole record sees it


def test_a_record_without_rests_gives_no_evidence():
    prof, _ = _record(0, True)
    plain = fit_model("thevenin", prof, mode="constant")
    assert rest_windows(prof)
    drive = prof.with_(current_a=np.full(prof.n, 0.2 * plain.params.capacity_ah))
    assert rest_evidence(plain, drive) is None
    assert fit_rests(plain, drive) is None


def _diagnosed(seed: int, two_branches: bool):
    rng = np.random.default_rng([seed, 31])
    cell = _cell(rng, two_branches)
    lay = replace(random_layout(rng), gaps=False, rest_s=float(np.exp(rng.uniform(np.log(1800.0), np.log(7200.0)))))
    ins = random_instrument(rng)
    hppc = hppc_record(cell, lay, ins, seed=seed, with_soc_ref=False).profile
    drive = drive_record(cell, Instrument(dt=1.0, i_noise_c=ins.i_noise_c, v_noise=ins.v_noise), seed=seed + 1,
                         duration_s=7200.0).profile
    return diagnose("thevenin", [hppc], [drive], soc=False)


@pytest.mark.slow
def test_the_diagnosis_names_the_branch_the_rests_show():
    named, by_rests = 0, 0
    for seed in range(4):
        d = _diagnosed(seed, True)
        named += "extra_rc" in d.effects_added
        found = d.fit.get("fit_test_effect", {})
        by_rests += bool(found.get("shown_by_rests")) and found.get("added", False)
    assert named >= 3, named
    assert by_rests >= 1, by_rests


@pytest.mark.slow
def test_the_diagnosis_names_no_branch_a_cell_does_not_have():
    added = [(seed, d.effects_added) for seed in range(4) for d in [_diagnosed(seed, False)]
             if "extra_rc" in d.effects_added]
    assert not added, added
