"""The randomised benchmark's generator and scoring (socbench.diagnose.randomized), and the current-sensor evidence of
the effect search on field records shaped like its loads.

* the evaluation loads never run the cell past empty (a drive used to be cut only once below 25 %, so one more drive
  could take the cell to 0 % and its voltage to a fraction of a volt, a record no instrument delivers);
* a vehicle's stop (a small steady auxiliary current, below C/20, for a minute or two) is not a rest that measures
  the current sensor: the search reads no offset from such records, and reads the offset when there is one;
* the footprint of each hidden effect alone, and the rates by detectability.
"""

from __future__ import annotations

import numpy as np
import pytest

from socbench.diagnose.randomized import (
    FOOTPRINT_BINS,
    by_footprint,
    case_kind,
    draw_case,
    eval_current,
    footprint,
)
from socbench.diagnose.search import FIELD_REST_MIN_S, REST_OFFSET_C, rest_current
from socbench.profile import Profile


@pytest.mark.parametrize("kind", ["drive", "uav", "day"])
def test_evaluation_loads_keep_the_cell_above_empty(kind):
    lows = []
    for seed in range(12):
        rng = np.random.default_rng([99, seed])
        q = float(np.exp(rng.uniform(0.0, np.log(50.0))))
        dt = float(np.exp(rng.uniform(np.log(0.5), np.log(10.0))))
        _, i, _ = eval_current(rng, kind, q, dt)
        z = 0.98 - np.cumsum(i) * dt / (3600.0 * q)
        lows.append(float(z.min()))
    assert min(lows) >= 0.1 - 1e-9, lows  # the charge planned on the true capacity stops at 10 %


def _drive_record(seed: int, offset_c: float):
    """A drive record (stops with an auxiliary load, rests between drives) read by a sensor with ``offset_c``·C."""
    rng = np.random.default_rng([5, seed])
    q = float(rng.uniform(2.0, 30.0))
    dt = float(rng.uniform(0.5, 2.0))
    t, i, _ = eval_current(rng, "drive", q, dt)
    i_meas = i + offset_c * q + rng.normal(0.0, 0.003 * q, t.size)
    return Profile(t, i_meas, voltage_v=np.full(t.size, 3.7)), q


def test_field_rests_do_not_read_a_vehicles_stops_as_a_sensor_offset():
    wrong, seen = 0, 0
    for seed in range(10):
        p, q = _drive_record(seed, 0.0)
        r = rest_current(p, q, min_s=FIELD_REST_MIN_S)
        if r is None:
            continue
        seen += 1
        mean, se, _ = r
        wrong += abs(mean) > max(4.0 * se, q * REST_OFFSET_C)  # the search's rule for "the rests read an offset"
    assert seen >= 8 and wrong == 0
    # while every quiet spell of 30 s or more (the stops included) does read one, in most records
    short = [rest_current(*_drive_record(seed, 0.0)) for seed in range(10)]
    assert sum(abs(m) > max(4 * se, 5e-4 * q) for (m, se, _), (_, q) in
               zip(short, [_drive_record(s, 0.0) for s in range(10)])) >= 5


def test_field_rests_read_a_real_sensor_offset():
    for seed in range(6):
        p, q = _drive_record(seed, 0.01)
        mean, se, _ = rest_current(p, q, min_s=FIELD_REST_MIN_S)
        assert mean == pytest.approx(0.01 * q, abs=5 * se + 0.001 * q)


def test_each_hidden_effect_has_its_own_footprint():
    k = next(k for k in range(10) if case_kind(k)[0] == "pair")
    case = draw_case(k, 11)
    own = {n: footprint(case, only=n) for n in case.effects}
    both = footprint(case)
    assert all(v >= 0 for v in own.values()) and both > 0
    assert max(own.values()) > 0.2 * both  # one of the two carries a real share of what both add
    single = draw_case(next(k for k in range(10) if case_kind(k)[0] == "single"), 11)
    assert footprint(single, only=single.effects[0]) == pytest.approx(footprint(single), rel=1e-9)


def test_rates_by_detectability_put_each_case_in_its_footprint_class():
    res = [{"kind": "single", "effects": ["hysteresis"], "added": [], "first": None, "footprint": 0.4,
            "footprints": {"hysteresis": 0.4}, "rmse_before": 1.0, "rmse_after": 1.0},
           {"kind": "single", "effects": ["capacity"], "added": ["capacity"], "first": "capacity", "footprint": 9.0,
            "footprints": {"capacity": 9.0}, "rmse_before": 1.0, "rmse_after": 0.2},
           {"kind": "pair", "effects": ["capacity", "coulombic_efficiency"], "added": ["capacity"],
            "first": "capacity", "footprint": 9.0, "footprints": {"capacity": 8.0, "coulombic_efficiency": 2.0},
            "rmse_before": 1.0, "rmse_after": 0.3}]
    bins = by_footprint(res)
    assert [b["footprint"] for b in bins] == [label for _, _, label in FOOTPRINT_BINS]
    low, mid, high = bins
    assert low["named_first_single"] == {"n": 1, "hits": 0, "rate": 0.0}
    assert high["named_first_single"] == {"n": 1, "hits": 1, "rate": 1.0} and high["cut_30_single"]["hits"] == 1
    assert mid["named_in_pair"] == {"n": 1, "hits": 0, "rate": 0.0}
    assert high["named_in_pair"] == {"n": 1, "hits": 1, "rate": 1.0}
