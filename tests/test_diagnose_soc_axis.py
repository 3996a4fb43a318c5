"""The diagnosis scores its SOC filters on the record's own SOC axis.

A measured record's reference SOC is often a count from full with a capacity of its own (Panasonic: the charge the
cell delivers at the record's temperature, smaller in the cold; ``meta.extra["soc_ref_capacity_ah"]``), while the
filters run on the model's axis (the fit test's capacity). :mod:`socbench.socaxis` converts between the two, and the
held-out SOC errors the diagnosis reports (:func:`socbench.diagnose.core.soc_errors`) are on the record's axis, as
``socbench estimate`` reports them. Scored on the model's axis, an exact count of the charge would read an error of
``(1 − z)·(Q_ref/Q_data − 1)``.

Randomised: each draw takes a base structure, a load, a start SOC and the ratio ``Q_ref/Q_data`` (1.05–1.35: what
0 to −20 °C take off an NCA cell's delivered charge in the Panasonic data).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from socbench.diagnose import make_folds
from socbench.diagnose.core import IGNORE_VOLTAGE, soc_errors
from socbench.diagnose.search import initial_soc
from socbench.diagnose.synthetic import cell, eval_current
from socbench.models import make_model
from socbench.profile import Profile, ProfileMeta
from socbench.socaxis import REFERENCE_CAPACITY_KEY, SocAxis

DRAWS = 8


def _draw(seed: int):
    rng = np.random.default_rng([2611, seed])
    base, params = cell(str(rng.choice(["thevenin", "dp"])))
    model = make_model(base, params)
    t, i = eval_current(str(rng.choice(["pulses", "rests", "steps"])), seed=seed)
    z0 = float(rng.uniform(0.8, 1.0))
    prof = Profile(t, i, temperature_c=np.full(t.size, 25.0))
    sim = model.simulate(prof, soc0=z0)
    v = sim.voltage_v + rng.normal(0.0, 2e-3, t.size)
    i_meas = i + rng.normal(0.0, 0.005 * params.capacity_ah, t.size)
    meta = ProfileMeta(name="eval", source="eval", capacity_ah=params.capacity_ah)
    on_model = Profile(t, i_meas, voltage_v=v, temperature_c=prof.temperature_c, soc_ref=sim.soc, meta=meta)
    axis = SocAxis(params.capacity_ah, params.capacity_ah / float(rng.uniform(1.05, 1.35)))
    on_data = on_model.with_(soc_ref=axis.to_data(sim.soc), meta=dataclasses.replace(
        meta, extra={REFERENCE_CAPACITY_KEY: axis.data_capacity_ah}))
    return model, axis, on_model, on_data


def _soc_rmse(model, profile, voltage_sd):
    folds = make_folds([profile], 4)
    soc0s = [initial_soc(model, p) for p in folds.records]
    out = soc_errors(lambda layout, fold=None: (model, None), folds, soc0s, np.full(folds.k, voltage_sd))
    return {name: r["soc_rmse"] for name, r in out.items()}


@pytest.mark.parametrize("seed", range(DRAWS))
def test_a_reference_counted_with_the_records_capacity_is_scored_on_its_axis(seed):
    model, axis, on_model, on_data = _draw(seed)
    # the same filter run, scored on either axis: the data's SOC error is the model's × Q_ref/Q_data
    got, want = _soc_rmse(model, on_data, 2e-3), _soc_rmse(model, on_model, 2e-3)
    for name in want:
        assert got[name] == pytest.approx(axis.ratio * want[name], rel=1e-6), name
    # counting the current alone (the voltage ignored) is the reference's own count: no error on its axis (on the
    # model's axis the same count would read (1 − z)·(Q_ref/Q_data − 1), several points here)
    counted = _soc_rmse(model, on_data, IGNORE_VOLTAGE * 2e-3)
    z = on_model.soc_ref
    offset = float(np.sqrt(np.mean(((1.0 - z) * (axis.ratio - 1.0)) ** 2)))
    assert offset > 0.01
    for name, e in counted.items():
        assert e < 0.1 * offset, (name, e, offset)
