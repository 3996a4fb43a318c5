"""What a reference SOC column counts, read off the column (``socbench.socaxis.read_reference_count``), and the
diagnosis' report of it beside the model's capacity.

The reader is checked on records it did not make: a randomised generator of its own here (sample periods 0.1–10 s,
capacities 1–50 Ah, charge and discharge segments and rests, current noise, an offset and ADC steps on the current, a
reference rounded to 0.01 points), and the evaluation records of the randomised undeclared-effect benchmark, whose
reference is the truth cell's SOC: there a hidden fade shows as the capacity and a hidden current-sensor offset as the
current the reference leaves out.
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from socbench.checks import implied_reference_capacity
from socbench.diagnose import diagnose
from socbench.diagnose.randomized import draw_case
from socbench.diagnose.report import COUNT_GAP, reference_count_sentence, write_report
from socbench.profile import Profile, ProfileMeta
from socbench.socaxis import read_reference_count

#: reading tolerances on this file's records: capacity (share), current left out (share of 1C). The reference is
#: rounded to 1e-4 (±0.005 points) and the current carries white noise up to 1 % of 1C and ADC steps of 0.1 % of 1C
#: (a constant error within each segment): both put the read a few 0.01 % off
Q_TOL, C_TOL = 0.005, 0.001


def _record(rng, q: float, dt: float, offset_a: float, hours: float = 3.0, z0: float = 0.95,
            steady: bool = False) -> tuple[Profile, float]:
    """A record of a cell of ``q`` Ah whose current sensor reads ``offset_a`` too much discharge, with its reference
    SOC counted from the true current (rounded to 1e-4). Segments of 5–600 s at −0.5…2C or rest, kept within
    5–98 % SOC (a steady 0.5C discharge with ``steady``)."""
    segs, z, total = [], z0, 0.0
    while total < hours * 3600.0:
        d = float(rng.uniform(5.0, 600.0))
        c = 0.5 * q if steady else float(rng.choice([0.0, 0.2, 0.5, 1.0, 2.0, -0.5])) * q
        if not 0.05 < z - c * d / 3600.0 / q < 0.98:
            c = 0.0
        z -= c * d / 3600.0 / q
        segs.append((d, c))
        total += d
    t = np.arange(0.0, total, dt)
    seg = np.minimum(np.searchsorted(np.cumsum([s[0] for s in segs]), t, side="right"), len(segs) - 1)
    i_true = np.array([segs[k][1] for k in seg])
    ref = z0 - np.concatenate([[0.0], np.cumsum(i_true[:-1] * np.diff(t))]) / 3600.0 / q
    i_meas = i_true + offset_a + rng.normal(0.0, rng.uniform(0.0, 0.01) * q, t.size)
    i_meas = np.round(i_meas / (0.001 * q)) * (0.001 * q)
    return Profile(time_s=t, current_a=i_meas, voltage_v=np.full(t.size, 3.7), soc_ref=np.round(ref, 4),
                   meta=ProfileMeta(capacity_ah=q, name="r")), i_true


def test_the_count_and_the_current_left_out_are_read_over_random_records():
    rng = np.random.default_rng(20261201)
    misses = []
    for k in range(120):
        q = float(np.exp(rng.uniform(np.log(1.0), np.log(50.0))))
        dt = float(np.exp(rng.uniform(np.log(0.1), np.log(10.0))))
        offset = float(rng.uniform(-0.005, 0.005)) * q
        p, _ = _record(rng, q, dt, offset)
        r = read_reference_count([p])
        if r is None or r["uncounted_current_a"] is None or abs(r["capacity_ah"] / q - 1.0) > Q_TOL \
                or abs(r["uncounted_current_a"] - offset) > C_TOL * q:
            misses.append((k, q, dt, offset, r))
    assert not misses, misses


def test_records_share_one_count_each_from_its_own_start():
    rng = np.random.default_rng(7)
    q, offset = 12.0, 0.03
    recs = [_record(rng, q, 2.0, offset, hours=2.0, z0=z0)[0] for z0 in (0.95, 0.6)]
    r = read_reference_count(recs)
    assert r["records"] == 2
    assert r["capacity_ah"] == pytest.approx(q, rel=Q_TOL)
    assert r["uncounted_current_a"] == pytest.approx(offset, abs=C_TOL * q)


def test_a_steady_current_reads_the_capacity_alone():
    rng = np.random.default_rng(3)
    p, _ = _record(rng, 5.0, 1.0, 0.0, hours=1.5, steady=True)
    r = read_reference_count([p])
    assert r["uncounted_current_a"] is None  # the count and the time move together: no offset can be told apart
    assert r["capacity_ah"] == pytest.approx(5.0, rel=Q_TOL)


def test_a_reference_too_short_or_clipped_or_absent():
    rng = np.random.default_rng(5)
    p, _ = _record(rng, 3.0, 1.0, 0.0, hours=0.05)  # three minutes: the reference hardly moves
    assert read_reference_count([p]) is None
    assert read_reference_count([p.with_(soc_ref=None)]) is None
    # a count that runs past empty and is clipped there: the clipped samples do not count
    t = np.arange(0.0, 4000.0, 1.0)
    ref = 1.0 - t / 3600.0  # 1C from full
    clipped = Profile(time_s=t, current_a=np.full(t.size, 2.0), voltage_v=np.full(t.size, 3.7),
                      soc_ref=np.clip(ref, 0.0, 1.0), meta=ProfileMeta(capacity_ah=2.0, name="c"))
    assert read_reference_count([clipped])["capacity_ah"] == pytest.approx(2.0, rel=1e-6)


def test_the_fit_checks_implied_capacity_is_the_count_alone():
    rng = np.random.default_rng(11)
    p, _ = _record(rng, 8.0, 2.0, 0.02)
    alone = read_reference_count([p], uncounted=False)
    assert alone["uncounted_current_a"] is None
    assert implied_reference_capacity(p) == alone["capacity_ah"]
    # without the offset term the capacity takes up the offset: the two reads differ
    assert abs(alone["capacity_ah"] - read_reference_count([p])["capacity_ah"]) > 1e-3 * 8.0


def test_the_benchmarks_truth_shows_its_fade_and_its_sensor_offset():
    """The randomised benchmark's evaluation reference is the truth cell's SOC, counted from the true current: the
    read capacity is the cell's (faded where a fade is hidden), the current left out the field sensor's offset."""
    checked = {"capacity": 0, "current_bias": 0, "other": 0}
    for index in range(48):
        case = draw_case(index, 90210)
        r = read_reference_count(case.evals)
        assert r is not None
        fade = case.draws.get("capacity", {}).get("fade", 0.0)
        bias = case.draws.get("current_bias", {}).get("b0", 0.0)
        if "self_discharge" in case.effects or "coulombic_efficiency" in case.effects:
            continue  # a leak and a charge efficiency move the truth off the count too
        assert r["capacity_ah"] == pytest.approx(case.capacity_ah * (1.0 - fade), rel=Q_TOL), index
        assert r["uncounted_current_a"] == pytest.approx(bias, abs=C_TOL * case.capacity_ah), index
        checked["capacity" if fade else "current_bias" if bias else "other"] += 1
    assert checked["capacity"] >= 3 and checked["current_bias"] >= 3 and checked["other"] >= 10, checked


def _rc(q=8.0, c=0.02, rms=0.0005, before=8.3, after=8.3) -> dict:
    return {"capacity_ah": q, "uncounted_current_a": c, "residual_soc_rms": rms, "span": 0.8, "records": 1,
            "model_capacity_ah": {"before": before, "after": after}}


def test_the_sentence_says_what_the_axes_part_by():
    s = reference_count_sentence(_rc())
    assert "counts 8 Ah per unit of SOC" in s and "20.0 mA less discharge" in s and "8.3 Ah (+3.8 %)" in s
    assert "drifts by 3.8 % of the charge moved" in s
    s = reference_count_sentence(_rc(c=-0.02, before=8.0 * (1 + COUNT_GAP / 2), after=8.0 * (1 + COUNT_GAP / 2)))
    assert "20.0 mA more discharge" in s and "drifts" not in s  # within COUNT_GAP: no drift to speak of
    s = reference_count_sentence(_rc(after=8.0))  # a capacity effect put the final model on the reference's axis
    assert "the model after the search 8 Ah (+0.0 %)" in s and "drifts" not in s
    s = reference_count_sentence(_rc(rms=0.03))
    assert "is no count of their current" in s and "Ah" not in s
    # a reference its records declare a count on a capacity: the scoring converts to that axis, no drift remains
    s = reference_count_sentence({**_rc(), "declared_capacity_ah": [8.0]})
    assert "declare their reference a count on 8 Ah" in s and "drifts" not in s


@functools.cache
def _fade_diagnosis():
    case = draw_case(6, 123)  # a single hidden fade of 24 %, drive cycles
    assert tuple(case.effects) == ("capacity",) and case.kind == "single"
    return case, diagnose(case.base, case.fit, case.evals)


def test_the_diagnosis_reports_the_reference_count(tmp_path):
    case, d = _fade_diagnosis()
    rc = d.soc["reference_count"]
    fade = case.draws["capacity"]["fade"]
    assert rc["capacity_ah"] == pytest.approx(case.capacity_ah * (1.0 - fade), rel=Q_TOL)
    assert rc["model_capacity_ah"]["before"] == pytest.approx(d.base_model.params.capacity_ah)
    assert rc["declared_capacity_ah"] is None  # the benchmark's truth is no declared count
    write_report(d, tmp_path, with_figures=False)
    js = json.loads((tmp_path / "diagnosis.json").read_text())
    assert js["soc"]["reference_count"]["capacity_ah"] == pytest.approx(rc["capacity_ah"])
    assert reference_count_sentence(rc) in (tmp_path / "diagnosis.md").read_text()
