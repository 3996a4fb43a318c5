"""Inputs a lab's files hold that the commands once mishandled (found by running the CLI on variants of records of
an independent generator, ``tests/hppc_records.py``): each is a user error with one line and exit 2 naming what is
wrong, or a record the commands now take.

* a parameter file with a NaN, a negative resistance, a zero capacitance, a string capacity, a model it does not
  name correctly, or a directory given as the file: exit 2 naming the file (a NaN once ran to exit 0 and wrote NaN
  into the metrics; a string capacity and a directory were internal errors, exit 1);
* ``socbench estimate`` with another cell's parameter set: refused as ``simulate`` refuses it (it once ran to a
  12 V RMS error);
* a fit record whose capacity is given in mAh as Ah: exit 2 saying so (once a singular matrix, exit 1), and a
  warning where a reference SOC contradicts it; the diagnosis' refusal names the capacity;
* an evaluation record with a day-long pause at rest: diagnosed, its held-out blocks spanning equal recorded time
  (once refused: equal spans of clock time left two of four blocks empty);
* a record whose time is in ms: one warning where the reference SOC shows it (it once passed silently); without a
  reference, the fit's refusal of such an HPPC says that its current counts more than the cell holds;
* a canonical CSV without its current column, or with its voltage column twice: the column named (once only "could
  not detect the format", and the first of two voltage columns taken silently);
* a parameter set of another model under this one's name: one warning naming the parameters it leaves unused;
* a record of one sample: refused naming the file (it once ran to metrics over no step);
* a JSON sidecar with a byte-order mark, or ``n_series: 1.0``: read (both were refused as invalid);
* ``--voltage-sd nan`` or ``--current-sd inf``: refused naming the option (the message named an internal class);
* a DJI telemetry file with a repeated time stamp or a segment out of time order: one warning each (the loader
  dropped and sorted them silently).
"""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from socbench.cli import main
from socbench.profile import Profile
from tests.hppc_records import ISSUE_CELL, Instrument, drive_record, issue_record, write_canonical


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """An issue-13 HPPC (with its reference SOC), a drive record of the same cell, and a parameter file fitted on
    the HPPC."""
    d = tmp_path_factory.mktemp("odd")
    hppc = write_canonical(issue_record(seed=3, soc_ref_capacity_ratio=1.0).profile, d / "hppc.csv")
    drive = drive_record(ISSUE_CELL, Instrument(dt=1.0, v_noise=1e-3), seed=4, duration_s=4 * 3600.0).profile
    field = write_canonical(drive, d / "field.csv")
    assert main(["fit", "--data", str(hppc), "--model", "thevenin", "--out", str(d / "p.json")]) == 0
    return d, hppc, field, json.loads((d / "p.json").read_text())


def _one_line_error(capsys, argv, *words) -> str:
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2, (rc, err)
    lines = [ln for ln in err.splitlines() if ": error: " in ln]
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


@pytest.mark.parametrize("change, words", [
    (lambda d: d["params"].update(R0={"const": float("nan")}), ("'R0' must be finite",)),
    (lambda d: d["params"].update(R1={"const": -0.01}), ("'R1' must be a resistance, at least 0",)),
    (lambda d: d["params"].update(C1={"const": 0.0}), ("'C1' must be above 0",)),
    (lambda d: d.update(capacity_ah="abc"), ("'capacity_ah' must be a number",)),
    (lambda d: d["params"].pop("C1"), ("needs parameter 'C1'",)),
    (lambda d: d.update(model="nosuchmodel"), ("unknown model 'nosuchmodel'",)),
])
def test_a_bad_parameter_file_is_a_user_error_naming_it(records, tmp_path, capsys, change, words):
    d, _, field, good = records
    bad = json.loads(json.dumps(good))
    change(bad)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(bad, allow_nan=True))
    for cmd in (["simulate", "--data", str(field), "--params", str(path), "--json", str(tmp_path / "m.json")],
                ["estimate", "--data", str(field), "--params", str(path), "--estimator", "ekf",
                 "--out", str(tmp_path / "e")]):
        _one_line_error(capsys, cmd, str(path), *words)
    assert not (tmp_path / "m.json").exists()


def test_a_directory_as_the_parameter_file(records, tmp_path, capsys):
    _, _, field, _ = records
    _one_line_error(capsys, ["simulate", "--data", str(field), "--params", str(tmp_path)], str(tmp_path),
                    "is a directory")


def test_estimate_refuses_another_cells_parameter_set(records, tmp_path, capsys):
    _, _, field, _ = records
    _one_line_error(capsys, ["estimate", "--data", str(field), "--params", "paper:dp", "--estimator", "ekf",
                             "--out", str(tmp_path / "e")], "does not match the 'paper:dp' parameter set")


def _mah_copy(src, dst, with_reference: bool) -> str:
    """``src`` written again with its sidecar's capacity in mAh (× 1000), with or without the reference SOC."""
    from socbench.datasets import load

    p = load(src)
    if not with_reference:
        p = Profile(p.time_s, p.current_a, p.voltage_v, meta=p.meta)
    write_canonical(p, dst)
    side = json.loads(dst.with_suffix(".json").read_text())
    side["capacity_ah"] *= 1000.0
    dst.with_suffix(".json").write_text(json.dumps(side))
    return str(dst)


def test_a_capacity_in_mah_is_said_not_crashed_on(records, tmp_path, capsys):
    d, hppc, field, _ = records
    q_mah = 1000.0 * ISSUE_CELL.capacity_ah
    _one_line_error(capsys, ["fit", "--data", str(hppc), "--model", "thevenin", "--out", str(tmp_path / "x.json"),
                             "--capacity", f"{q_mah:g}"], "too narrow for SOC-dependent parameters", "mAh")
    bare = _mah_copy(hppc, tmp_path / "bare.csv", with_reference=False)
    _one_line_error(capsys, ["fit", "--data", bare, "--model", "thevenin", "--out", str(tmp_path / "x.json")],
                    "too narrow", f"{q_mah:.4g} Ah")
    # with a reference SOC that contradicts the capacity, a warning says so before the fit refuses the axis
    ref = _mah_copy(hppc, tmp_path / "ref.csv", with_reference=True)
    _one_line_error(capsys, ["fit", "--data", ref, "--model", "thevenin", "--out", str(tmp_path / "y.json")],
                    "too narrow")
    assert main(["fit", "--data", ref, "--model", "thevenin", "--out", str(tmp_path / "y.json")]) == 2
    assert "the reference SOC moves 100 points but the current column counts 0.1 points of 3300 Ah" in \
        capsys.readouterr().err
    # the diagnosis finds no record with load at that capacity, and says the capacity is why
    _one_line_error(capsys, ["diagnose", "--fit", ref, "--eval", str(field), "--model", "thevenin",
                             "--out", str(tmp_path / "d")], "is the declared capacity right?", "of 3300 Ah")


def test_an_evaluation_record_with_a_day_long_pause(records, tmp_path, capsys):
    """A drive record logged for two hours, a day at rest with the logger off, and two hours more: diagnosed, every
    held-out block holding samples."""
    from socbench.datasets import load

    d, hppc, field, _ = records
    p = load(field)
    t = p.time_s.copy()
    half = int(np.searchsorted(t, t[0] + 2 * 3600.0))
    i = p.current_a.copy()
    i[half - 600:half + 600] = 0.0  # at rest on both sides of the pause (the cell held, the current bridges it)
    t[half:] += 86400.0
    paused = write_canonical(Profile(t, i, p.voltage_v, soc_ref=p.soc_ref, meta=p.meta), tmp_path / "paused.csv")
    out = tmp_path / "d"
    assert main(["diagnose", "--fit", str(hppc), "--eval", str(paused), "--model", "thevenin", "--out", str(out),
                 "--no-figures"]) == 0, capsys.readouterr().err
    split = json.loads((out / "diagnosis.json").read_text())["split"]
    assert "equal recorded duration" in split["note"]
    assert all(len(r["block_starts_s"]) == split["folds"] for r in split["records"])


def _rewritten(src, dst, edit) -> str:
    """``src``'s CSV text with ``edit(header, rows)`` applied (lists of cells), its sidecar copied."""
    lines = src.read_text().splitlines()
    header, rows = lines[0].split(","), [ln.split(",") for ln in lines[1:]]
    header, rows = edit(header, rows)
    dst.write_text("\n".join(",".join(r) for r in [header, *rows]) + "\n")
    dst.with_suffix(".json").write_text(src.with_suffix(".json").read_text())
    return str(dst)


def test_time_in_milliseconds_is_said_where_the_reference_shows_it(records, tmp_path, capsys):
    d, _, field, _ = records

    def to_ms(header, rows):
        k = header.index("time_s")
        for r in rows:
            r[k] = repr(1000.0 * float(r[k]))
        return header, rows

    ms = _rewritten(field, tmp_path / "ms.csv", to_ms)
    assert main(["simulate", "--data", ms, "--params", str(d / "p.json"), "--json", str(tmp_path / "m.json")]) == 0
    err = capsys.readouterr().err
    assert "time in ms, current in mA or a capacity too small?" in err, err
    assert float(re.search(r"(\d+)× the", err).group(1)) >= 1000.0, err  # ms: at least the thousandfold
    # the record as it was: no such warning
    assert main(["simulate", "--data", str(field), "--params", str(d / "p.json"), "--json",
                 str(tmp_path / "m.json")]) == 0
    assert "time in ms" not in capsys.readouterr().err


def test_an_hppc_with_time_in_milliseconds_and_no_reference(records, tmp_path, capsys):
    """Without a reference SOC to compare, the fit's refusal says what the count shows: far more than the capacity."""
    _, hppc, _, _ = records

    def to_ms_without_reference(header, rows):
        k, z = header.index("time_s"), header.index("soc_ref")
        for r in rows:
            r[k] = repr(1000.0 * float(r[k]))
        return [c for j, c in enumerate(header) if j != z], [[c for j, c in enumerate(r) if j != z] for r in rows]

    ms = _rewritten(hppc, tmp_path / "hppc_ms.csv", to_ms_without_reference)
    line = _one_line_error(capsys, ["fit", "--data", ms, "--model", "thevenin", "--out", str(tmp_path / "p.json")],
                           "hppc_ms.csv", "no HPPC rest points", "time in ms (column 'time_s')")
    assert float(re.search(r"counts (\d+)× the capacity", line).group(1)) >= 1000.0


def test_a_missing_or_repeated_canonical_column_is_named(records, tmp_path, capsys):
    d, _, field, _ = records

    def drop_current(header, rows):
        k = header.index("current_a")
        return [c for j, c in enumerate(header) if j != k], [[c for j, c in enumerate(r) if j != k] for r in rows]

    def voltage_twice(header, rows):
        return header + ["voltage_v"], [r + ["3.0"] for r in rows]

    for edit, words in ((drop_current, ("column 'current_a'", "its first line reads 'time_s,",
                                        "this one has no 'current_a'")),
                        (voltage_twice, ("column 'voltage_v'", "appears more than once"))):
        path = _rewritten(field, tmp_path / f"{edit.__name__}.csv", edit)
        _one_line_error(capsys, ["simulate", "--data", path, "--params", str(d / "p.json")], path, *words)


def test_a_set_of_another_model_under_this_ones_name_is_said(records, tmp_path, capsys):
    """A Thevenin set labelled "rint": the Rint model runs without R1 and C1, and one warning says so."""
    d, _, field, good = records
    relabelled = {**good, "model": "rint"}
    path = tmp_path / "rint.json"
    path.write_text(json.dumps(relabelled))
    assert main(["simulate", "--data", str(field), "--params", str(path), "--json", str(tmp_path / "m.json")]) == 0
    err = capsys.readouterr().err
    assert "model 'rint' does not use the parameter(s) C1, R1" in err, err
    assert main(["simulate", "--data", str(field), "--params", str(d / "p.json"), "--json",
                 str(tmp_path / "m.json")]) == 0
    assert "does not use" not in capsys.readouterr().err


# ----------------------------------------------------------------------------------- other commands and formats
def test_an_output_file_name_taken_by_a_folder_and_the_files_mode(records, tmp_path, capsys):
    """A folder where ``estimate.csv`` goes: one line, exit 2 (was an internal error after the run). The files
    written get the mode a plain write gives under the umask (``mkstemp`` alone left them 0600)."""
    import os

    from socbench.io import atomic_write_text

    d, _, field, _ = records
    out = tmp_path / "e"
    (out / "estimate.csv").mkdir(parents=True)
    _one_line_error(capsys, ["estimate", "--data", str(field), "--params", str(d / "p.json"), "--estimator", "ekf",
                             "--out", str(out)], "estimate.csv", "a folder of that name is in the way")
    mask = os.umask(0o022)
    try:
        atomic_write_text(tmp_path / "m.txt", "x")
    finally:
        os.umask(mask)
    assert (tmp_path / "m.txt").stat().st_mode & 0o777 == 0o666 & ~mask


def test_a_scenario_file_that_is_not_text(tmp_path, capsys):
    path = tmp_path / "bin.toml"
    path.write_bytes(b"\xff\xfe\x00bin")
    _one_line_error(capsys, ["scenarios", str(path)], str(path), "not UTF-8 text")


def test_diagnose_says_what_its_evaluation_records_cannot_test(records, tmp_path, capsys):
    """``--effects ,`` is empty (the fit test read it as none, the search as all); the fit record given as --eval too,
    and records at rest throughout, each get one warning."""
    from socbench.datasets import load

    d, hppc, field, _ = records
    _one_line_error(capsys, ["diagnose", "--fit", str(hppc), "--eval", str(field), "--model", "thevenin", "--out",
                             str(tmp_path / "x"), "--effects", ","], "--effects is empty")
    assert main(["diagnose", "--fit", str(hppc), "--eval", str(hppc), "--model", "thevenin", "--out",
                 str(tmp_path / "same"), "--no-figures"]) == 0
    assert "given as --fit and as --eval" in capsys.readouterr().err
    p = load(field)
    rest = write_canonical(Profile(p.time_s, 0.0 * p.current_a, p.voltage_v, meta=p.meta), tmp_path / "rest.csv")
    main(["diagnose", "--fit", str(hppc), "--eval", str(rest), "--model", "thevenin", "--out", str(tmp_path / "r"),
          "--no-figures"])
    assert "at rest throughout" in capsys.readouterr().err
    assert main(["diagnose", "--fit", str(hppc), "--eval", str(field), "--model", "thevenin", "--out",
                 str(tmp_path / "ok"), "--no-figures"]) == 0
    err = capsys.readouterr().err
    assert "at rest throughout" not in err and "given as --fit" not in err


def test_a_bad_cell_is_quoted_short():
    from socbench.errors import CELL_SHOWN, shown

    assert shown(np.float64(np.nan)) == "empty or NaN" and shown(None) == "empty or NaN"
    assert shown(np.float64(np.inf)) == "inf" and shown("ERR") == "'ERR'"
    long = shown("2" + "\x00" * 16000)
    assert len(long) == CELL_SHOWN + 1 and long.endswith("…")


def test_a_corrupt_events_file_beside_the_dji_telemetry(data_dir, tmp_path, capsys):
    src = data_dir / "uav_dji_m100"
    # a copy, not a link: the loader reads the events beside the telemetry file it resolves
    shutil.copy(src / "battery_telemetry_all_flights.csv", tmp_path)
    events = (src / "flight_mode_events_all_flights.csv").read_text().splitlines()
    k = events[0].split(",").index("to_mode")
    cut = [",".join(c for j, c in enumerate(line.split(",")) if j != k) for line in events]
    (tmp_path / "flight_mode_events_all_flights.csv").write_text("\n".join(cut) + "\n")
    _one_line_error(capsys, ["simulate", "--data", str(tmp_path / "battery_telemetry_all_flights.csv"),
                             "--params", "paper:thevenin"], "flight_mode_events_all_flights.csv",
                    "column 'to_mode'", "missing column")


def test_a_leaderboard_whose_every_cell_fails_on_its_record(data_dir, tmp_path, capsys, monkeypatch):
    """The CALCE US06 record with a NaN voltage: the study still writes its report, and exits 2 naming the file,
    the column and the row (it exited 0, the reason only in leaderboard.md)."""
    calce = tmp_path / "data" / "calce_a123_lfp"
    calce.mkdir(parents=True)
    for f in (data_dir / "calce_a123_lfp").iterdir():
        (calce / f.name).symlink_to(f)
    us06 = calce / "A1-00x_20degC_US06_from_full.csv"
    lines = us06.read_text().splitlines()
    us06.unlink()
    k = lines[0].split(",").index("Voltage_V")
    row = lines[100].split(",")
    row[k] = "NaN"
    lines[100] = ",".join(row)
    us06.write_text("\n".join(lines) + "\n")
    monkeypatch.setenv("SOCBENCH_DATA_DIR", str(tmp_path / "data"))
    line = _one_line_error(capsys, ["leaderboard", "--models", "thevenin", "--estimators", "ekf", "--scenarios",
                                    "calce-us06", "--seeds", "1", "--backend", "serial", "--no-figures", "--out",
                                    str(tmp_path / "lb")], "every cell failed on its input", "column 'Voltage_V'")
    assert "row 100" in line
    assert (tmp_path / "lb" / "leaderboard.md").exists()


def test_a_record_of_one_sample(records, tmp_path, capsys):
    _, hppc, _, _ = records
    one = tmp_path / "one.csv"
    one.write_text("\n".join(hppc.read_text().splitlines()[:2]) + "\n")
    for argv in (["simulate", "--data", str(one), "--params", "paper:thevenin"],
                 ["estimate", "--data", str(one), "--params", "paper:thevenin", "--estimator", "ekf", "--out",
                  str(tmp_path / "e")]):
        _one_line_error(capsys, argv, "one.csv", "column 'time_s'", "1 sample")


def test_a_sidecar_with_a_byte_order_mark_and_a_float_cell_count(records, tmp_path):
    from socbench.datasets import load
    from socbench.errors import DataError

    _, hppc, _, _ = records
    shutil.copy(hppc, tmp_path / "r.csv")
    meta = {**json.loads(hppc.with_suffix(".json").read_text()), "n_series": 1.0}
    (tmp_path / "r.json").write_bytes(b"\xef\xbb\xbf" + json.dumps(meta).encode())
    p = load(tmp_path / "r.csv")
    assert p.meta.n_series == 1 and isinstance(p.meta.n_series, int)
    assert p.meta.capacity_ah == pytest.approx(meta["capacity_ah"])
    (tmp_path / "r.json").write_text(json.dumps({**meta, "n_series": 1.5}))
    with pytest.raises(DataError, match="n_series must be a positive integer"):
        load(tmp_path / "r.csv")


@pytest.mark.parametrize("option, value", [("--voltage-sd", "nan"), ("--current-sd", "inf"), ("--voltage-sd", "-1")])
def test_a_sensor_noise_that_is_not_a_number(records, tmp_path, capsys, option, value):
    _, hppc, _, _ = records
    line = _one_line_error(capsys, ["estimate", "--data", str(hppc), "--params", "paper:thevenin", "--estimator",
                                    "ekf", "--out", str(tmp_path / "e"), option, value], option)
    assert "SensorNoise" not in line


def test_dji_repeats_and_disorder_are_said(data_dir, tmp_path):
    import warnings

    from socbench.datasets.dji import load_dji
    from socbench.errors import SocbenchWarning

    lines = (data_dir / "uav_dji_m100" / "battery_telemetry_all_flights.csv").read_text().splitlines()
    repeated = lines[:6] + [lines[5]] + lines[6:]  # a record logged twice
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "battery_telemetry_all_flights.csv").write_text("\n".join(repeated) + "\n")
    with pytest.warns(SocbenchWarning, match=r"row 7: 1 record\(s\) repeat a time stamp"):
        p = load_dji(tmp_path / "a" / "battery_telemetry_all_flights.csv")
    assert p.meta.extra["dropped"]["duplicate_time"] == 1
    swapped = lines[:5] + [lines[6], lines[5]] + lines[7:]  # two records of one segment swapped
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "battery_telemetry_all_flights.csv").write_text("\n".join(swapped) + "\n")
    with pytest.warns(SocbenchWarning, match="not in time order; they are sorted"):
        q = load_dji(tmp_path / "b" / "battery_telemetry_all_flights.csv")
    assert np.all(np.diff(q.time_s) > 0)
    with warnings.catch_warnings():  # the published file: neither
        warnings.simplefilter("error", SocbenchWarning)
        load_dji(data_dir / "uav_dji_m100")
