"""The domain block of every JSON output and the one-line warning of the CLI (socbench.domain through the commands)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from socbench.cli import main
from socbench.models import paper_params, save_params
from socbench.models.params import Constant

DOMAIN_KEYS = {"samples", "soc_below_0", "soc_above_1", "ocv_extrapolated", "ocv_held", "guards", "outside",
               "outside_fraction", "segments"}


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if "outside the model's domain" in line]


def test_every_json_output_carries_the_domain(tmp_path, capsys):
    sim = tmp_path / "sim.json"
    assert main(["simulate", "--data", "builtin:1c", "--params", "paper:thevenin", "--json", str(sim)]) == 0
    d = json.loads(sim.read_text())
    assert DOMAIN_KEYS <= set(d["domain"]) and d["segments"]["count"] == 1 and isinstance(d["guard_fractions"], dict)
    est = tmp_path / "est"
    assert main(["estimate", "--data", "builtin:1c", "--params", "paper:thevenin", "--estimator", "ekf",
                 "--out", str(est)]) == 0
    m = json.loads((est / "metrics.json").read_text())
    assert DOMAIN_KEYS | {"soc_clamped"} <= set(m["domain"]) and m["failed_reason"] == [""]
    fit = tmp_path / "params.json"
    assert main(["fit", "--data", "builtin:hppc", "--model", "rint", "--mode", "constant", "--out", str(fit)]) == 0
    assert DOMAIN_KEYS <= set(json.loads(fit.read_text())["fit"]["domain"])
    diag = tmp_path / "diag"
    assert main(["diagnose", "--fit", "builtin:hppc", "--eval", "builtin:1c", "--model", "rint", "--out", str(diag),
                 "--no-figures", "--no-soc", "--effects", "capacity"]) == 0
    dd = json.loads((diag / "diagnosis.json").read_text())
    assert DOMAIN_KEYS <= set(dd["domain"]["before"]) and DOMAIN_KEYS <= set(dd["domain"]["after"])
    assert not _warnings(capsys.readouterr().err)  # clean records: no warning


def test_a_voltage_in_kilovolts_is_never_reported_without_a_warning(tmp_path, capsys):
    """A parameter set with R0 = 100 Ω on the paper pack at 1 C: the model reads thousands of volts below zero;
    SOC stays in range, the OCV is fine, and still the CLI says the result is outside the model's domain."""
    p = paper_params("rint")
    p = p.__class__(**{**p.__dict__, "values": {"R0": Constant(100.0)}})
    params = tmp_path / "huge_r0.json"
    save_params(params, "rint", p)
    out = tmp_path / "sim.json"
    assert main(["simulate", "--data", "builtin:1c", "--params", str(params), "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    assert d["rmse_v"] > 1000.0
    assert d["domain"]["voltage_implausible"] == d["n"] and d["domain"]["soc_below_0"] == 0
    (line,) = _warnings(capsys.readouterr().err)
    assert line.startswith("socbench simulate: warning: rint on") and "implausible" in line


@pytest.mark.realdata
def test_dji_command_of_the_issue(data_dir, tmp_path, capsys):
    """The issue's command: per pack, no warning and volts, not kilovolts; forced through as one piece, the warning."""
    data = str(data_dir / "uav_dji_m100" / "battery_telemetry_all_flights.csv")
    out = tmp_path / "out.json"
    assert main(["simulate", "--data", data, "--params", "paper:dp", "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    stdout, err = capsys.readouterr()
    assert d["rmse_v"] < 2.0 and d["segments"]["count"] > 144 and d["domain"]["outside_fraction"] < 0.01
    assert "out of domain 0.0 %" in stdout and not _warnings(err)
    assert main(["simulate", "--data", data, "--params", "paper:dp", "--json", str(out), "--no-segments"]) == 0
    d = json.loads(out.read_text())
    assert d["segments"]["count"] == 1 and d["domain"]["outside_fraction"] > 0.9
    assert np.isfinite(d["rmse_v"]) and d["rmse_v"] < 30.0  # the held OCV: volts, never kilovolts
    (line,) = _warnings(capsys.readouterr().err)
    assert "SOC below 0" in line and "OCV held" in line


@pytest.mark.realdata
def test_dji_pack_capacity_mismatch_is_named(data_dir, tmp_path, capsys):
    """paper:dp is a 22 Ah pack, the M100 flights a 5.5 Ah one: the command names the mismatch in one line, and the
    same parameters at the record's capacity bring the per-segment error under 1 V RMS — the capacity, not the
    segmenting, is what is left."""
    import dataclasses

    data = str(data_dir / "uav_dji_m100" / "battery_telemetry_all_flights.csv")
    out = tmp_path / "out.json"
    assert main(["simulate", "--data", data, "--params", "paper:dp", "--json", str(out)]) == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "declares a capacity" in line]
    assert len(lines) == 1 and "5.5 Ah" in lines[0] and "22 Ah" in lines[0]
    mismatched = json.loads(out.read_text())
    assert mismatched["capacity_ratio"] == pytest.approx(0.25)
    params = paper_params("dp")
    params = params[1] if isinstance(params, tuple) else params
    path = tmp_path / "dp_5p5.json"
    save_params(path, "dp", dataclasses.replace(params, capacity_ah=5.5))
    assert main(["simulate", "--data", data, "--params", str(path), "--json", str(out)]) == 0
    matched = json.loads(out.read_text())
    assert "declares a capacity" not in capsys.readouterr().err
    assert matched["rmse_v"] < 1.0 < mismatched["rmse_v"]
