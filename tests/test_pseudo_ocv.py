"""The OCV refined between an HPPC's rest points from its step segments (socbench.identify.pseudo_ocv).

Records come from tests/hppc_records.py (a continuous-time truth with hand-drawn OCV shapes, random layouts and
instruments), not from socbench's own generators; the refined curve is judged by what it is for: the voltage the
fitted model predicts on another record of the same cell (a drive cycle it was not fitted on)."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pytest

from socbench.diagnose.core import fit_base
from socbench.identify import fit_model, pseudo_ocv, validation_rmse
from socbench.identify.fit import branch_time_constants
from socbench.identify.pseudo_ocv import REFIT_GAIN, VALIDATION_GAIN, refine_ocv
from socbench.profile import Profile

from . import hppc_records as H

REPO = Path(__file__).resolve().parents[1]

#: randomised draws of cell, layout and instrument (seeds the development of the module did not look at: it was
#: measured on seeds 0–29: better in 26 of 30 draws, median RMSE ratio 0.54 NMC, 0.40 NCA, 0.66 LFP)
SEEDS = range(300, 312)


def _drive(rec: H.Record, seed: int):
    """A 40-minute drive of the same cell from a random SOC in [0.6, 0.95] (it stays inside the HPPC's range)."""
    z0 = float(np.random.default_rng(seed).uniform(0.6, 0.95))
    return H.drive_record(rec.cell, H.Instrument(dt=1.0, v_noise=1e-3), seed=seed, duration_s=2400.0, soc0=z0).profile


def _base(rec: H.Record) -> str:
    return "dp" if len(rec.cell.branches) == 2 else "thevenin"


@pytest.fixture(scope="module")
def draws():
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed in SEEDS:
            rec = H.random_hppc(seed)
            fit = fit_model(_base(rec), rec.profile, mode="constant")
            ocv = refine_ocv(fit, rec.profile)
            out.append((seed, rec, fit, ocv))
    return out


def test_refined_curve_keeps_every_rest_point(draws):
    """Only the shape between the points comes from the load: the curve passes through each rest point as measured,
    and between two of them it stays within their voltages."""
    for seed, _rec, fit, ocv in draws:
        assert ocv is not None, seed
        old = fit.params.ocv
        assert ocv.soc.size > old.soc.size, seed
        np.testing.assert_allclose(ocv(old.soc), old.voltage, rtol=0, atol=1e-9, err_msg=str(seed))
        for za, zb, va, vb in zip(old.soc[:-1], old.soc[1:], old.voltage[:-1], old.voltage[1:]):
            v = ocv(np.linspace(za, zb, 50))
            assert v.min() >= va - 1e-9 and v.max() <= vb + 1e-9, seed


def test_refined_curve_predicts_another_record_better(draws):
    """The model fitted with the refined curve predicts a drive cycle of the same cell better than the one fitted with
    the rest points' interpolant, in most draws and by a clear margin at the median."""
    ratios = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed, rec, fit, ocv in draws:
            refit = fit_model(_base(rec), rec.profile, mode="constant", ocv=ocv)
            drive = _drive(rec, seed)
            ratios.append(validation_rmse(refit, drive) / validation_rmse(fit, drive))
    ratios = np.array(ratios)
    print("drive RMSE ratio refined/rest points per draw:", ratios.round(2))
    assert np.mean(ratios < 1.0) >= 0.7, ratios.round(2)
    assert np.median(ratios) <= 0.8, ratios.round(2)


def test_fit_base_keeps_the_refinement_only_when_it_validates_no_worse():
    """Asked to (``refine_ocv``), the diagnosis' base fit tries the refined curve beside the chosen setting and keeps
    it when it predicts the evaluation records no worse (``VALIDATION_GAIN``; and its branches are identified, and it
    fits its own record ``REFIT_GAIN`` better); both scores are reported. Not asked, it does not try it."""
    for seed in (300, 303):
        rec = H.random_hppc(seed)
        drive = _drive(rec, seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _, info = fit_base(_base(rec), [rec.profile], validation=[drive], refine_ocv=True)
        scores = info["selection"]["validation_rmse_v"]
        refined = [k for k in scores if k.endswith("OCV refined")]
        assert len(refined) == 1
        plain = refined[0][: -len(", OCV refined")]
        rep = info["ocv_refinement"]
        kept = rep["branches_identified"] and rep["fit_rmse_v"][1] <= (1 - REFIT_GAIN) * rep["fit_rmse_v"][0] \
            and scores[refined[0]] <= (1 - VALIDATION_GAIN) * scores[plain]
        best = refined[0] if kept else plain
        assert info["selection"]["chosen"] == best
        assert ("refined" in info["ocv"]) == (best == refined[0])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _, plain_info = fit_base(_base(rec), [rec.profile], validation=[drive])
        assert not any("refined" in k for k in plain_info["selection"]["validation_rmse_v"])


def test_branch_time_constants_are_r_times_c():
    rec = H.random_hppc(301)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_model("dp", rec.profile, mode="constant")
    v = fit.params.values
    taus = branch_time_constants(fit.params)
    assert set(taus) == {"R1C1", "R2C2"}
    for j in (1, 2):
        assert taus[f"R{j}C{j}"] == pytest.approx(float(v[f"R{j}"](0.5)) * float(v[f"C{j}"](0.5)), rel=1e-12)


def test_a_refit_whose_branch_is_slower_than_the_record_is_not_kept(monkeypatch):
    """A branch whose time constant exceeds the fit record's duration only ramps with the charge moved (a capacitor):
    it stands in for the OCV's slope, so a refit on the refined curve that leans on one is not kept, whatever it
    validates to — by ``refit_on_refined_ocv`` and so by the diagnosis' base fit."""
    rec = H.random_hppc(303)
    drive = _drive(rec, 303)
    original, validate = pseudo_ocv.fit_model, pseudo_ocv.validation_rmse

    def degenerate_when_refined(name, prof, **kw):
        fit = original(name, prof, **kw)
        if "refined" not in (kw.get("ocv").source if kw.get("ocv") is not None else ""):
            return fit
        values = dict(fit.params.values)
        values["C1"] = values["C1"].scaled(1e3 * prof.duration_s / branch_time_constants(fit.params)["R1C1"])
        return dataclasses.replace(fit, params=fit.params.replace(values=values))

    def refined_validates_best(fit, record):  # the guard must hold whatever the validation says
        return 0.0 if "refined" in fit.params.ocv.source else validate(fit, record)

    monkeypatch.setattr(pseudo_ocv, "fit_model", degenerate_when_refined)
    monkeypatch.setattr(pseudo_ocv, "validation_rmse", refined_validates_best)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_model(_base(rec), rec.profile, mode="constant")
        refit, report = pseudo_ocv.refit_on_refined_ocv(fit, rec.profile, [drive], mode="constant")
        _, info = fit_base(_base(rec), [rec.profile], validation=[drive], refine_ocv=True)
    assert refit is None and report["branches_identified"] is False and report["kept"] is False
    assert report["validation_rmse_v"][1] == 0.0  # it did validate best
    assert info["ocv_refinement"]["branches_identified"] is False
    assert "refined" not in info["selection"]["chosen"] and "refined" not in info["ocv"]


def test_cli_fit_refine_ocv(tmp_path, capsys):
    """``socbench fit --refine-ocv`` on a generated LFP-like HPPC (its OCV bends between the rest points): one line says
    what the refinement measured; the parameter file carries the refined curve when it was kept, the rest points'
    curve when not. With ``--ocv`` it is one error line and exit code 2."""
    from socbench.cli import main
    from socbench.models import load_params

    cell = H.Cell(5.0, "lfp", 0.012, ((0.006, 30.0),))
    rec = H.hppc_record(cell, H.Layout(step=0.08), H.Instrument(dt=1.0, v_noise=1e-3), seed=5)
    data, drive, out = tmp_path / "hppc.csv", tmp_path / "drive.csv", tmp_path / "p.json"
    H.write_canonical(rec.profile, data)
    H.write_canonical(_drive(rec, 5), drive)
    assert main(["fit", "--data", str(data), "--model", "thevenin", "--out", str(out), "--mode", "constant",
                 "--refine-ocv", "--validation", str(drive)]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("OCV refined")]
    assert len(lines) == 1 and "validation RMS" in lines[0], lines
    _, params = load_params(out)
    n_rest = int(lines[0].split("between its ")[1].split(" rest points")[0])
    kept = lines[0].endswith("; kept")
    assert (params.ocv.soc.size > n_rest) == kept
    assert kept, lines[0]  # the LFP-like curve's bends between 8 % steps: the refit predicts the drive better
    rc = main(["fit", "--data", str(data), "--model", "thevenin", "--out", str(out), "--refine-ocv", "--ocv",
               str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--refine-ocv" in err[0], err


@pytest.mark.realdata
def test_a_refit_that_fits_its_own_real_record_better_but_predicts_the_cell_worse_is_not_kept(data_dir, monkeypatch):
    """The ORNL Nissan Leaf HPPC at 25 °C (a regen pulse runs straight into each step; data we did not make): the
    curve refined from the record fits the record itself better, so the own-record rule alone would keep it, but it
    predicts the cell's first 1C discharge (a record it never saw) worse; given that discharge as validation, the refit
    is not kept. The case as found: the curve below the lowest rest point the line through the two lowest (with the
    bottom extension, socbench.identify.hppc.BOTTOM_EXTENSION, the constant fit itself fits its record better, and the
    refinement gains 4 %, short of the own-record rule)."""
    from socbench.datasets import load
    from socbench.identify import hppc

    monkeypatch.setattr(hppc, "BOTTOM_EXTENSION", False)

    prof = load(data_dir / "nissan_leaf_ornl" / "hppc_25degC.csv", "nissan-leaf")
    runs = load(data_dir / "nissan_leaf_ornl" / "discharge_1C_bitrode.csv", "nissan-leaf")
    edges = np.flatnonzero(np.diff((runs.current_a > 5.0).astype(int)))
    first = runs.slice(int(edges[0]) - 5, int(edges[1]) + 1)  # from the rest after the first full charge
    assert first.soc_ref[0] == pytest.approx(1.0) and first.soc_ref[-1] < 0.15
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_model("thevenin", prof, mode="constant")
        alone, own = pseudo_ocv.refit_on_refined_ocv(fit, prof, mode="constant")
        refit, report = pseudo_ocv.refit_on_refined_ocv(fit, prof, validation=[first], mode="constant")
    assert own["refined"] and own["branches_identified"]
    assert own["fit_rmse_v"][1] <= (1.0 - pseudo_ocv.REFIT_GAIN) * own["fit_rmse_v"][0] and alone is not None
    before, after = report["validation_rmse_v"]
    assert after > before  # the refined curve's shape between the rest points is the record's, not the cell's
    assert refit is None and report["kept"] is False and report["why_not"].startswith("validation")


#: draws of an HPPC run in the charge direction (levels 12–20 % apart reached by charge steps)
CHARGE_DIRECTION_DRAWS = 8


@pytest.mark.parametrize("seed", range(CHARGE_DIRECTION_DRAWS))
def test_an_hppc_in_the_charge_direction_is_refined_from_its_charge_steps(seed):
    """Its rest points follow charge steps, and its discharges are only pulses: the curve between the points is read
    from the charge steps. Judged against the truth's OCV over the points' range (before this, read from the
    discharge pulses, the refinement was refused in 9 of 10 draws of this layout with another seed, and the error
    stayed 7–26 mV; now 0.3–2.7 mV)."""
    rng = np.random.default_rng([seed, 49])
    cell = H.random_cell(rng)
    lay = H.Layout(pulses_c=(1.0, -0.75), rest_s=float(rng.uniform(1800.0, 3600.0)),
                   step=float(rng.uniform(0.12, 0.2)), step_c=float(rng.uniform(0.3, 1.0)), ascending=True)
    rec = H.hppc_record(cell, lay, H.Instrument(dt=1.0, i_noise_c=0.002, v_noise=1e-3), seed=seed)
    fit = fit_model("dp", rec.profile, mode="constant")
    assert pseudo_ocv.step_direction(rec.profile) == "charge"
    refit, report = pseudo_ocv.refit_on_refined_ocv(fit, rec.profile, mode="constant")
    assert refit is not None, report
    z = np.linspace(fit.params.ocv.soc[0] + 0.01, fit.params.ocv.soc[-1] - 0.01, 300)
    before = np.sqrt(np.mean((fit.params.ocv.value(z) - cell.ocv.value(z)) ** 2))
    after = np.sqrt(np.mean((refit.params.ocv.value(z) - cell.ocv.value(z)) ** 2))
    assert after < 0.5 * before, (before, after)


#: draws of the validation rule's test (cell shape cycled so every OCV shape comes in a third of them); measured before
#: the test was written on draws 700–789 of the same construction: the sign of the validation fall agreed with the
#: noise-free verdict in 90 of 90, and the 9 falls of 0–10 % (the old bar's refusals) were all better without noise
VALIDATION_DRAWS = range(800, 840)


def test_a_refinement_the_noisy_validation_records_do_not_reject_predicts_the_noise_free_voltage_better():
    """The keep rule's validation bar (``VALIDATION_GAIN``: no worse) against what it stands for, the voltage without
    the sensor's noise. Each draw: an HPPC of the tests' generator (random cell, layout, instrument; NMC, NCA and LFP
    shapes in turn) and a 40-minute drive of the same cell from 98 % SOC (the top of charge, where the rest points'
    interpolant misses most) read with 2–5 mV of voltage noise, given as the validation record. Whether the refit on
    the refined curve predicts that noisy record better agrees with whether it predicts the noise-free voltage better;
    and where it does by less than 10 % (what the bar of 10 %, until stop 51, refused: noise-dominated records) the
    refined curve is the better one without noise."""
    agree, small = [], []
    shapes = ("lfp", "nmc", "nca")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for seed in VALIDATION_DRAWS:
            rng, cell, lay, ins = H.random_setup(seed)
            cell = dataclasses.replace(cell, ocv_shape=shapes[seed % 3])
            rec = H.hppc_record(cell, lay, ins, seed=seed + 1, with_soc_ref=lay.gaps or rng.random() < 0.5)
            drive = H.drive_record(cell, H.Instrument(dt=1.0, v_noise=float(rng.uniform(2e-3, 5e-3))), seed=seed + 2,
                                   duration_s=2400.0, soc0=0.98)
            p = drive.profile
            clean = Profile(p.time_s, p.current_a, voltage_v=drive.v_clean, soc_ref=p.soc_ref, meta=p.meta)
            base = "dp" if len(cell.branches) == 2 else "thevenin"
            fit = fit_model(base, rec.profile, mode="constant")
            refit, report = pseudo_ocv.refit_on_refined_ocv(fit, rec.profile, validation=[p], mode="constant")
            if not report["refined"]:
                continue
            # the refit on the refined curve, kept or not (refit_on_refined_ocv returns it only when kept)
            on_curve = refit if refit is not None else fit_model(
                base, rec.profile, mode="constant", ocv=refine_ocv(fit, rec.profile),
                capacity_ah=fit.params.capacity_ah)
            before, after = report["validation_rmse_v"]
            better_clean = validation_rmse(on_curve, clean) < validation_rmse(fit, clean)
            agree.append((after <= before) == better_clean)
            if report["kept"]:
                assert refit is not None and after <= (1.0 - VALIDATION_GAIN) * before, seed
                if after > (1.0 - REFIT_GAIN) * before:  # kept now, refused by the old bar
                    small.append((seed, better_clean))
    print(f"validation verdict = noise-free verdict in {sum(agree)} of {len(agree)}; kept with a fall under "
          f"{100 * REFIT_GAIN:.0f} %: {small}")
    assert len(agree) >= 30 and np.mean(agree) >= 0.95, agree
    assert small and np.mean([b for _, b in small]) >= 0.9, small


def test_collapse_ties_gives_one_point_per_run():
    from socbench.ocv import collapse_ties

    z, v = collapse_ties([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], [3.1, 3.2, 3.2, 3.2, 3.3, 3.3])
    np.testing.assert_allclose(z, [0.1, 0.3, 0.55])
    np.testing.assert_allclose(v, [3.1, 3.2, 3.3])
    z, v = collapse_ties([0.1, 0.2], [3.1, 3.2])  # nothing tied: unchanged
    np.testing.assert_allclose(z, [0.1, 0.2])
    np.testing.assert_allclose(v, [3.1, 3.2])


#: LFP draws of the randomised generator with a 1 mV voltage ADC (seeds the refinement was not developed on): on a
#: plateau the step segments' medians tie, and the isotonic regression pooled them into runs (8–102 flat segments per
#: curve before socbench.ocv.collapse_ties)
LFP_SEEDS = range(400, 412)


@pytest.mark.parametrize("seed", LFP_SEEDS)
def test_a_refined_lfp_curve_has_no_flat_run_but_between_rest_points_that_tie(seed):
    """A flat segment of the refined curve is only where two of the HPPC's rest points read the same voltage (a
    measurement at the ADC's resolution); between them every point rises, so a filter's Jacobian (the curve's slope)
    is never zero inside a run the regression pooled."""
    rng, cell, lay, ins = H.random_setup(seed)
    cell, ins = dataclasses.replace(cell, ocv_shape="lfp"), dataclasses.replace(ins, v_lsb=1e-3)
    rec = H.hppc_record(cell, lay, ins, seed=seed + 1, with_soc_ref=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_model(_base(rec), rec.profile, mode="constant")
        ocv = refine_ocv(fit, rec.profile)
    assert ocv is not None
    rest = fit.params.ocv
    np.testing.assert_allclose(ocv(rest.soc), rest.voltage, rtol=0, atol=1e-9)  # every rest point as measured
    is_rest = np.isin(ocv.soc, rest.soc)
    flat = np.flatnonzero(np.diff(ocv.voltage) == 0)
    assert all(is_rest[k] and is_rest[k + 1] for k in flat), [(ocv.soc[k], ocv.soc[k + 1]) for k in flat]


def test_an_ekf_on_a_refined_lfp_curve_of_a_foreign_record_holds_the_soc(tmp_path):
    """Case 7010 of benchmarks/foreign_records.py (an LFP cell, a 5 mV voltage ADC, the HPPC stopping at 17 %): the
    curve refined from its HPPC was a staircase (113 flat segments of 164), and the EKF on the diagnosed model ran
    50 SOC points off within minutes (held-out 5.3 → 29.0 %) where the UKF held within a point. With one point per
    pooled run it holds too."""
    import importlib.util

    from socbench.datasets import load
    from socbench.diagnose import diagnose

    spec = importlib.util.spec_from_file_location("foreign_records", REPO / "benchmarks" / "foreign_records.py")
    fr = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fr)
    fr.draw(7010, tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d = diagnose("thevenin", [load(tmp_path / "case7010_hppc.csv")], [load(tmp_path / "case7010_field.csv")])
    before, after = (getattr(d, k)["soc"]["ekf"]["soc_rmse"] for k in ("before", "after"))
    assert after <= before + 0.002, (before, after)
    assert after <= 0.02, after
