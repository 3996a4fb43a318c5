"""The diagnosis' base fit does not choose a fit whose RC branch is slower than its record
(socbench.identify.fit.branches_identified): such a branch only ramps with the charge moved, an OCV or capacity error
in disguise. Checked by handing fit_base a selection whose best-scoring setting carries such a branch."""

from __future__ import annotations

import dataclasses

import numpy as np

from socbench import loads
from socbench.diagnose import core
from socbench.diagnose.synthetic import eval_current
from socbench.identify.fit import branches_identified
from socbench.models import Constant, ModelParams, make_model, paper_ocv
from socbench.ocv import OCVCurve
from socbench.profile import Profile, ProfileMeta


def _records():
    q = 5.0
    pack = paper_ocv()
    params = ModelParams(q, OCVCurve(pack.soc, pack.voltage / 6.0, "paper pack OCV / 6"),
                         {"R0": Constant(0.006), "R1": Constant(0.004), "C1": Constant(20.0 / 0.004)})
    cell = make_model("thevenin", params)
    rng = np.random.default_rng(5)

    def measured(prof, soc0, name):
        sim = cell.simulate(prof, soc0=soc0)
        meta = ProfileMeta(name=name, source=name, capacity_ah=q, n_series=1)
        return Profile(prof.time_s, prof.current_a, voltage_v=sim.voltage_v + rng.normal(0.0, 1e-3, prof.n),
                       temperature_c=np.full(prof.n, 25.0), soc_ref=np.clip(sim.soc, 0.0, 1.0), meta=meta)

    t, i = eval_current("pulses", q, 5)
    return measured(loads.hppc(q, dt=2.0, rest_s=1800.0), 1.0, "hppc"), measured(Profile(t, i), 0.95, "eval")


def test_a_branch_slower_than_the_record_is_not_identified():
    hppc, _ = _records()
    params = ModelParams(5.0, paper_ocv(), {"R0": Constant(0.006), "R1": Constant(0.004), "C1": Constant(5000.0)})
    assert branches_identified(params, hppc.duration_s)  # τ = 20 s
    slow = params.replace(values={**params.values, "C1": Constant(100.0 * hppc.duration_s / 0.004)})
    assert not branches_identified(slow, hppc.duration_s)


def test_the_base_fit_passes_over_a_setting_whose_branch_is_slower_than_its_record(monkeypatch):
    hppc, ev = _records()
    real = core.select_fit
    doctored = {}

    def select_with_a_slow_branch(*args, **kwargs):
        sel = real(*args, **kwargs)
        # the worst-scoring setting gets a branch 100 × slower than the record and the best score
        worst = max(sel.scores, key=lambda k: np.mean(sel.scores[k]))
        f = sel.fits[worst]
        r1 = float(np.ravel(f.params.values["R1"](0.5))[0])
        vals = {**f.params.values, "C1": Constant(100.0 * hppc.duration_s / r1)}
        fits = {**sel.fits, worst: dataclasses.replace(f, params=f.params.replace(values=vals))}
        scores = {**sel.scores, worst: [0.0]}
        doctored["label"] = worst
        return dataclasses.replace(sel, fits=fits, scores=scores, chosen=worst)

    monkeypatch.setattr(core, "select_fit", select_with_a_slow_branch)
    base, info = core.fit_base("thevenin", [hppc], validation=[ev], refine_ocv=False)
    sel = info["selection"]
    assert sel["setting"] != doctored["label"]
    assert sel["chosen"] != f"constant, {doctored['label']}"
    assert sel["branch_slower_than_record"] == [f"constant, {doctored['label']}"]
    assert branches_identified(base.params, hppc.duration_s)
