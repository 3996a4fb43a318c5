"""An evaluation record with a logging gap the current does not bridge (socbench.diagnose.data.split_at_gaps).

The records are tests/hppc_records.py's (a generator independent of the diagnosis): the issue's HPPC of a two-branch
cell to fit a Thevenin base on, and a two-hour drive of the same cell whose logger paused for 5–15 minutes while the
cell was driven, with the reference SOC on both sides of the pause. Across it the zero-order hold carries the last
sample's current, so the diagnosis simulated the rest of the record from a SOC several points off.
"""

from __future__ import annotations

import numpy as np
import pytest

import socbench.diagnose.core as core
from socbench.diagnose import diagnose
from socbench.profile import Profile, ProfileMeta

from . import hppc_records as H


def _gapped_drive(seed: int) -> Profile:
    rng = np.random.default_rng(seed)
    ins = H.Instrument(dt=1.0, i_noise_c=0.003, v_noise=1e-3)
    d = H.drive_record(H.ISSUE_CELL, ins, seed=100 + seed, duration_s=7200).profile
    a = rng.uniform(1500.0, 4500.0)
    keep = (d.time_s < a) | (d.time_s > a + rng.uniform(300.0, 900.0))
    return Profile(d.time_s[keep], d.current_a[keep], voltage_v=d.voltage_v[keep], soc_ref=d.soc_ref[keep],
                   meta=ProfileMeta(name="gapped", source="gapped"))


@pytest.mark.slow
def test_a_record_cut_at_its_gap_names_the_missing_branch_alone(monkeypatch):
    """Cut at the gap, each piece starting from its own reference SOC, the diagnosis names the branch the Thevenin
    base lacks and nothing else, and ends under half the error of the same diagnosis on the record kept whole, in
    every draw (measured, seeds 0–4: 3–6.5 mV against 15–93 mV; kept whole it named a capacity fade or a
    self-discharge beside the branch in three draws and nothing in two)."""
    for seed in range(3):
        hppc, record = H.issue_record(seed=seed).profile, _gapped_drive(seed)
        cut = diagnose("thevenin", [hppc], [record], soc=False)
        notes = cut.fit.get("evaluation_records_cut", [])
        assert len(notes) == 1 and notes[0].startswith("gapped: cut into 2 at 1 gap"), notes
        assert [r.name for r in cut.split.records] == ["gapped [1/2]", "gapped [2/2]"]
        assert cut.effects_added == ["extra_rc"], (seed, cut.effects_added)
        with monkeypatch.context() as m:
            m.setattr(core, "split_at_gaps", lambda profiles, model: (list(profiles), []))
            whole = diagnose("thevenin", [hppc], [record], soc=False)
        assert "evaluation_records_cut" not in whole.fit
        assert cut.after["rmse_v"] < 0.5 * whole.after["rmse_v"], (seed, cut.after["rmse_v"], whole.after["rmse_v"])


def test_a_record_without_a_gap_is_kept_whole():
    from socbench.diagnose.data import split_at_gaps
    from socbench.identify import fit_model
    from socbench.models import make_model

    hppc = H.issue_record(seed=0).profile
    model = make_model("thevenin", fit_model("thevenin", hppc, mode="constant").params)
    drive = H.drive_record(H.ISSUE_CELL, H.Instrument(dt=1.0, i_noise_c=0.003, v_noise=1e-3), seed=1).profile
    records, notes = split_at_gaps([drive], model)
    assert records[0] is drive and notes == []
    records, notes = split_at_gaps([_gapped_drive(0)], model)
    assert len(records) == 2 and len(notes) == 1
    assert records[1].soc_ref[0] == pytest.approx(_gapped_drive(0).soc_ref[records[0].n])  # from its own reference
