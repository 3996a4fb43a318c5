"""socbench.identify.hppc.analyze_hppc keeps the analyses of the records it analysed last, and reads a rest's end
voltage only where it uses it: neither may change what the analysis says."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from socbench.errors import DataError
from socbench.identify import hppc
from tests import hppc_records as H


@pytest.fixture
def counted(monkeypatch):
    """Counts the analyses actually run (the memo's misses); the memo starts empty."""
    monkeypatch.setattr(hppc, "_MEMO", type(hppc._MEMO)())
    calls = []
    inner = hppc._analyze_with_ladder

    def run(*args):
        calls.append(args)
        return inner(*args)

    monkeypatch.setattr(hppc, "_analyze_with_ladder", run)
    return calls


def _fields(a: hppc.HPPCAnalysis) -> str:
    return repr(dataclasses.astuple(a))


def test_a_record_analysed_again_is_not_analysed_again_and_reads_the_same(counted):
    rec = H.random_hppc(3).profile
    first = hppc.analyze_hppc(rec)
    fresh = hppc._analyze_with_ladder(rec, None, None, None, hppc.MIN_OCV_REST_S, None)
    assert _fields(first) == _fields(fresh)  # what the memo returns is what the analysis gives
    again = hppc.analyze_hppc(rec.with_())  # another object holding the same samples and metadata
    assert again is first and len(counted) == 2  # the direct call above, and the first analysis
    with pytest.raises(ValueError):
        first.soc[0] = 0.5  # shared by every caller: read-only


def test_anything_the_analysis_reads_is_in_the_key(counted, monkeypatch):
    rec = H.random_hppc(4).profile
    base = hppc.analyze_hppc(rec)
    variants = [
        lambda: hppc.analyze_hppc(rec.with_(voltage_v=rec.voltage_v + 1e-3)),  # the samples
        lambda: hppc.analyze_hppc(rec.with_(meta=dataclasses.replace(rec.meta, extra={"soc_ref_capacity_ah": 2.0}))),
        lambda: hppc.analyze_hppc(rec, capacity_ah=1.1 * base.capacity_ah),  # an argument
        lambda: hppc.analyze_hppc(rec, soc_start=0.9),
    ]
    for k, run in enumerate(variants):
        run()
        assert len(counted) == 2 + k, k
    monkeypatch.setattr(hppc, "MIN_PULSE_S", 2.0 * hppc.MIN_PULSE_S)  # a setting of the module
    hppc.analyze_hppc(rec)
    assert len(counted) == 2 + len(variants)


def test_a_record_refused_is_refused_again_with_the_same_line(counted):
    rec = H.drive_record(H.ISSUE_CELL, H.Instrument(dt=1.0, i_noise_c=0.003, v_noise=1e-3), seed=2).profile
    msgs = []
    for _ in range(2):
        with pytest.raises(DataError) as e:
            hppc.analyze_hppc(rec)
        msgs.append(str(e.value))
    assert msgs[0] == msgs[1] and msgs[0].startswith(rec.meta.source or rec.meta.name) and len(counted) == 1


@pytest.mark.parametrize("seed", range(6))
def test_every_rest_carries_its_end_voltage(seed):
    """The end voltages read only where used are filled in for every rest of the analysis returned."""
    rec = H.random_hppc(seed).profile
    a = hppc._analyze_with_ladder(rec, None, None, None, hppc.MIN_OCV_REST_S, None)
    t, v = rec.time_s, rec.voltage_v
    got = np.array([r.v_end for r in a.rests])
    want = np.array([hppc._rest_end_voltage(t, v, r.start, r.stop, r.duration_s) for r in a.rests])
    assert got.size > 0 and np.array_equal(got, want)
