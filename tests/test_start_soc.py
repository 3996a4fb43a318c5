"""The SOC a record without a reference starts from, when its first sample is under load (a UAV's take-off, a drive
that was already running when the logger started): ``Model.soc_from_voltage`` corrects the OCV inverse for the load's
instantaneous drop, and every command that starts from the first voltage (simulate, fit, diagnose, the filters) uses
it through ``socbench.segments.restart_soc``.

The drive records come from the independent generator of ``tests/hppc_records.py`` (its own exact-solution truth,
OCV shapes and instrument), not from the models under test."""

from __future__ import annotations

import numpy as np
import pytest

from socbench.cli import main
from socbench.diagnose.search import initial_soc
from socbench.estimators import SensorNoise, make_estimator
from socbench.estimators.base import Inputs
from socbench.models import make_model, model_names, save_params
from socbench.models.paper import paper_params
from socbench.models.params import ModelParams

from . import hppc_records as H


@pytest.mark.parametrize("name", model_names())
def test_soc_from_voltage_inverts_the_loaded_rest_state(name):
    """For every model: the voltage ``U(z) − ΔV(z)`` of a rested cell with a current flowing (``ΔV`` the model's own
    instantaneous drop) reads back as ``z``, over random SOCs and currents of both signs; at zero current the answer
    is the OCV inverse itself, bit for bit."""
    m = make_model(name, paper_params(name))
    rng = np.random.default_rng(7)
    n = 300
    z0 = rng.uniform(0.1, 0.95, n)
    i = rng.uniform(0.2, 3.0, n) * m.capacity_ah * np.where(rng.random(n) < 0.7, 1.0, -1.0)
    x = m.x0(z0, (n,))
    v = m.ocv.value(z0) + m.output(x, i, None)[0] - m.output(x, np.zeros(n), None)[0]
    np.testing.assert_allclose(m.soc_from_voltage(v, i), z0, atol=1e-9)
    v_rest = m.ocv.value(z0)
    np.testing.assert_array_equal(m.soc_from_voltage(v_rest, 0.0), np.clip(m.ocv.inverse(v_rest), 0.0, 1.0))


def _truth_model(cell: H.Cell):
    """The generator's cell as a socbench RC model (constant parameters, the same OCV)."""
    values = {"R0": cell.r0}
    for k, (r, tau) in enumerate(cell.branches, start=1):
        values.update({f"R{k}": r, f"C{k}": tau / r})
    name = "thevenin" if len(cell.branches) == 1 else "dp"
    return name, ModelParams(cell.capacity_ah, cell.ocv, values, source="tests/hppc_records")


def _loaded_start(seed: int):
    """A random cell's drive record that starts under load, without its reference SOC, and the true first SOC."""
    rng = np.random.default_rng(seed)
    cell = H.random_cell(rng)
    ins = H.Instrument(dt=1.0, v_noise=float(rng.uniform(0.5e-3, 2e-3)), phase=0.0)
    z_true = float(rng.uniform(0.3, 0.95))
    rec = H.drive_record(cell, ins, seed=seed, duration_s=900.0, soc0=z_true, stops=False)
    return cell, rec.profile.with_(soc_ref=None), ins, z_true


def test_every_start_reads_the_soc_of_a_record_that_starts_under_load():
    """20 random cells (NMC/NCA/LFP-like shapes, 1–2 RC branches, 1–50 Ah), each driven from a random SOC with the
    load already on at the first sample: simulate, the diagnosis and a filter's default start all begin at the same
    SOC, whose OCV is within 4 voltage-noise SDs of the true SOC's in at least 18 of 20 draws (an OCV distance: on the
    flat LFP plateau a millivolt of noise is several SOC points); the plain OCV inverse of the first voltage is
    further off (median OCV distance more than twice as large), so the check tells the two apart."""
    off_new, off_plain = [], []
    for seed in range(20):
        cell, prof, ins, z_true = _loaded_start(1000 + seed)
        assert abs(prof.current_a[0]) > 0.2 * cell.capacity_ah  # the record does start under load
        name, params = _truth_model(cell)
        m = make_model(name, params)
        z_sim = float(m.simulate(prof).soc[0])
        z_diag = initial_soc(m, prof)
        est = make_estimator("ekf", m, SensorNoise(voltage_sd=2e-3, current_sd=0.01))
        z_filter = float(est.initial_state(Inputs.from_profile(prof), None)[0, 0])
        assert z_sim == pytest.approx(z_diag, abs=1e-12) and z_filter == pytest.approx(z_diag, abs=1e-12)
        z_plain = float(np.clip(m.ocv.inverse(prof.voltage_v[0]), 0.0, 1.0))
        u_true = float(cell.ocv(z_true))
        off_new.append(abs(float(cell.ocv(z_diag)) - u_true) / ins.v_noise)
        off_plain.append(abs(float(cell.ocv(z_plain)) - u_true) / ins.v_noise)
    off_new, off_plain = np.array(off_new), np.array(off_plain)
    assert np.sum(off_new <= 4.0) >= 18, np.round(off_new, 2)
    assert np.median(off_plain) > 2 * np.median(off_new), (np.median(off_plain), np.median(off_new))


def test_cli_simulate_of_a_take_off_record_starts_at_its_soc(tmp_path, capsys):
    """`socbench simulate` on a record that starts under load and has no reference SOC: its voltage RMSE against the
    measurement stays at the sensor's noise level, as when it is told the true starting SOC (`--soc0`)."""
    cell = H.Cell(5.0, "nca", 0.012, ((0.006, 30.0),))
    ins = H.Instrument(dt=1.0, v_noise=1e-3, phase=0.0)
    rec = H.drive_record(cell, ins, seed=3, duration_s=1800.0, soc0=0.9, stops=False)
    data = H.write_canonical(rec.profile.with_(soc_ref=None), tmp_path / "drive.csv")
    name, params = _truth_model(cell)
    save_params(tmp_path / "p.json", name, params)
    rms = {}
    for label, extra in (("default", []), ("told", ["--soc0", "0.9"])):
        assert main(["simulate", "--data", str(data), "--params", str(tmp_path / "p.json"), *extra]) == 0
        out = capsys.readouterr().out
        rms[label] = float(out.split("RMS ")[1].split(" mV")[0])
    assert rms["default"] <= max(1.5 * rms["told"], 2.0), rms
