"""Panasonic 18650PF (Kollmeyer, Mendeley doi:10.17632/wykht8y7tg.1): the original MATLAB ``.mat`` files.

Each file holds one struct ``meas`` whose fields are N×1 columns: ``Time`` [s], ``Voltage`` [V], ``Current`` [A,
**negative = discharge**], ``Ah`` (amp-hour counter reset before each test, negative while discharging),
``Battery_Temp_degC`` (case thermocouple) and others we do not use (``Chamber_Temp_degC`` is NaN or unreliable in
several files, so it is ignored).

What the loader does on the way in:

* current sign flipped to socbench's convention (positive = discharge);
* repeated time stamps: the tester writes two records with the same ``Time`` at step boundaries (up to 153 per HPPC
  file, sometimes with different current: end of one step, start of the next). Under a zero-order hold the first of
  the pair lasts zero seconds, so the *last* record of each equal-stamp run is kept; the number dropped is recorded in
  ``meta.extra["duplicate_stamps_dropped"]``. Time going backwards is still an error;
* reference SOC from the counter: ``soc = 1 + (Ah - Ah[0]) / C`` (every test starts from a full charge: 1C to 4.2 V,
  50 mA cut-off), with ``C`` chosen as below and stored as ``meta.capacity_ah``.

Which capacity ``C``:

* HPPC and drive cycles (US06, HWFET, LA92, NN, Cycle_n): the largest charge discharged from full at the same
  temperature among the HPPC and drive-cycle files of this dataset (:data:`CAPACITY_AH`, measured from the ``Ah``
  columns; a test that discharges more than the table, e.g. a file not in our copy, uses its own discharge). The
  HPPC test ends at its "0 % SOC" pulse set, so at most temperatures its discharge is that maximum; at 0 °C the
  Cycle_1 run went deeper. The two rising-temperature runs are each alone in their folder, so their own discharge
  defines ``C`` and their SOC ends at 0.
* capacity tests (C/20 OCV, 1C ``Dis1C``): measuring the capacity is what these tests do, so ``C`` is the test's own
  discharge and its SOC runs 1 → 0 (the C/20 test then climbs back on its charge branch).
* ``dis5_10p`` (the discharges between the 25 °C HPPC pulse sets, recorded apart): its counter does not start at a
  full charge (first value −0.124 Ah, with a jump mid-file), so no reference SOC is attached.

The HPPC files hold the pulses and rests only: the time axis has long gaps where the inter-pulse discharges ran
(``Profile.gaps()`` lists them). Only the counter knows the charge removed in the gaps, which is why SOC comes from it.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import DataError, first_line
from ..profile import Profile, ProfileMeta
from .units import check_cell_units

#: Largest discharge from full [Ah] among the HPPC and drive-cycle files of each temperature folder of the dataset
#: (``Ah[0] - min(Ah)``; the file that sets it in brackets). tests/test_datasets.py re-measures these from the files.
CAPACITY_AH: dict[str, float] = {
    "25degC": 2.77280,  # 03-11-17_08.47_25degC_5Pulse_HPPC
    "10degC": 2.62175,  # 03-27-17_09.06_10degC_5Pulse_HPPC
    "0degC": 2.61000,  # 05-30-17_12.56_0degC_Cycle_1 (its HPPC reached 2.47573)
    "n10degC": 2.33032,  # 06-07-17_12.29_n10degC_5pulse_HPPC
    "n20degC": 2.18218,  # 06-15-17_11.31_n20degC_5Pulse_HPPC
    "10degC_trise": 2.32001,  # 07-09-17_19.11_10degC_trise_Cycle_1 (alone in its folder)
    "n20degC_trise": 2.32005,  # 07-01-17_19.59_n20degC_trise_US06 (alone in its folder)
}

NOMINAL_CAPACITY_AH = 2.9
CHEMISTRY = "NCA"
REQUIRED_FIELDS = ("Time", "Current", "Voltage", "Ah")
#: Plausibility ranges of one 18650PF cell on this tester (25 A channel, 2.5-4.2 V window).
VOLTAGE_RANGE = (1.5, 4.6)
MAX_ABS_CURRENT = 40.0

# test type from the file name: (pattern, canonical name); first match wins
_TESTS = (
    (re.compile(r"hppc", re.I), "HPPC"),
    (re.compile(r"dis5_10p", re.I), "HPPC inter-pulse discharge"),
    (re.compile(r"c20_?ocv", re.I), "C20 OCV"),
    (re.compile(r"dis1c", re.I), "1C capacity"),
    (re.compile(r"us06", re.I), "US06"),
    (re.compile(r"hwft", re.I), "HWFET"),
    (re.compile(r"la92", re.I), "LA92"),
    (re.compile(r"udds", re.I), "UDDS"),
    (re.compile(r"_nn_", re.I), "NN"),
    (re.compile(r"cycle_?\d", re.I), "Cycle"),
)
_CAPACITY_TESTS = ("C20 OCV", "1C capacity")
_TEMP_RE = re.compile(r"(?:^|[_/\\])(n|-)?(\d+)d(?:eg)?C", re.I)


def test_type(path) -> str:
    """The test a Panasonic file holds, from its name: ``HPPC``, ``US06``, ``C20 OCV``, ``1C capacity``, ..."""
    name = Path(path).name
    for pattern, test in _TESTS:
        if pattern.search(name):
            return test
    return "unknown"


test_type.__test__ = False  # not a pytest test despite the name


def temperature_tag(path) -> str | None:
    """``"25degC"``, ``"n10degC"``, ``"10degC_trise"``...: from the file name, else from its folder."""
    path = Path(path)
    for text in (path.name, path.parent.name):
        m = _TEMP_RE.search("_" + text)
        if m:
            tag = f"{'n' if m.group(1) else ''}{int(m.group(2))}degC"
            trise = "trise" in path.name.lower() or "trise" in path.parent.name.lower()
            return tag + ("_trise" if trise else "")
    return None


def _tag_celsius(tag: str) -> float:
    m = re.match(r"(n?)(\d+)degC", tag)
    return -float(m.group(2)) if m.group(1) else float(m.group(2))


def find_panasonic(data_dir, temp: str = "25degC", test: str | None = None) -> list[Path]:
    """The ``.mat`` files of one temperature folder, optionally only one test type, sorted by name.

    ``data_dir`` is the dataset folder or its parent (the one holding ``panasonic_18650pf``). ``temp`` is a folder
    name (``"25degC"``, ``"n10degC"`` or ``"-10degC"``, ``"10degC_Trise"``). ``test`` matches :func:`test_type`
    case-insensitively (``"US06"``, ``"HPPC"``, ``"C20 OCV"``, ``"1C capacity"``, ``"Cycle"``...).
    """
    root = Path(data_dir)
    if (root / "panasonic_18650pf").is_dir():
        root = root / "panasonic_18650pf"
    wanted = str(temp).lower().replace("-", "n")
    folders = [d for d in root.iterdir() if d.is_dir() and d.name.lower().replace("-", "n") == wanted] \
        if root.is_dir() else []
    if not folders:
        raise DataError(f"no Panasonic temperature folder '{temp}' under {root}")
    files = sorted(folders[0].glob("*.mat"))
    if test is not None:
        files = [f for f in files if test_type(f).lower() == str(test).lower()]
    return files


def panasonic_tests(data_dir, temp: str = "25degC") -> dict[str, list[Path]]:
    """``{test type: [files]}`` for one temperature folder."""
    out: dict[str, list[Path]] = {}
    for f in find_panasonic(data_dir, temp):
        out.setdefault(test_type(f), []).append(f)
    return out


def sniff(path) -> bool:
    """A MATLAB file holding a variable ``meas``."""
    path = Path(path)
    if path.suffix.lower() != ".mat":
        return False
    try:
        from scipy.io import whosmat

        return any(name == "meas" for name, _, _ in whosmat(str(path)))
    except Exception:  # not a readable MAT file: simply not ours
        return False


def _read_struct(path: Path) -> dict[str, np.ndarray]:
    from scipy.io import loadmat

    src = str(path)
    try:
        mat = loadmat(src)
    except Exception as exc:  # scipy raises ValueError, TypeError, MatReadError... on non-MAT or truncated input
        raise DataError(f"not a readable MATLAB .mat file ({first_line(exc)})", file=src) from None
    if "meas" not in mat:
        found = [k for k in mat if not k.startswith("__")]
        raise DataError(f"no struct 'meas' (variables: {', '.join(found) or 'none'}); not a Panasonic 18650PF file",
                        file=src)
    meas = mat["meas"]
    if meas.dtype.names is None or meas.size != 1:
        raise DataError("'meas' is not a 1×1 struct", file=src)
    meas = meas.ravel()[0]
    cols: dict[str, np.ndarray] = {}
    n = None
    for name in REQUIRED_FIELDS + ("Battery_Temp_degC",):
        if name not in meas.dtype.names:
            if name == "Battery_Temp_degC":
                continue
            raise DataError("missing field in struct 'meas'", file=src, column=name)
        raw = np.asarray(meas[name])
        if raw.dtype.kind not in "fiu":
            raise DataError(f"field is not numeric (dtype {raw.dtype})", file=src, column=name)
        values = raw.ravel().astype(float)
        if n is None:
            n = values.size
        elif values.size != n:
            raise DataError(f"has {values.size} samples but Time has {n}", file=src, column=name)
        bad = ~np.isfinite(values)
        if bad.any():
            raise DataError("NaN or infinite value", file=src, column=name, row=int(np.argmax(bad)) + 1)
        cols[name] = values
    if not n:
        raise DataError("no samples", file=src, column="Time")
    return cols


def _check_ranges(cols: dict[str, np.ndarray], src: str) -> None:
    check_cell_units(cols["Voltage"], cols["Current"], voltage_range=VOLTAGE_RANGE, max_abs_current=MAX_ABS_CURRENT,
                     cell="2.9 Ah cell", src=src, voltage_column="Voltage", current_column="Current")


def _check_sign_against_counter(cols: dict[str, np.ndarray], src: str) -> None:
    """The tester's Ah counter falls while it discharges: a current whose sign disagrees with it was flipped."""
    d_ah = np.diff(cols["Ah"])
    i_next = cols["Current"][1:]
    votes = (np.abs(d_ah) > 1e-5) & (np.abs(i_next) > 0.05)
    if votes.sum() >= 20:
        agree = np.sign(d_ah[votes]) == np.sign(i_next[votes])
        if agree.mean() < 0.2:
            k = int(np.nonzero(votes)[0][np.argmax(~agree)]) + 1
            raise DataError("current sign disagrees with the Ah counter (this dataset: negative = discharge)",
                            file=src, column="Current", row=k + 1)


def _drop_repeated_stamps(cols: dict[str, np.ndarray], src: str) -> int:
    t = cols["Time"]
    dt = np.diff(t)
    back = dt < 0
    if back.any():
        k = int(np.argmax(back))
        raise DataError(f"time goes backwards ({t[k]:g} s then {t[k + 1]:g} s)", file=src, column="Time", row=k + 2)
    keep = np.ones(t.size, dtype=bool)
    keep[:-1] = dt > 0  # keep the last record of a run of equal stamps
    dropped = int(t.size - keep.sum())
    if dropped:
        for name in list(cols):
            cols[name] = cols[name][keep]
    return dropped


def capacity_for(path, ah: np.ndarray) -> tuple[float | None, str]:
    """``(C, where it comes from)`` for the reference SOC of ``path`` (see the module docstring)."""
    test = test_type(path)
    own = float(ah[0] - ah.min())
    if test == "HPPC inter-pulse discharge":
        return None, "no reference SOC: counter not referenced to a full charge"
    if test in _CAPACITY_TESTS:
        return own, f"own discharge of this {test} test"
    tag = temperature_tag(path)
    table = CAPACITY_AH.get(tag or "")
    if table is None:
        return (own, "own discharge (temperature not in the capacity table)") if own > 0 else (None, "no discharge")
    if own > table:
        return own, f"own discharge (exceeds the {tag} table value {table:g} Ah)"
    return table, f"largest HPPC/drive-cycle discharge at {tag} (CAPACITY_AH)"


def load_panasonic(path) -> Profile:
    """Load one original Panasonic 18650PF ``.mat`` file as a :class:`Profile` (positive = discharge)."""
    path = Path(path)
    src = str(path)
    cols = _read_struct(path)
    _check_ranges(cols, src)
    _check_sign_against_counter(cols, src)
    dropped = _drop_repeated_stamps(cols, src)
    ah = cols["Ah"]
    capacity, cap_note = capacity_for(path, ah)
    soc = None
    if capacity is not None and capacity > 0:
        soc = 1.0 + (ah - ah[0]) / capacity
        # the counter has 5 decimals: rounding may overshoot [0, 1] by ~1e-5; clip only that, never more
        soc = np.where(np.abs(soc - np.clip(soc, 0.0, 1.0)) < 1e-4, np.clip(soc, 0.0, 1.0), soc)
    tag = temperature_tag(path)
    test = test_type(path)
    extra = {
        "test": test,
        "temperature_tag": tag,
        "ambient_temperature_c": _tag_celsius(tag) if tag else None,
        "capacity_source": cap_note,
        "duplicate_stamps_dropped": dropped,
        # the reference SOC is 1 − Ah/C counted from full with this C (socbench.socaxis converts to a model's axis)
        **({"soc_ref_capacity_ah": float(capacity)} if soc is not None else {}),
        "dataset": "Panasonic 18650PF (Kollmeyer 2018, doi:10.17632/wykht8y7tg.1)",
        "nominal_capacity_ah": NOMINAL_CAPACITY_AH,
    }
    meta = ProfileMeta(name=path.stem, source=src, capacity_ah=capacity if capacity else NOMINAL_CAPACITY_AH,
                       n_series=1, chemistry=CHEMISTRY, extra=extra)
    return Profile(cols["Time"] - cols["Time"][0], -cols["Current"], cols["Voltage"], cols.get("Battery_Temp_degC"),
                   soc, meta)
