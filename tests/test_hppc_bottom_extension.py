"""An HPPC that stops under load at its cut-off (no rest at the bottom, as the ORNL Leaf HPPC does) gets its OCV
continued from the lowest rest point down to its most discharged point (:attr:`socbench.identify.hppc.HPPCAnalysis.
ocv_bottom_extension`), not along the straight line through its two lowest points, which misses the knee at empty by
hundreds of mV.

Randomised over the tests' own generator (``tests/hppc_records.py``: cell, layout, instrument), the last step run to
empty under load. Measured along that last step, where a record running as low reads the curve: the OCV the analysis
gives at each sample's SOC against the truth's at the sample's true SOC.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from socbench.identify.hppc import analyze_hppc
from socbench.ocv import OCVCurve, monotone_points

from . import hppc_records as H

DRAWS = 12


def _draw(seed: int, under_load: bool):
    _, cell, lay, ins = H.random_setup(seed)
    lay = dataclasses.replace(lay, stop_under_load=under_load, stop_soc=0.0, gaps=False)
    rec = H.hppc_record(cell, lay, ins, seed=seed + 1, with_soc_ref=False)
    return rec, analyze_hppc(rec.profile)


@pytest.mark.parametrize("seed", range(200, 200 + DRAWS))
def test_the_ocv_follows_the_knee_below_the_lowest_rest_point(seed):
    rec, a = _draw(seed, under_load=True)
    assert a.ocv_bottom_extension is not None
    z_bot, z_lo = a.ocv_bottom_extension
    assert z_bot < z_lo
    last = (a.soc <= z_lo) & (np.arange(a.soc.size) >= a.start_index)  # the last step, below the lowest rest point
    truth = rec.cell.ocv(rec.soc_true[last])
    extended = a.ocv()(a.soc[last]) - truth
    line = OCVCurve(*monotone_points(a.ocv_soc, a.ocv_voltage))(a.soc[last]) - truth  # the rest points alone

    def rms(e):
        return float(np.sqrt(np.mean(e * e)))

    assert rms(extended) <= 0.8 * rms(line), (rms(extended), rms(line))
    assert np.max(np.abs(extended)) <= 0.5 * np.max(np.abs(line)), (np.max(np.abs(extended)), np.max(np.abs(line)))


@pytest.mark.parametrize("seed", range(200, 204))
def test_a_test_that_rests_at_its_bottom_keeps_its_rest_point_as_the_end(seed):
    _, a = _draw(seed, under_load=False)
    assert a.bottom_point is None and a.ocv_bottom_extension is None
    z, v = monotone_points(a.ocv_soc, a.ocv_voltage)
    np.testing.assert_array_equal(a.ocv().soc, z)
