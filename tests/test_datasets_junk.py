"""Property-based: junk fed to the loaders gives a DataError or a clean Profile — never another exception, never NaN."""

from __future__ import annotations

import json
import math
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from socbench.datasets import FORMATS, detect_format, load
from socbench.datasets.calce import load_calce
from socbench.datasets.canonical import load_canonical
from socbench.datasets.cmu_evtol import LAYOUTS as EVTOL_LAYOUTS
from socbench.datasets.cmu_evtol import load_cmu_evtol
from socbench.datasets.nissan_leaf import load_nissan_leaf
from socbench.errors import DataError, SocbenchWarning
from socbench.profile import SOC_WARN_MARGIN, Profile

SETTINGS = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(scope="module")
def workdir():
    with tempfile.TemporaryDirectory() as d:
        yield Path(d)


def _assert_clean(p: Profile) -> None:
    assert isinstance(p, Profile)
    for a in (p.time_s, p.current_a, p.voltage_v, p.temperature_c, p.soc_ref):
        if a is not None:
            assert np.all(np.isfinite(a))
    assert np.all(np.diff(p.time_s) > 0)
    if p.soc_ref is not None:  # kept (with a warning) up to SOC_WARN_MARGIN outside [0, 1]; further out refused
        assert p.soc_ref.min() >= -SOC_WARN_MARGIN and p.soc_ref.max() <= 1 + SOC_WARN_MARGIN
    elif p.soc_ref_error is not None:
        assert p.soc_ref_error.column == "soc_ref" and p.soc_ref_error.row >= 1


def _load_or_dataerror(fn, path):
    """The profile ``fn`` reads from ``path``, clean, or None where it raised a one-line DataError; any warning on the
    way is socbench's own one-line warning (no library warning leaks)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            p = fn(path)
        except DataError as exc:
            assert str(exc)  # a message, one line
            assert "\n" not in str(exc)
            p = None
    for w in caught:
        assert issubclass(w.category, SocbenchWarning), f"{w.category.__name__}: {w.message}"
        assert "\n" not in str(w.message)
    if p is not None:
        _assert_clean(p)
    return p


cell = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.integers(min_value=-10**12, max_value=10**12),
    st.sampled_from(["", "nan", "NaN", "inf", "-inf", "abc", "1e309", "3,7", '"', "NULL", " ", "1.0.0", "0x10"]),
    st.text(max_size=6),
)
names = st.sampled_from(["time_s", "current_a", "voltage_v", "temperature_c", "soc_ref", "current_ma", "Time",
                         "voltage_mv", "soc_pct", "x", "", "time_s "])


def _csv_field(v) -> str:
    text = repr(float(v)) if isinstance(v, (float, np.floating)) else str(v)
    if any(ch in text for ch in ',"\n\r'):
        text = '"' + text.replace('"', '""') + '"'
    return text


@SETTINGS
@given(data=st.binary(max_size=400))
def test_random_bytes(workdir, data):
    for name in ("bytes.csv", "bytes.parquet"):
        path = workdir / name
        path.write_bytes(data)
        _load_or_dataerror(load_canonical, path)
        try:
            assert detect_format(path) in FORMATS
        except DataError:
            pass


@st.composite
def tables(draw):
    cols = draw(st.lists(names, min_size=0, max_size=7))
    n = draw(st.integers(min_value=0, max_value=12))
    rows = draw(st.lists(st.lists(cell, min_size=len(cols), max_size=len(cols)), min_size=n, max_size=n))
    return cols, rows


@st.composite
def plausible_tables(draw):
    """Mostly valid canonical tables with a few cells damaged: reaches the unit, sign and Profile checks."""
    n = draw(st.integers(min_value=1, max_value=40))
    t = np.cumsum(draw(st.lists(st.floats(0.0, 5.0), min_size=n, max_size=n)))
    order = draw(st.permutations(range(n))) if draw(st.booleans()) else list(range(n))
    cur = draw(st.lists(st.floats(-10, 10), min_size=n, max_size=n))
    volt = draw(st.lists(st.floats(2.0, 4.5), min_size=n, max_size=n))
    soc = draw(st.lists(st.floats(-0.1, 1.1), min_size=n, max_size=n)) if draw(st.booleans()) else None
    cols = {"time_s": list(t[order]), "current_a": cur, "voltage_v": volt}
    if soc is not None:
        cols["soc_ref"] = soc
    header = draw(st.permutations(list(cols)))
    rows = [[cols[c][k] for c in header] for k in range(n)]
    for _ in range(draw(st.integers(0, 3))):
        r, c = draw(st.integers(0, n - 1)), draw(st.integers(0, len(header) - 1))
        rows[r][c] = draw(cell)
    return header, rows


def _write_table(path: Path, cols, rows, meta=None) -> None:
    lines = [",".join(cols)] + [",".join(_csv_field(v) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    side = path.with_suffix(".json")
    if meta is None:
        side.unlink(missing_ok=True)
    else:
        side.write_text(json.dumps(meta))


sidecars = st.one_of(
    st.none(),
    st.fixed_dictionaries({}, optional={
        "capacity_ah": st.one_of(st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=3), st.none()),
        "n_series": st.one_of(st.integers(-2, 8), st.text(max_size=2), st.booleans()),
        "name": st.text(max_size=5)}),
)


@SETTINGS
@given(table=tables(), meta=sidecars)
def test_random_tables(workdir, table, meta):
    cols, rows = table
    path = workdir / "table.csv"
    _write_table(path, cols, rows, meta)
    _load_or_dataerror(load_canonical, path)


@SETTINGS
@given(table=plausible_tables(), meta=sidecars)
def test_damaged_plausible_tables(workdir, table, meta):
    cols, rows = table
    path = workdir / "plausible.csv"
    _write_table(path, cols, rows, meta)
    p = _load_or_dataerror(load_canonical, path)
    if p is not None:  # what passes is exactly what was written
        assert p.n == len(rows)


def test_plausible_tables_do_load(workdir):
    """The generator above is not only junk: a clean table of its kind loads (the property is not vacuous)."""
    path = workdir / "clean.csv"
    _write_table(path, ["time_s", "current_a", "voltage_v"], [[k, 1.0, 3.7 - 0.01 * k] for k in range(10)])
    p = load_canonical(path)
    assert p.n == 10 and not math.isnan(p.voltage_v.sum())


@settings(max_examples=60, deadline=None)
@given(table=tables())
def test_source_loaders_on_junk_with_their_headers(workdir, table):
    _, rows = table
    for fn, header in ((load_calce, ["Test_Time_s", "Current_A", "Voltage_V"]),
                       (load_nissan_leaf, ["time_s", "cycle", "step", "step_time_s", "current_A", "voltage_V",
                                           "power_W", "capacity_Ah", "energy_Wh", "mode", "flag"]),
                       *((load_cmu_evtol, list(head)) for head in EVTOL_LAYOUTS.values())):
        path = workdir / "source.csv"
        width = len(header)
        _write_table(path, header, [(list(r) + [0.0] * width)[:width] for r in rows])
        _load_or_dataerror(fn, path)
        _load_or_dataerror(load, path)


@settings(max_examples=40, deadline=None)
@given(data=st.binary(min_size=0, max_size=300))
def test_panasonic_loader_on_junk_bytes(workdir, data):
    path = workdir / "junk.mat"
    path.write_bytes(data)
    with pytest.raises(DataError):
        load(path, "panasonic-mat")


def test_spreadsheet_byte_order_mark_and_empty_file(tmp_path):
    """A canonical CSV saved by a spreadsheet with a UTF-8 byte-order mark is detected and loads with its first column
    intact; an empty file says "empty file", not that no format recognises it."""
    rows = "time_s,current_a,voltage_v\n0,1.0,3.70\n1,1.0,3.69\n2,0.0,3.72\n"
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + rows.encode())
    assert detect_format(bom) == "canonical"
    prof = load(bom)
    np.testing.assert_array_equal(prof.time_s, [0.0, 1.0, 2.0])
    empty = tmp_path / "empty.csv"
    empty.write_bytes(b"")
    with pytest.raises(DataError, match="empty file"):
        load(empty)
