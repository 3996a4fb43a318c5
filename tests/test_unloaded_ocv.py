"""A one-branch slow test at C/4–C/10 as the OCV (socbench.identify.unloaded_ocv, diagnose.core.split_fit_records) and
the SOC axis of a model with a fitted fade (socbench.socaxis.soc_capacity), on records of the independent generator
(tests/hppc_records.py: exact continuous-time cells, not socbench's models)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from socbench.diagnose.core import diagnose, split_fit_records
from socbench.errors import DataError
from socbench.identify.hppc import ocv_from_slow_test
from socbench.identify.unloaded_ocv import unloaded_branch
from socbench.models import make_model
from socbench.models.effects import augment, make_effect
from socbench.models.params import Constant, ModelParams
from socbench.profile import Profile, ProfileMeta
from socbench.socaxis import REFERENCE_CAPACITY_KEY, soc_axis, soc_capacity
from tests.hppc_records import Instrument, _solve, hppc_record, random_cell, random_layout

DRAWS = range(20)


def capacity_check(cell, c_rate: float, dt: float, rng, v_noise: float = 1e-3, reference_ah: float | None = None):
    """A capacity check of ``cell``: 20 min at rest at full, a discharge at ``c_rate`` to 2 % SOC, 20 min at rest;
    sampled every ``dt`` s at a random phase, the voltage with white noise. ``reference_ah``: a reference SOC counted
    from full with that capacity (and recorded as the reference's capacity)."""
    q = cell.capacity_ah
    i_dis = c_rate * q
    t_dis = 0.98 * q * 3600.0 / i_dis
    seg_i, seg_t0 = np.array([0.0, i_dis, 0.0]), np.array([0.0, 1200.0, 1200.0 + t_dis])
    t = np.arange(rng.uniform(0.0, dt), 2400.0 + t_dis, dt)
    cur, soc, _, v = _solve(cell, seg_i, seg_t0, t)
    v = v + rng.normal(0.0, v_noise, t.size)
    extra, ref = {}, None
    if reference_ah is not None:
        ah = np.concatenate([[0.0], np.cumsum(cur[:-1] * np.diff(t))]) / 3600.0
        ref, extra = np.clip(1.0 - ah / reference_ah, 0.0, 1.0), {REFERENCE_CAPACITY_KEY: reference_ah}
    meta = ProfileMeta(name="capacity-check", source="capacity-check", capacity_ah=q, n_series=1, extra=extra)
    return Profile(t, cur, v, None, ref, meta), soc


def truth_params(cell, ocv) -> ModelParams:
    """The cell's own resistances and time constants (a dp where it has two branches) on the curve ``ocv``."""
    values = {"R0": Constant(cell.r0)}
    for k, (r, tau) in enumerate(cell.branches, start=1):
        values[f"R{k}"], values[f"C{k}"] = Constant(r), Constant(tau / r)
    return ModelParams(cell.capacity_ah, ocv, values)


def test_unloading_a_c5_branch_removes_the_over_potential():
    """The discharge branch of a C/4–C/10 test lies I·(R0 + ΣR) below the OCV; freed of the over-potential of the
    cell's own model (its true resistances: this checks the unloading, not a fit), the curve's median distance from
    the true OCV over SOC 0.15–0.95 (past the branches' first transient, above the knee) is under a fifth of that
    gap, in every draw (the branch's own SOC axis, counted over the charge the test moved, differs a little from the
    cell's)."""
    shrunk = []
    for seed in DRAWS:
        rng = np.random.default_rng(7000 + seed)
        cell = random_cell(rng)
        test, _ = capacity_check(cell, float(rng.uniform(0.1, 0.25)), float(rng.uniform(10.0, 60.0)), rng)
        branch = ocv_from_slow_test(test).discharge
        model = "thevenin" if len(cell.branches) == 1 else "dp"
        fit = SimpleNamespace(name=model, params=truth_params(cell, branch))
        curve, eta = unloaded_branch(fit, test)
        z = np.linspace(0.15, 0.95, 81)
        left = np.median(np.abs(curve.value(z) - cell.ocv.value(z)))
        expected = test.current_a.max() * (cell.r0 + sum(r for r, _ in cell.branches))
        assert eta == pytest.approx(expected, rel=0.2), (seed, eta, expected)
        shrunk.append(left / expected)
    assert max(shrunk) < 0.2, np.round(shrunk, 3)


def test_two_fit_records_a_c5_test_beside_a_dynamic_one_is_the_slow_test():
    """Of two fit records, a C/5 discharge beside an HPPC is the slow test; alone it stays a dynamic record, and two
    records neither of them slow are refused by the diagnosis' base fit as before."""
    rng = np.random.default_rng(3)
    cell = random_cell(rng)
    check, _ = capacity_check(cell, 0.2, 30.0, rng)
    hppc = hppc_record(cell, random_layout(rng), Instrument(dt=1.0, v_noise=1e-3), seed=4).profile
    slow, dynamic = split_fit_records([check, hppc])
    assert slow == [check] and dynamic == [hppc]
    assert split_fit_records([check]) == ([], [check])
    slow, dynamic = split_fit_records([hppc, hppc.with_(meta=hppc.meta)])
    assert slow == [] and len(dynamic) == 2
    with pytest.raises(DataError, match="one dynamic fit record"):
        diagnose("thevenin", [hppc, hppc.with_(meta=hppc.meta)], [check], soc=False)


def test_soc_capacity_of_a_fitted_fade():
    """A model with a capacity effect counts the SOC of the faded cell: ``Q/cap0``; a parameter set carrying the
    effect the same; without one, the set's capacity."""
    rng = np.random.default_rng(5)
    cell = random_cell(rng)
    params = truth_params(cell, cell.ocv)
    base = make_model("thevenin" if len(cell.branches) == 1 else "dp", params)
    cap0 = float(rng.uniform(1.05, 1.3))
    faded = augment(base, [make_effect("capacity", cap0=cap0)])
    assert soc_capacity(base) == pytest.approx(cell.capacity_ah)
    assert soc_capacity(faded) == pytest.approx(cell.capacity_ah / cap0)
    with_effect = ModelParams(params.capacity_ah, params.ocv, params.values,
                              effects=({"name": "capacity", "values": {"cap0": cap0, "r_growth": 0.0}},))
    assert soc_capacity(with_effect) == pytest.approx(cell.capacity_ah / cap0)
    check, _ = capacity_check(cell, 0.2, 30.0, rng, reference_ah=cell.capacity_ah / cap0)
    assert soc_axis(faded, check).identity


@pytest.mark.parametrize("draw", range(4))
def test_a_fade_on_a_counted_reference_is_named_and_the_soc_is_not_worse(draw):
    """A cell (NMC- or NCA-like OCV) characterised fresh (a C/5 capacity check and an HPPC), evaluated on a capacity
    check of the same cell faded 6–20 %, whose reference SOC is counted with the charge that check delivers (the faded
    capacity): the fade is named within 1.5 points of the truth, and neither filter's SOC error grows (before the fix
    of the SOC axis the fitted fade was taken off twice: a correct fade made the SOC several points worse)."""
    rng = np.random.default_rng(9100 + draw)
    cell = random_cell(rng)
    # a sloped OCV: on LFP's plateau a fade shows only at the knee (docs/foreign_effects.md measures that case)
    cell = type(cell)(cell.capacity_ah, str(rng.choice(["nmc", "nca"])), cell.r0, cell.branches)
    fade = float(rng.uniform(0.06, 0.2))
    fresh, _ = capacity_check(cell, 0.2, 30.0, rng)
    hppc = hppc_record(cell, random_layout(rng), Instrument(dt=1.0, v_noise=1e-3), seed=draw).profile
    aged = type(cell)(cell.capacity_ah * (1.0 - fade), cell.ocv_shape, cell.r0, cell.branches)
    check, _ = capacity_check(aged, 0.2, 30.0, rng, reference_ah=aged.capacity_ah)
    check = check.with_(meta=ProfileMeta(name="aged", source="aged", capacity_ah=cell.capacity_ah, n_series=1,
                                         extra=check.meta.extra))
    d = diagnose("dp", [fresh, hppc], [check])
    assert "capacity" in d.effects_added, d.effects_added
    cap0 = next(s.params["cap0"] for s in d.steps if s.effect == "capacity")
    assert abs((1.0 - 1.0 / cap0) - fade) < 0.015, (cap0, fade)
    for name in ("ekf", "ukf"):
        assert d.after["soc"][name]["soc_rmse"] <= d.before["soc"][name]["soc_rmse"] + 0.002, (d.before, d.after)


def test_a_faded_model_starts_the_filters_at_the_same_soc_on_its_own_axis():
    """A record that starts part charged, its reference counted with the faded cell's capacity: the start handed to
    the filters on the parameter set's axis is converted to the faded model's axis, the reference's own SOC there."""
    from socbench.diagnose.core import _start_on_axis

    rng = np.random.default_rng(11)
    cell = random_cell(rng)
    cap0 = 1.25
    base = make_model("thevenin" if len(cell.branches) == 1 else "dp", truth_params(cell, cell.ocv))
    faded = augment(base, [make_effect("capacity", cap0=cap0)])
    check, _ = capacity_check(cell, 0.2, 30.0, rng, reference_ah=cell.capacity_ah / cap0)
    part = check.with_(soc_ref=np.clip(check.soc_ref - 0.2, 0.0, 1.0))  # starts at 0.8 of the faded cell
    z0_base = float(soc_axis(base, part).to_model(part.soc_ref[0]))
    assert z0_base == pytest.approx(1.0 - 0.2 / cap0)
    assert _start_on_axis(z0_base, faded, part) == pytest.approx(0.8)
    assert _start_on_axis(z0_base, base, part) == z0_base


def test_the_diagnosed_model_file_runs_in_estimate(tmp_path):
    """`socbench diagnose` writes the final model as a parameter file (model.json: the base as refitted, the fade in
    its ``effects``, the noise recipe's model error measured on the evaluation record); `socbench estimate --params`
    runs it on the aged record, and its SOC error there is lower than the same file's without the effect."""
    import json
    import subprocess
    import sys

    from tests.hppc_records import write_canonical

    rng = np.random.default_rng(9200)
    cell = random_cell(rng)
    cell = type(cell)(cell.capacity_ah, "nmc", cell.r0, cell.branches)
    fresh, _ = capacity_check(cell, 0.2, 30.0, rng)
    hppc = hppc_record(cell, random_layout(rng), Instrument(dt=1.0, v_noise=1e-3), seed=3).profile
    aged = type(cell)(cell.capacity_ah * 0.85, cell.ocv_shape, cell.r0, cell.branches)
    check, _ = capacity_check(aged, 0.2, 30.0, rng, reference_ah=aged.capacity_ah)
    files = [write_canonical(p, tmp_path / f"{n}.csv") for p, n in ((fresh, "fresh"), (hppc, "hppc"))]
    ev = write_canonical(check.with_(meta=ProfileMeta(name="aged", source="aged", capacity_ah=cell.capacity_ah,
                                                      n_series=1)), tmp_path / "aged.csv")
    sidecar = json.loads(ev.with_suffix(".json").read_text())
    ev.with_suffix(".json").write_text(json.dumps({**sidecar, REFERENCE_CAPACITY_KEY: aged.capacity_ah}))

    def cli(*args):
        done = subprocess.run([sys.executable, "-m", "socbench.cli", *map(str, args)], capture_output=True,
                              text=True, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        return done

    cli("diagnose", "--fit", *files, "--eval", ev, "--model", "dp", "--out", tmp_path / "out", "--no-figures")
    saved = json.loads((tmp_path / "out" / "model.json").read_text())
    assert [e["name"] for e in saved["effects"]] == ["capacity"]
    assert saved["model_error"]["measured_on"] == "identification"  # measured on the evaluation record, in sample
    assert 1.0 - 1.0 / saved["effects"][0]["values"]["cap0"] == pytest.approx(0.15, abs=0.015)
    without = tmp_path / "without.json"
    without.write_text(json.dumps({**saved, "effects": []}))
    rmse = {}
    for name, params in (("with", tmp_path / "out" / "model.json"), ("without", without)):
        done = cli("estimate", "--data", ev, "--params", params, "--estimator", "ekf", "--out", tmp_path / name)
        rmse[name] = json.loads((tmp_path / name / "metrics.json").read_text())["soc_rmse"]
        # its model error is in sample, and it says on which records; `fit`'s advice (refit with --validation) is
        # not an option for a diagnosed model
        assert "`socbench diagnose` fitted its effects on (aged), in sample" in done.stderr, done.stderr
        assert "--validation" not in done.stderr, done.stderr
    assert rmse["with"] < 0.5 * rmse["without"], rmse


def test_every_effect_round_trips_through_the_model_file(tmp_path):
    """``final_params`` of a model with any one effect of the catalogue saves and loads back to a model that runs the
    same open loop (settings such as a temperature's reference or a hysteresis branch kept)."""
    from socbench.diagnose.report import final_params
    from socbench.models.effects import EFFECTS
    from socbench.models.params import load_params, save_params

    rng = np.random.default_rng(13)
    cell = random_cell(rng)
    base = make_model("thevenin", ModelParams(cell.capacity_ah, cell.ocv, {
        "R0": Constant(cell.r0), "R1": Constant(cell.branches[0][0]),
        "C1": Constant(cell.branches[0][1] / cell.branches[0][0])}))
    test, _ = capacity_check(cell, 0.5, 30.0, rng)
    test = test.with_(temperature_c=np.linspace(10.0, 30.0, test.n))
    for name in EFFECTS:
        model = augment(base, [make_effect(name)])
        diag = SimpleNamespace(final_model=model, model="thevenin")
        path = tmp_path / f"{name}.json"
        save_params(path, "thevenin", final_params(diag))
        loaded_name, params = load_params(path)
        again = make_model(loaded_name, params)
        assert [e.name for e in again.effects] == [name]
        a = model.simulate(test, soc0=1.0).voltage_v
        b = again.simulate(test, soc0=1.0).voltage_v
        assert np.allclose(a, b, atol=1e-9), name
