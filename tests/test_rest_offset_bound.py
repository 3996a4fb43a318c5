"""A current-sensor offset the evaluation records' rests measure is fitted within what they measured
(socbench.diagnose.search: the bounds of ``current_bias`` are the rests' level ± 3 standard errors, ±
``REST_BOUND_C`` of 1C beside them).

Wider bounds let the offset take up another SOC drift the base model carries (a capacity a few per cent off: the
drift of a count from the wrong capacity reads like an offset while the cell discharges), and the diagnosis names an
offset the sensor does not have: with 0.05 % of 1C beside the 3 standard errors (until stop 65) the offset named here
lay 6.8–9.4 standard errors from the truth in 8 of 8 draws, every one at its bound; within the rests' own error,
2.1–4.9. Truth and instrument from tests/hppc_records.py (not socbench code): an HPPC of the cell
from full, and a field record of the same cell 3–5 % smaller (aged) with stretches of 1–2C between rests of
5–15 min, read by a current sensor with an offset of 0.1–0.4 % of 1C; the diagnosis may add the offset only."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from socbench.diagnose import diagnose, search
from socbench.profile import Profile, ProfileMeta

from . import hppc_records as H

DRAWS = 4


def draw(seed: int, fade: tuple = (0.95, 0.97), offset_c: tuple = (0.001, 0.004), i_noise_c: float = 0.003,
         i_lsb_c: float = 0.0):
    """``(fit record, field record, true offset [A], capacity [Ah])``: the field cell ``fade`` × the HPPC's capacity,
    its current sensor ``offset_c`` of 1C off (either sign), with white noise and an ADC step (shares of 1C)."""
    rng = np.random.default_rng([seed, 53])
    cell = H.Cell(float(rng.uniform(2.0, 20.0)), str(rng.choice(["nmc", "nca"])), 0.0, ())
    cell = dataclasses.replace(cell, r0=0.05 / cell.capacity_ah,
                               branches=((0.02 / cell.capacity_ah, float(rng.uniform(10.0, 40.0))),))
    q = cell.capacity_ah
    hppc = H.hppc_record(cell, H.Layout(), H.Instrument(dt=1.0, i_noise_c=0.002, v_noise=1e-3), seed=seed)
    aged = dataclasses.replace(cell, capacity_ah=q * float(rng.uniform(*fade)))
    segs, z = [(0.0, 600.0)], 0.95
    while z > 0.3:
        amps, secs = float(rng.uniform(1.0, 2.0)) * q, float(rng.uniform(300.0, 900.0))
        segs += [(amps, secs), (0.0, float(rng.uniform(300.0, 900.0)))]
        z -= amps * secs / 3600.0 / aged.capacity_ah
    seg_i = np.array([a for a, _ in segs])
    seg_t0 = np.concatenate([[0.0], np.cumsum([s for _, s in segs])[:-1]])
    t = np.arange(0.0, seg_t0[-1] + segs[-1][1], 2.0)
    cur, soc, _, v = H._solve(aged, seg_i, seg_t0, t, soc0=0.95)
    offset = float(rng.uniform(*offset_c)) * q * float(rng.choice([-1.0, 1.0]))
    ins = H.Instrument(dt=2.0, i_noise_c=i_noise_c, i_offset_c=offset / q, i_lsb_c=i_lsb_c, v_noise=1e-3)
    i_meas, v_meas = H._measure(t, cur, v, ins, q, np.random.default_rng([seed, 54]))
    field = Profile(t, i_meas, voltage_v=v_meas, soc_ref=np.clip(soc, 0.0, 1.0),
                    meta=ProfileMeta(name="field", source="field", capacity_ah=q))
    return hppc.profile, field, offset, q


@pytest.mark.parametrize("seed", range(DRAWS))
def test_a_measured_offset_is_fitted_within_what_the_rests_read(seed):
    fit, field, offset, q = draw(seed)
    level, se, _ = search.rest_current(field, q, min_s=search.FIELD_REST_MIN_S)
    assert abs(level - offset) <= 3.0 * se + 0.0002 * q  # the rests read the truth
    d = diagnose("thevenin", [fit], [field], candidates=["current_bias"], soc=False)
    assert d.effects_added == ["current_bias"]
    b0 = next(s for s in d.steps if s.effect == "current_bias").params["b0"]
    # the rests' own error (3 se, the first assertion) and the bounds' (3 se): the offset the sensor has
    assert abs(b0 - offset) <= 6.0 * se, (b0, offset, se)


@pytest.mark.parametrize("seed", range(2))
def test_an_offset_an_undithered_adc_reads_as_one_level_is_not_pinned_to_that_level(seed):
    """A noise-free current read in 0.5 %-of-1C steps: each rest reads the one level nearest the offset (0.3–0.45 %
    of 1C reads 0.5 %), with no scatter to give it a standard error. The offset is known to the step, not to the level:
    the bounds stand on the step over √12 (pinned to the level, the offset named would be the level's, 0.05–0.2 % of
    1C off), and the voltage (the field cell is the HPPC's own) places it nearer the truth than the level."""
    step = 0.005
    fit, field, offset, q = draw(seed, fade=(1.0, 1.0), offset_c=(0.003, 0.0045), i_noise_c=0.0, i_lsb_c=step)
    level, se, _ = search.rest_current(field, q, min_s=search.FIELD_REST_MIN_S)
    assert se == 0.0 and abs(level) == pytest.approx(step * q)  # one level, no scatter
    d = diagnose("thevenin", [fit], [field], candidates=["current_bias"], soc=False)
    assert d.effects_added == ["current_bias"]
    b0 = next(s for s in d.steps if s.effect == "current_bias").params["b0"]
    assert abs(b0 - offset) < 0.95 * abs(level - offset), (b0, offset, level)
