"""Records shaped the way other people's tools write them (found by feeding the CLI files no socbench generator
made): headers in another case or quoted, another separator, a hole in a column the command does not use, a pack's
record beside a cell's fit, a record too short to cross-validate, a gap with no reference to restart from. Each is
read, or refused in one line with exit code 2 — never a traceback, never numbers of volts passed off as a model's
error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from socbench.cli import main
from socbench.datasets import detect_format, load
from socbench.models import make_model, paper_params
from socbench.profile import Profile, ProfileMeta

HEADER = ("time_s", "current_a", "voltage_v", "temperature_c", "soc_ref")


def paper_record(n: int = 1200, dt: float = 1.0, seed: int = 0, gap: tuple[int, int] | None = None):
    """The paper pack (thevenin, its own parameters: 6 cells in series) under a varying load, with sensor noise:
    ``(columns dict, sidecar dict)``;
    ``gap = (a, b)`` drops samples ``a … b − 1`` (the load went on, the logger did not)."""
    rng = np.random.default_rng(seed)
    params = paper_params("thevenin")
    q = params.capacity_ah
    t = np.arange(n) * dt
    cur = q * (0.8 + 0.6 * np.sin(t / 47.0) + 0.3 * rng.standard_normal(n).cumsum() / np.sqrt(n))
    sim = make_model("thevenin", params).simulate(Profile(t, cur, meta=ProfileMeta(capacity_ah=q)), soc0=0.95,
                                                  segments=False)
    cols = {"time_s": t, "current_a": cur + rng.normal(0, 0.01 * q, n),
            "voltage_v": sim.voltage_v + rng.normal(0, 0.005, n), "temperature_c": np.full(n, 25.0),
            "soc_ref": sim.soc}
    if gap is not None:
        keep = np.r_[0:gap[0], gap[1]:n]
        cols = {k: v[keep] for k, v in cols.items()}
    return cols, {"capacity_ah": q, "n_series": 6}


def write(path: Path, cols: dict, header=None, sep: str = ",", quote: bool = False, meta: dict | None = None,
          cells: dict | None = None) -> Path:
    """A CSV of ``cols`` under ``header`` (default: their names); ``cells`` = {(row from 1, column): text}."""
    names = list(header or cols)
    rows = [[f"{v:.6f}" for v in vals] for vals in zip(*cols.values())]
    for (row, col), text in (cells or {}).items():
        rows[row - 1][list(cols).index(col)] = text

    def fmt(fields):
        return sep.join(f'"{f}"' if quote else f for f in fields)

    path.write_text("\n".join([fmt(names)] + [fmt(r) for r in rows]) + "\n")
    if meta is not None:
        path.with_suffix(".json").write_text(json.dumps(meta))
    return path


def cli(capsys, *argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.mark.parametrize("case", ["upper", "mixed", "quoted"])
def test_canonical_headers_in_another_case_or_quoted_are_read(tmp_path, case):
    cols, meta = paper_record()
    header = {"upper": [c.upper() for c in HEADER], "mixed": [c.capitalize() for c in HEADER],
              "quoted": HEADER}[case]
    path = write(tmp_path / f"{case}.csv", cols, header=header, quote=case == "quoted", meta=meta)
    assert detect_format(path) == "canonical"
    p = load(path)
    np.testing.assert_allclose(p.voltage_v, np.round(cols["voltage_v"], 6))
    np.testing.assert_allclose(p.soc_ref, np.round(cols["soc_ref"], 6))


def test_a_header_another_format_knows_exactly_stays_with_that_format(tmp_path):
    """The ORNL Leaf files' header holds time_s and current_A: it is theirs, not a canonical CSV in another case."""
    leaf = ("time_s,cycle,step,step_time_s,current_A,voltage_V,power_W,capacity_Ah,energy_Wh,mode,flag\n"
            "0,1,1,0,0,3.9,0,0,0,R,0\n1,1,1,1,0,3.9,0,0,0,R,0\n")
    path = tmp_path / "leaf.csv"
    path.write_text(leaf)
    assert detect_format(path) == "nissan-leaf"


@pytest.mark.parametrize("sep", [";", "\t"])
def test_another_separator_is_named_in_one_line(tmp_path, capsys, sep):
    cols, meta = paper_record(n=50)
    path = write(tmp_path / "semi.csv", cols, sep=sep, meta=meta)
    rc, _, err = cli(capsys, "simulate", "--data", path, "--format", "canonical", "--params", "paper:thevenin")
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert repr(sep) in err and "comma-separated" in err and str(path) in err


def test_a_hole_in_the_reference_fails_only_where_the_reference_is_used(tmp_path, capsys):
    cols, meta = paper_record()
    path = write(tmp_path / "hole.csv", cols, meta=meta, cells={(101, "soc_ref"): ""})
    rc, out, err = cli(capsys, "simulate", "--data", path, "--params", "paper:thevenin", "--soc0", "0.95")
    assert rc == 0 and "RMS" in out, err
    rc, _, err = cli(capsys, "estimate", "--data", path, "--params", "paper:thevenin", "--estimator", "coulomb",
                     "--soc0", "0.95", "--out", tmp_path / "est")
    assert rc == 2 and "'soc_ref'" in err and "row 101" in err and len(err.strip().splitlines()) == 1


def test_a_reference_that_overshoots_once_is_not_called_percent(tmp_path, capsys):
    cols, meta = paper_record()
    spike = write(tmp_path / "spike.csv", cols, meta=meta, cells={(300, "soc_ref"): "1.5"})
    rc, _, err = cli(capsys, "estimate", "--data", spike, "--params", "paper:thevenin", "--estimator", "coulomb",
                     "--soc0", "0.95", "--out", tmp_path / "e1")
    assert rc == 2 and "row 300" in err and "percent" not in err
    cols_pct = dict(cols, soc_ref=100 * cols["soc_ref"])
    pct = write(tmp_path / "pct.csv", cols_pct, meta=meta)
    rc, _, err = cli(capsys, "estimate", "--data", pct, "--params", "paper:thevenin", "--estimator", "coulomb",
                     "--soc0", "0.95", "--out", tmp_path / "e2")
    assert rc == 2 and "percent" in err


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_a_pack_record_beside_a_cell_fit_is_refused_before_any_fit(tmp_path, capsys, command):
    """A 4-series pack's drive given as the validation (fit) or evaluation (diagnose) record of a single cell's test:
    before, the model error came out at volts and the EKF built on it counted coulombs."""
    cell, meta = paper_record(seed=1)
    cell = dict(cell, voltage_v=cell["voltage_v"] / 6.0)  # one cell of the 6-series paper pack
    pack = dict(cell, voltage_v=4.0 * cell["voltage_v"])
    fit = write(tmp_path / "cell.csv", cell, meta=dict(meta, n_series=1))
    other = write(tmp_path / "pack4.csv", pack, meta=dict(meta, n_series=4))
    if command == "fit":
        argv = ["fit", "--data", fit, "--model", "thevenin", "--validation", other, "--out", tmp_path / "p.json"]
    else:
        argv = ["diagnose", "--fit", fit, "--eval", other, "--model", "thevenin", "--out", tmp_path / "d"]
    rc, _, err = cli(capsys, *argv)
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert "pack4.csv" in err and "'voltage_v'" in err and "n_series" in err


def test_an_evaluation_record_too_short_to_cross_validate_is_refused(tmp_path, capsys):
    cols, meta = paper_record(n=600)
    fit = write(tmp_path / "fit.csv", cols, meta=meta)
    short = write(tmp_path / "short.csv", {k: v[:2] for k, v in cols.items()}, meta=meta)
    for argv in (["--eval", short], ["--eval", fit, "--dt", "100000"]):
        rc, _, err = cli(capsys, "diagnose", "--fit", fit, *argv, "--model", "thevenin", "--out", tmp_path / "d")
        assert rc == 2 and "blocks of held-out time" in err and len(err.strip().splitlines()) == 1
    one = write(tmp_path / "one.csv", {k: v[:1] for k, v in cols.items()}, meta=meta)  # no time step at all
    rc, _, err = cli(capsys, "diagnose", "--fit", fit, "--eval", one, "--model", "thevenin", "--out", tmp_path / "d")
    assert rc == 2 and "1 sample: a record needs at least 2" in err and len(err.strip().splitlines()) == 1
    for value in ("inf", "nan", "-1"):
        rc, _, err = cli(capsys, "diagnose", "--fit", fit, "--eval", fit, "--model", "thevenin", "--out",
                         tmp_path / "d", "--capacity", value)
        assert rc == 2 and "--capacity" in err


def test_a_gap_with_nothing_to_restart_from_is_reported(tmp_path, capsys):
    """No reference SOC, the load on both sides of a 10-minute gap: the run holds the last current across it, and
    says so (stderr and the JSON), where before it said nothing."""
    cols, meta = paper_record(n=2400, gap=(1200, 1800))
    # with its reference (which falls across the gap as the held current counts: no restart) and run as one piece
    referenced = write(tmp_path / "referenced.csv", cols, meta=meta)
    rc, _, err = cli(capsys, "simulate", "--data", referenced, "--params", "paper:thevenin", "--no-segments")
    assert rc == 0 and "1 gap(s)" in err
    cols.pop("soc_ref")
    path = write(tmp_path / "gap.csv", cols, meta=meta)
    rc, _, err = cli(capsys, "simulate", "--data", path, "--params", "paper:thevenin", "--soc0", "0.95",
                     "--json", tmp_path / "m.json")
    assert rc == 0
    assert "1 gap(s)" in err and "601 s" in err and "row 1201" in err
    report = json.loads((tmp_path / "m.json").read_text())["logger_pauses"]
    assert report["gaps"] == 1 and report["longest_gap_row"] == 1201
    rc, _, err = cli(capsys, "estimate", "--data", path, "--params", "paper:thevenin", "--estimator", "ekf",
                     "--soc0", "0.95", "--out", tmp_path / "e")
    assert rc == 0 and "1 gap(s)" in err
    # the same record without the gap: nothing said
    whole, meta = paper_record(n=2400)
    whole.pop("soc_ref")
    rc, _, err = cli(capsys, "simulate", "--data", write(tmp_path / "whole.csv", whole, meta=meta),
                     "--params", "paper:thevenin", "--soc0", "0.95")
    assert rc == 0 and "gap" not in err


@pytest.mark.parametrize("option", [("--soc0-sd", "10"), ("--particles", "2")])
def test_estimate_options_that_give_no_band_are_refused(tmp_path, capsys, option):
    """Before: --soc0-sd 10 exited 0 with every run failed; --particles 2 exited 0 with a NEES of 1e15."""
    cols, meta = paper_record(n=100)
    path = write(tmp_path / "r.csv", cols, meta=meta)
    rc, _, err = cli(capsys, "estimate", "--data", path, "--params", "paper:thevenin", "--estimator", "pf",
                     *option, "--out", tmp_path / "e")
    assert rc == 2 and option[0] in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("stamp", ["2024-03-01 12:00:00", "2024-03-01T12:00:00Z", "03/01/2024 12:00"])
def test_date_time_stamps_in_the_seconds_column_are_named_as_such(tmp_path, capsys, stamp):
    cols, meta = paper_record(n=20)
    path = write(tmp_path / "dt.csv", cols, meta=meta, cells={(1, "time_s"): stamp})
    rc, _, err = cli(capsys, "simulate", "--data", path, "--params", "paper:thevenin")
    assert rc == 2 and "'time_s'" in err and "row 1" in err and "date and time" in err
    assert len(err.strip().splitlines()) == 1
    junk = write(tmp_path / "junk.csv", cols, meta=meta, cells={(1, "time_s"): "n/a"})
    rc, _, err = cli(capsys, "simulate", "--data", junk, "--params", "paper:thevenin")
    assert rc == 2 and "not a finite number" in err


def test_short_temperature_holes_are_interpolated_and_long_ones_refused_over_random_records():
    """A thermocouple that drops out: 200 random records (0.1–10 s sampling, jittered stamps, 1–4 holes each, some at
    the record's ends). Holes silent for at most TEMPERATURE_HOLE_S are filled by linear interpolation in time — each
    filled value equal to the line between the readings around it (or the nearest reading at an end) — with one
    warning; where the longest silence is longer, a DataError names the column and that hole's first row."""
    import warnings

    from socbench.errors import DataError, SocbenchWarning
    from socbench.profile import TEMPERATURE_HOLE_S

    rng = np.random.default_rng(2029)
    filled_cases = refused_cases = 0
    for _ in range(200):
        dt = float(np.exp(rng.uniform(np.log(0.1), np.log(10.0))))
        n = int(rng.integers(200, 3000))
        t = np.cumsum(dt * rng.uniform(0.8, 1.2, n))
        temp = 25.0 + 10.0 * np.sin(t / rng.uniform(300.0, 3000.0)) + rng.normal(0.0, 0.05, n)
        holes = []
        for _ in range(int(rng.integers(1, 5))):
            length = int(rng.integers(1, max(2, min(n // 4, int(1.5 * TEMPERATURE_HOLE_S / dt)))))
            a = int(rng.integers(0, n - length)) if rng.random() > 0.15 else (0 if rng.random() < 0.5 else n - length)
            holes.append((a, a + length))
        given = temp.copy()
        for a, b in holes:
            given[a:b] = np.nan
        hole = np.isnan(given)
        runs = np.flatnonzero(np.diff(np.r_[0, hole.astype(int), 0])).reshape(-1, 2)
        silent = [t[min(b, n - 1)] - t[max(a - 1, 0)] for a, b in runs]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                p = Profile(t, np.ones(n), 3.7 * np.ones(n), given, meta=ProfileMeta(name="logger"))
            except DataError as exc:
                k = int(np.argmax(silent))
                assert silent[k] > TEMPERATURE_HOLE_S, (silent, str(exc))
                assert exc.column == "temperature_c" and exc.row == runs[k][0] + 1, (str(exc), runs)
                refused_cases += 1
                continue
        assert max(silent) <= TEMPERATURE_HOLE_S
        msgs = [str(w.message) for w in caught if issubclass(w.category, SocbenchWarning)]
        assert len(msgs) == 1 and "temperature_c" in msgs[0] and f"row {runs[0][0] + 1}" in msgs[0], msgs
        good = ~hole
        np.testing.assert_array_equal(p.temperature_c[good], given[good])
        for a, b in runs:
            lo, hi = a - 1, b  # the readings around the hole
            for k in range(a, b):
                if lo < 0:
                    want = given[hi]
                elif hi >= n:
                    want = given[lo]
                else:
                    w = (t[k] - t[lo]) / (t[hi] - t[lo])
                    want = (1.0 - w) * given[lo] + w * given[hi]
                assert p.temperature_c[k] == pytest.approx(want, abs=1e-9)
        filled_cases += 1
    assert filled_cases >= 40 and refused_cases >= 40, (filled_cases, refused_cases)  # both sides drawn often


def test_a_thermocouple_dropout_in_a_csv_is_filled_or_refused_in_one_line(tmp_path, capsys):
    """The CLI on a canonical CSV whose temperature has empty cells: a 20 s hole (and an 'NA') is filled with a warning
    and the simulation runs; a 5 min hole exits 2 naming the file, column and row; a word in the column is still an
    error, and so is an empty voltage cell."""
    cols, meta = paper_record(n=1200)
    cells = {(r, "temperature_c"): "" for r in range(301, 321)}
    cells[900, "temperature_c"] = "NA"
    short = write(tmp_path / "short.csv", cols, meta=meta, cells=cells)
    rc, out, err = cli(capsys, "simulate", "--data", short, "--params", "paper:thevenin", "--soc0", "0.95",
                       "--out", tmp_path / "sim.csv")
    assert rc == 0 and "temperature_c" in err and "row 301" in err and "interpolation" in err, err
    assert "Traceback" not in err
    long_ = write(tmp_path / "long.csv", cols, meta=meta, cells={(r, "temperature_c"): "" for r in range(501, 801)})
    rc, _, err = cli(capsys, "simulate", "--data", long_, "--params", "paper:thevenin", "--soc0", "0.95")
    assert rc == 2 and "long.csv" in err and "temperature_c" in err and "row 501" in err, err
    assert len(err.strip().splitlines()) == 1
    for col, text in (("temperature_c", "open"), ("voltage_v", "")):
        bad = write(tmp_path / "bad.csv", cols, meta=meta, cells={(700, col): text})
        rc, _, err = cli(capsys, "simulate", "--data", bad, "--params", "paper:thevenin", "--soc0", "0.95")
        assert rc == 2 and col in err and "row 700" in err, err
