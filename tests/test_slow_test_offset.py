"""The current offset a slow OCV test's count still holds, read from its two branches (identify.hppc.
slow_test_count_error), and the OCV the diagnosis reads from such a test (diagnose.core.slow_test_branches).

A generator of this file's own draws cells over ranges (a Thevenin structure on the paper's pack OCV per cell, or on
a flat LFP-like curve; 2–40 Ah; R0 10–60 mΩ·Ah/Q) and records a slow test on each: a rest, a C/25–C/10 discharge to
2–5 %, a rest, a charge at another C/25–C/10 rate to 85–100 %, a rest (each rest 30–90 min), sampled every 10–60 s,
with white current noise of 0–1 % of 1C, an offset of up to ±0.5 % of 1C and 1 mV of voltage noise. Over a test of
forty hours, an offset the rests leave by 0.1 % of 1C moves the charge branch by 4 % of SOC and the mean curve by 2 %:
tens of mV on a sloped OCV. The rates over the draws are asserted, and against the rests' reading alone.
"""

from __future__ import annotations

import numpy as np

from socbench.diagnose import core
from socbench.identify import slow_test_count_error
from socbench.models import Constant, ModelParams, make_model, paper_ocv
from socbench.ocv import OCVCurve
from socbench.profile import Profile, ProfileMeta

DRAWS = 12


def _cell(rng, flat: bool):
    q = float(np.exp(rng.uniform(np.log(2.0), np.log(40.0))))
    r0 = rng.uniform(0.01, 0.06) / q
    if flat:  # a plateau with knees at both ends (LFP-like)
        z = np.linspace(0.0, 1.0, 21)
        v = 3.30 + 0.04 * z - 0.35 * np.exp(-z / 0.04) + 0.15 * np.exp((z - 1.0) / 0.03)
        ocv = OCVCurve(z, v, "flat")
    else:
        pack = paper_ocv()
        ocv = OCVCurve(pack.soc, pack.voltage / 6.0, "paper pack OCV / 6")
    params = ModelParams(q, ocv, {"R0": Constant(r0), "R1": Constant(rng.uniform(0.3, 1.0) * r0),
                                  "C1": Constant(rng.uniform(5.0, 40.0) / r0)})
    return make_model("thevenin", params), q


def slow_test(rng, model, q, adc_step_c: float = 0.0):
    """``(measured record, true offset [A])``: the module docstring's slow test on ``model``; with ``adc_step_c`` a
    noise-free current read by an ADC of that step (fraction of 1C)."""
    dt = float(rng.uniform(10.0, 60.0))
    c_dis, c_chg = rng.uniform(1 / 25, 1 / 10, 2)
    depth = rng.uniform(0.95, 0.98)
    top = rng.uniform(0.85, 1.0)
    rests = rng.uniform(1800.0, 5400.0, 3)
    segs = [(0.0, rests[0]), (c_dis * q, 3600.0 * depth / c_dis), (0.0, rests[1]),
            (-c_chg * q, 3600.0 * (top - 1.0 + depth) / c_chg), (0.0, rests[2])]
    cur = np.concatenate([np.full(int(d / dt), a) for a, d in segs])
    t = np.arange(cur.size) * dt
    sim = model.simulate(Profile(t, cur), soc0=1.0)
    offset = float(rng.uniform(-0.005, 0.005)) * q
    i_meas = cur + offset + rng.normal(0.0, float(rng.uniform(0.0, 0.01)) * q, cur.size)
    if adc_step_c:
        i_meas = np.round((cur + offset) / (adc_step_c * q)) * adc_step_c * q
    v = sim.voltage_v + rng.normal(0.0, 1e-3, cur.size)
    meta = ProfileMeta(name="slow", source="slow", capacity_ah=q, n_series=1)
    return Profile(t, i_meas, voltage_v=v, temperature_c=np.full(cur.size, 25.0), meta=meta), offset


def test_the_branches_read_the_offset_left_in_the_count():
    # the test's current with a wrong offset taken off (the true one ± up to 0.15 % of 1C): what is left is read
    # from the branches within 0.02 % of 1C on the sloped OCV (measured: within 0.011 % in 11 of 12 draws)
    hits = 0
    for seed in range(DRAWS):
        rng = np.random.default_rng([seed, 11])
        model, q = _cell(rng, flat=False)
        prof, offset = slow_test(rng, model, q)
        wrong = offset + float(rng.uniform(-0.0015, 0.0015)) * q
        test = prof.with_(current_a=prof.current_a - wrong)
        e, se = slow_test_count_error(test, capacity_ah=q, i_min=0.5 * float(np.median(np.abs(prof.current_a))))
        hits += abs(e - (offset - wrong)) <= 2e-4 * q and se < 2e-4 * q
    assert hits >= DRAWS - 1


def _ocv_errors(flat: bool, monkeypatch=None, adc_step_c: float = 0.0) -> np.ndarray:
    """RMS error [V] over 10–90 % SOC of the mean branch the diagnosis reads from each draw's slow test; with
    ``monkeypatch``, with the rests' reading of the offset alone."""
    if monkeypatch is not None:
        monkeypatch.setattr(core, "slow_test_count_error", lambda *a, **k: None)
    z = np.linspace(0.1, 0.9, 17)
    out = []
    for seed in range(DRAWS):
        rng = np.random.default_rng([seed, 13 + flat])
        model, q = _cell(rng, flat)
        prof, _ = slow_test(rng, model, q, adc_step_c)
        e = core.slow_test_branches(prof).mean(z) - model.params.ocv(z)
        out.append(float(np.sqrt(np.mean(e * e))))
    if monkeypatch is not None:
        monkeypatch.undo()
    return np.array(out)


def test_the_ocv_of_a_noisy_slow_test_is_read_with_its_count_corrected(monkeypatch):
    # on the sloped OCV, the branches' reading of what the rests leave takes the mean branch within 2.5 mV RMS of the
    # cell's in every draw, and halves the median error of the rests' reading alone (measured: 0.55 against 1.5 mV)
    with_branches, rests_only = _ocv_errors(False), _ocv_errors(False, monkeypatch)
    assert np.all(with_branches <= 2.5e-3)
    assert np.median(with_branches) <= 0.5 * np.median(rests_only)


def test_a_flat_ocv_is_not_moved_by_what_its_branches_read(monkeypatch):
    # on a plateau the branches do not move with the count, nor does the curve: whatever they read moves the mean
    # branch by less than 0.5 mV RMS
    with_branches, rests_only = _ocv_errors(True), _ocv_errors(True, monkeypatch)
    assert np.all(with_branches <= rests_only + 0.5e-3)


def test_an_undithered_adc_leaves_the_rests_a_step_of_doubt(monkeypatch):
    # a noise-free current read by an ADC of 0.2 % of 1C: the rests read one level (no spread, a standard error of 0)
    # while the offset lies anywhere within the step; the rests' reading is given the step's uniform spread
    # (step/√12) and the branches' reading counts beside it: the median error is lower than the rests' alone
    # (measured: 2.0 against 3.1 mV RMS; the test's own currents are quantised too, an error no offset describes)
    with_branches, rests_only = _ocv_errors(False, adc_step_c=0.002), _ocv_errors(False, monkeypatch, 0.002)
    assert np.median(with_branches) < np.median(rests_only)
