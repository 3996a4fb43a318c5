"""The residual diagnosis on data with one effect hidden in it (metadata silent), and its pieces.

The undeclared-effect cases cover several base models, loads, magnitudes and noise levels. Each runs the whole
diagnosis (base fit on the fit record, signatures, bounded fits on the training part, held-out judgement) with the
search capped at one step: what is judged is the first effect named and the error it removes on held-out data. The
stopping rule is judged by the cases without a hidden effect (nothing may be added) and the CLI case runs uncapped.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from socbench.cli import main
from socbench.diagnose import bin_average, diagnose, make_folds
from socbench.diagnose.search import rest_current
from socbench.diagnose.signatures import Trajectory, signatures
from socbench.diagnose.synthetic import cell, eval_current, hidden_case
from socbench.models import Constant, ModelParams, make_model
from socbench.models.effects import EFFECTS, augment, make_effect
from socbench.profile import Profile, ProfileMeta

DESIGN_KEYS = {"model", "effects_added", "before", "after", "candidates", "steps", "split"}


# ------------------------------------------------------------------------------------------------ pieces
def test_bin_average_keeps_the_charge_and_the_mean_voltage():
    rng = np.random.default_rng(3)
    t = np.arange(0, 600, 0.1)
    i = rng.uniform(-2, 5, t.size)
    v = 3.7 + 0.01 * rng.standard_normal(t.size)
    p = Profile(t, i, voltage_v=v)
    b = bin_average(p, 1.0)
    assert b.n == 600
    # the last bin lasts 0.9 s to the last sample (the last sample itself has no duration under the ZOH)
    assert b.amp_hours()[-1] + b.current_a[-1] * 0.9 / 3600 == pytest.approx(p.amp_hours()[-1], rel=1e-9)
    np.testing.assert_allclose(b.voltage_v[:5], v[:50].reshape(5, 10).mean(axis=1), rtol=1e-12)
    assert bin_average(b, 1.0) is b


def test_blocked_folds_score_every_sample_once_in_contiguous_blocks_of_equal_duration():
    t = np.r_[np.arange(0.0, 600.0), 600.0 + 10.0 * np.arange(240)]  # 1 s, then 10 s samples
    p = Profile(t, np.ones(t.size), voltage_v=np.full(t.size, 3.7))
    q = Profile(np.arange(0.0, 999.0), np.ones(999), voltage_v=np.full(999, 3.7))
    f = make_folds([p, q], 4)
    for prof, b in zip(f.records, f.blocks):
        assert b.min() == 0 and b.max() == 3 and np.all(np.diff(b) >= 0)  # contiguous, in time order
        starts = [prof.time_s[np.argmax(b == j)] - prof.time_s[0] for j in range(4)]
        np.testing.assert_allclose(starts, np.arange(4) * prof.duration_s / 4, atol=10.0)
    for j in range(4):  # fold j trains on everything but block j of every record
        for r in range(2):
            assert np.array_equal(f.train_mask(r, j), f.blocks[r] != j)
    d = f.describe()
    assert d["method"] == "blocked_cv" and d["folds"] == 4 and [x["n"] for x in d["records"]] == [840, 999]


def test_rest_current_reads_the_sensor_offset():
    t = np.arange(0.0, 3000.0)
    i = np.where((t % 1000) < 400, 2.0, 0.0) + 0.04
    p = Profile(t, i + np.random.default_rng(0).normal(0, 0.002, t.size), voltage_v=np.full(t.size, 3.7))
    mean, se, seconds = rest_current(p, 2.5)
    assert mean == pytest.approx(0.04, abs=5 * se + 1e-4) and seconds > 1500


def test_rest_current_reads_a_sub_step_offset_of_a_quantised_sensor():
    """A field current sensor with an ADC step of 1 % of 1C, dithered by noise of 0.5-1 step, reads a 0.15-0.5 %-of-1C
    offset at the rests: the plain median sticks to the zero level; the rest current (read through the dither,
    socbench.identify.hppc.reading_level) recovers the offset within three of its standard errors, in every one of
    20 random draws."""
    from socbench.identify.hppc import reading_level

    rng = np.random.default_rng(2611)
    for _ in range(20):
        q = float(np.exp(rng.uniform(np.log(2.0), np.log(40.0))))
        lsb, offset = 0.01 * q, float(rng.uniform(0.0015, 0.005) * q * rng.choice([-1.0, 1.0]))
        t = np.arange(0.0, 6 * 3600.0, float(rng.choice([1.0, 2.0, 5.0])))
        load = np.where((t % 3600.0) < 1800.0, q * rng.uniform(0.5, 1.5), 0.0)  # half-hour loads, half-hour rests
        raw = load + offset + rng.normal(0.0, rng.uniform(0.5, 1.0) * lsb, t.size)
        p = Profile(t, np.round(raw / lsb) * lsb, voltage_v=np.full(t.size, 3.7))
        rest = p.current_a[load == 0.0]
        assert np.median(rest) == 0.0 or abs(np.median(rest) - offset) > 0.3 * abs(offset)  # what the median read
        b, se, seconds = rest_current(p, q)
        assert abs(b - offset) <= 3 * se and se < 0.5 * abs(offset) and seconds > 2.5 * 3600
    x = np.random.default_rng(1).normal(0.02, 0.002, 999)  # not quantised: the plain median
    assert reading_level(x)[0] == np.median(x)


#: load that shows each effect's signature (ECM_SPEC §9)
SIGNATURE_LOADS = {
    "temperature": "pulses", "hysteresis": "pulses", "capacity": "pulses", "current_bias": "rests",
    "extra_rc": "pulses", "butler_volmer": "steps", "coulombic_efficiency": "cycling", "self_discharge": "rests",
}
#: current bias and self-discharge both drift SOC with elapsed time: the same regressor up to U(z)/U(1), told apart
#: by the rest current in the search, not by the signature
COLLINEAR = {"current_bias": {"self_discharge"}, "self_discharge": {"current_bias"}}


@pytest.mark.parametrize("effect", list(EFFECTS))
def test_the_hidden_effects_signature_explains_the_residual_best(effect):
    _, ev = hidden_case(effect, "thevenin", SIGNATURE_LOADS[effect], "large", v_sd=0.0)
    name, params = cell("thevenin")
    base = make_model(name, params)
    traj = Trajectory.simulate(base, ev, 0.95)
    bounds = {n: EFFECTS[n]().bounds(base) for n in EFFECTS}
    sigs = signatures(base, traj, bounds, 25.0)
    best = max(sigs, key=lambda n: sigs[n].r2)
    assert best == effect or best in COLLINEAR.get(effect, ()), {n: round(s.r2, 3) for n, s in sigs.items()}
    assert sigs[effect].r2 > 0.8


def test_signature_guess_recovers_the_hidden_parameter():
    _, ev = hidden_case("capacity", "thevenin", "pulses", "large", v_sd=0.0)
    base = make_model(*cell("thevenin"))
    traj = Trajectory.simulate(base, ev, 0.95)
    bounds = {n: EFFECTS[n]().bounds(base) for n in EFFECTS}
    assert signatures(base, traj, bounds, 25.0)["capacity"].guess["cap0"] == pytest.approx(1.3, abs=0.05)


def _aged_cell_eval(fade, growth, seed, v_sd=1e-3):
    """The synthetic Thevenin cell aged, built from its parameters (not from the capacity effect): the capacity
    faded by ``fade``, every resistance grown by ``1 + growth`` and the capacitance shrunk by it (SEI growth: the
    time constant unchanged); measured on the pulse load."""
    name, params = cell("thevenin")
    grown = {k: Constant(v.value * (1.0 + growth) if k.startswith("R") else v.value / (1.0 + growth))
             for k, v in params.values.items()}
    aged = make_model(name, ModelParams(params.capacity_ah * (1.0 - fade), params.ocv, grown))
    t, i = eval_current("pulses", seed=seed)
    sim = aged.simulate(Profile(t, i), soc0=0.95)
    v = sim.voltage_v + np.random.default_rng(seed).normal(0.0, v_sd, t.size)
    return Profile(t, i, voltage_v=v, temperature_c=np.full(t.size, 25.0), soc_ref=sim.soc,
                   meta=ProfileMeta(name="eval", source="eval", capacity_ah=params.capacity_ah))


@pytest.mark.parametrize("draw", range(3))
def test_an_aged_cell_is_named_capacity_with_its_resistance_growth(draw):
    """Ageing fades the capacity and grows the resistances together: the diagnosis that fits the capacity's
    resistance growth names the capacity alone, with its fade (``cap0 = 1/(1 − fade)``) and its growth recovered,
    and leaves nothing but the noise (fade-only, the search needs the base refit beside it)."""
    rng = np.random.default_rng(50 + draw)
    fade, growth = rng.uniform(0.08, 0.25), rng.uniform(0.15, 0.6)
    fit, _ = hidden_case(None, "thevenin", "pulses", v_sd=1e-3, seed=50 + draw)
    d = diagnose("thevenin", [fit], [_aged_cell_eval(fade, growth, 60 + draw)], soc=False, resistance_growth=True)
    # the capacity alone: no base refit took up the grown resistances
    assert [s.effect for s in d.steps] == ["capacity"], ([s.effect for s in d.steps], fade, growth)
    params = d.steps[0].params
    assert params["cap0"] == pytest.approx(1.0 / (1.0 - fade), abs=0.02), (params, fade)
    assert params["r_growth"] == pytest.approx(growth, abs=0.05 * (1.0 + growth)), (params, growth)
    assert d.after["rmse_v"] <= 1.5e-3  # within 1.5× the voltage noise: nothing of the ageing left


# ------------------------------------------------------------------------------------------------ hidden effects
#: (effect, base model, load, magnitude, voltage noise sd [V], current noise sd [A], seed)
HIDDEN_CASES = [
    ("temperature", "thevenin", "pulses", "small", 1e-3, 0.0, 0),
    ("hysteresis", "dp", "pulses", "small", 1e-3, 0.0, 1),
    ("capacity", "thevenin", "rests", "small", 2e-3, 0.0, 2),
    ("current_bias", "rint", "rests", "small", 1e-3, 0.0, 3),
    ("extra_rc", "rint", "pulses", "small", 1e-3, 0.0, 4),
    ("butler_volmer", "rint", "steps", "large", 3e-3, 0.0, 5),
    ("coulombic_efficiency", "thevenin", "cycling", "small", 1e-3, 0.005, 6),
    ("self_discharge", "thevenin", "rests", "small", 1e-3, 0.0, 7),
]


@pytest.mark.parametrize("case", HIDDEN_CASES, ids=[c[0] for c in HIDDEN_CASES])
def test_diagnosis_names_the_hidden_effect_and_cuts_the_held_out_error(case):
    effect, base, load, magnitude, v_sd, i_sd, seed = case
    fit, ev = hidden_case(effect, base, load, magnitude, v_sd=v_sd, i_sd=i_sd, seed=seed)
    assert effect not in fit.name + ev.name and not ev.meta.extra and not fit.meta.extra  # metadata silent
    d = diagnose(base, [fit], [ev], max_steps=1, soc=False)
    # a property the fit test shows is its first step, before any round (the extra branch on the Rint base)
    ranked = [c.effect for r in d.rounds[:1] for c in r["candidates"]]
    assert d.effects_added == [effect], ranked
    assert d.after["rmse_v"] <= 0.7 * d.before["rmse_v"]


def test_capacity_is_a_fade_an_soc_slower_than_counted_is_not_named_capacity():
    """The evaluation cell holds 8 % more charge than the fit test counted (``cap0 = 0.92``): no fade, and no capacity
    fitted below 1 in any round; the same record with a fade (``cap0 = 1.15``) names it (the unit case above)."""
    name, params = cell("thevenin")
    base = make_model(name, params)
    rng = np.random.default_rng(11)
    fit, _ = hidden_case(None, name, "rests", v_sd=1e-3, seed=11)
    t, i = eval_current("rests", seed=11)
    prof = Profile(t, i, temperature_c=np.full(t.size, 25.0))
    sim = augment(base, [make_effect("capacity", cap0=0.92)]).simulate(prof, soc0=0.95)
    ev = Profile(t, i, voltage_v=sim.voltage_v + rng.normal(0.0, 1e-3, t.size), temperature_c=prof.temperature_c,
                 soc_ref=np.clip(sim.soc, 0.0, 1.0), meta=ProfileMeta(name="eval", source="eval", capacity_ah=2.5))
    d = diagnose(name, [fit], [ev], soc=False)
    assert "capacity" not in d.effects_added, d.effects_added
    fitted = [c.params["cap0"] for r in d.rounds for c in r["candidates"] if c.effect == "capacity" and c.params]
    assert fitted and min(fitted) >= 1.0, fitted


@pytest.mark.parametrize("effect,base", [("extra_rc", "rint"), ("hysteresis", "dp")])
def test_the_compiled_fold_filters_give_the_numpy_references_soc_errors(effect, base, monkeypatch):
    """The held-out SOC errors from one compiled run per fold equal the batched numpy reference (a parameter batch of
    the folds, R per run), before and after the effect is added."""
    import socbench.diagnose.core as core

    fit, ev = hidden_case(effect, base, "pulses", "small", v_sd=1e-3, seed=4)
    used, original = [], core._compiled_fold_filters

    def spy(*args):
        out = original(*args)
        used.append(out is not None)
        return out

    monkeypatch.setattr(core, "_compiled_fold_filters", spy)
    compiled = diagnose(base, [fit], [ev], max_steps=1)
    assert compiled.effects_added  # the after-models are augmented, one parameter set per fold
    assert used and all(used)  # every filter of the diagnosis ran the compiled path
    monkeypatch.setattr(core, "_compiled_fold_filters", lambda *a, **k: None)
    reference = diagnose(base, [fit], [ev], max_steps=1)
    assert reference.effects_added == compiled.effects_added
    for key in ("before", "after"):
        for name in core.SOC_ESTIMATORS:
            got, want = (getattr(d, key)["soc"][name] for d in (compiled, reference))
            assert got["soc_rmse"] == pytest.approx(want["soc_rmse"], rel=1e-9, abs=1e-12)
            assert got["failed_runs"] == want["failed_runs"]


@pytest.mark.parametrize("base,load,seed", [("thevenin", "pulses", 8), ("dp", "steps", 9)])
def test_diagnosis_adds_nothing_when_nothing_is_hidden(base, load, seed):
    fit, ev = hidden_case(None, base, load, v_sd=1e-3, seed=seed)
    d = diagnose(base, [fit], [ev], soc=False)
    assert d.effects_added == [], [(c.effect, c.score, c.rmse_after) for c in d.rounds[0]["candidates"]]
    assert d.after["rmse_v"] == d.before["rmse_v"]


# ------------------------------------------------------------------------------------------------ CLI
def _write(profile, path):
    profile.to_frame().to_csv(path, index=False)
    path.with_suffix(".json").write_text(json.dumps({"name": path.stem, "capacity_ah": profile.meta.capacity_ah}))


def test_cli_writes_the_design_keys_and_reports_soc(tmp_path):
    fit, ev = hidden_case("butler_volmer", "rint", "steps", "large", v_sd=2e-3, seed=11)
    _write(fit, tmp_path / "fit.csv")
    _write(ev, tmp_path / "eval.csv")
    out = tmp_path / "out"
    rc = main(["diagnose", "--fit", str(tmp_path / "fit.csv"), "--eval", str(tmp_path / "eval.csv"),
               "--model", "rint", "--out", str(out)])
    assert rc == 0
    d = json.loads((out / "diagnosis.json").read_text())
    assert DESIGN_KEYS <= set(d)
    assert d["model"] == "rint" and d["effects_added"][0] == "butler_volmer"
    assert {"effect", "score", "evidence"} <= set(d["candidates"][0])
    assert {"effect", "rmse_v_before", "rmse_v_after", "params"} <= set(d["steps"][0])
    assert d["after"]["rmse_v"] < d["before"]["rmse_v"]
    # the data carry a true SOC: the EKF's held-out SOC error on the original and on the augmented model
    assert d["before"]["soc_rmse"] >= 0 and d["after"]["soc_rmse"] >= 0
    assert d["split"]["method"] == "blocked_cv" and d["before"]["soc"]["ukf"]["soc_rmse"] >= 0
    md = (out / "diagnosis.md").read_text()
    assert "butler_volmer" in md and "held-out" in md
    assert (out / "voltage.png").stat().st_size > 0 and list(out.glob("signature_1_butler_volmer.png"))


def test_cli_user_errors_exit_2(tmp_path, capsys):
    assert main(["diagnose", "--fit", str(tmp_path / "none.csv"), "--eval", str(tmp_path / "none.csv"),
                 "--model", "thevenin", "--out", str(tmp_path / "o")]) == 2
    assert main(["diagnose", "--fit", "x", "--eval", "y", "--model", "nosuchmodel", "--out", "o"]) == 2
    assert main(["diagnose", "--fit", "x", "--eval", "y", "--model", "rint", "--out", "o", "--effects", "magic"]) == 2
    err = capsys.readouterr().err
    assert "nosuchmodel" in err and "magic" in err


def test_augmented_result_is_a_model_the_estimators_run():
    from socbench.estimators import SensorNoise, make_estimator

    fit, ev = hidden_case("hysteresis", "thevenin", "pulses", "large", v_sd=1e-3, seed=12)
    m = augment(make_model(*cell("thevenin")), [make_effect("hysteresis", M=0.05, gamma=30.0, h0=1.0)])
    est = make_estimator("ekf", m, SensorNoise(voltage_sd=2e-3, current_sd=0.01)).run(ev, soc0=0.9)
    assert np.all(np.isfinite(est.soc)) and abs(est.soc[0, -1] - ev.soc_ref[-1]) < 0.05
