"""Dataset loaders: every source becomes a :class:`~socbench.profile.Profile` with units and sign normalised.

``load(path, fmt="auto")`` dispatches on ``fmt`` (see :data:`FORMATS`); ``auto`` detects the format from the file and
says which one it picked. ``builtin:NAME`` names an embedded profile (``builtin:hppc``, ``builtin:1c``).
"""

from __future__ import annotations

import importlib
from pathlib import Path

from ..errors import DataError
from ..profile import Profile

#: format name -> "module:function" taking (path) and returning a Profile
FORMATS: dict[str, str] = {
    "canonical": "socbench.datasets.canonical:load_canonical",
    "panasonic-mat": "socbench.datasets.panasonic:load_panasonic",
    "calce-csv": "socbench.datasets.calce:load_calce",
    "nissan-leaf": "socbench.datasets.nissan_leaf:load_nissan_leaf",
    "dji-log": "socbench.datasets.dji:load_dji",
    "cmu-evtol": "socbench.datasets.cmu_evtol:load_cmu_evtol",
}


def _loader(fmt: str):
    try:
        module, fn = FORMATS[fmt].split(":")
    except KeyError:
        raise DataError(f"unknown format '{fmt}'; known: auto, {', '.join(FORMATS)}") from None
    return getattr(importlib.import_module(module), fn)


def detect_format(path) -> str:
    """The one format whose ``sniff(path)`` says yes; a :class:`DataError` when none or several do.

    Never guesses: an ambiguous file must be given an explicit ``--format``.
    """
    p = Path(path)
    if p.is_file() and p.stat().st_size == 0:  # say so, rather than that no format recognises it
        raise DataError("empty file", file=str(path))
    hits = []
    for fmt, target in FORMATS.items():
        module = importlib.import_module(target.split(":")[0])
        sniff = getattr(module, "sniff", None)
        try:
            if sniff is not None and sniff(path):
                hits.append(fmt)
        except OSError as exc:
            raise DataError(f"cannot read ({exc.strerror or exc})", file=str(path)) from None
    if len(hits) == 2 and "canonical" in hits:
        # the canonical names match in any case; a format that knows this exact header (the Leaf files' time_s …
        # current_A, …) is the more specific reading
        hits.remove("canonical")
    if len(hits) == 1:
        return hits[0]
    if not hits:
        missing = _missing_canonical_column(p)
        raise DataError(f"could not detect the format{_first_line(p)}; a canonical CSV is comma-separated with the "
                        "columns time_s, current_a, voltage_v (temperature_c, soc_ref optional)"
                        + (f", and this one has no '{missing}'" if missing else "")
                        + f"; else pass --format (known: {', '.join(FORMATS)})", file=str(path), column=missing)
    raise DataError(f"ambiguous format: matches {' and '.join(hits)}; pass --format explicitly", file=str(path))


def _missing_canonical_column(path: Path) -> str | None:
    """The one required column of the canonical CSV a ``.csv`` header lacks where it names the other two (what
    :func:`detect_format`'s refusal then names), else None: a file with a time and a voltage column but no current
    column reads as that, not only as a format none knows."""
    from .canonical import REQUIRED
    from .header import header_columns

    if path.suffix.lower() != ".csv":
        return None
    try:
        cols = {c.lower() for c in header_columns(path)}
    except (OSError, UnicodeDecodeError):
        return None
    missing = [c for c in REQUIRED if c not in cols]
    return missing[0] if len(missing) == 1 else None


def _first_line(path: Path) -> str:
    """``": its first line reads '…'"`` for a text file (what the user sees of a header none of the formats knows),
    else ``""``."""
    try:
        with open(path, encoding="utf-8-sig") as fh:
            line = fh.readline(FIRST_LINE_SHOWN + 1).strip()
    except (OSError, UnicodeDecodeError):
        return ""
    if not line or not line.isprintable():
        return ""
    if len(line) > FIRST_LINE_SHOWN:
        line = line[:FIRST_LINE_SHOWN] + "…"
    return f": its first line reads {line!r}"


#: characters of an unrecognised file's first line the error quotes
FIRST_LINE_SHOWN = 100


#: the fewest samples a record file may hold: one sample has no time step to simulate, filter or fit over
MIN_SAMPLES = 2


def load(path, fmt: str = "auto") -> Profile:
    """Load ``path`` as a Profile. ``builtin:hppc`` / ``builtin:1c`` give the paper pack's embedded profiles."""
    text = str(path)
    if text.startswith("builtin:"):
        return builtin_profile(text.split(":", 1)[1])
    p = Path(path)
    if not p.exists():
        raise DataError("file not found", file=text)
    if fmt == "auto":
        fmt = detect_format(p)
    try:
        profile = _loader(fmt)(p)
    except DataError as exc:
        raise exc.with_file(text) from None
    if profile.n < MIN_SAMPLES:
        raise DataError(f"{profile.n} sample: a record needs at least {MIN_SAMPLES} to step a model through",
                        file=text, column="time_s")
    profile.meta.extra.setdefault("format", fmt)  # which loader read it (auto says what it picked)
    return profile


def builtin_profile(name: str) -> Profile:
    """Embedded load profiles on the paper pack, simulated with its Thevenin Table 3 set for a voltage column."""
    from .. import loads
    from ..models import make_model, paper_pack, paper_params

    pack = paper_pack()
    makers = {
        "hppc": lambda: loads.hppc(pack["capacity_ah"], n_series=pack["n_series"]),
        "1c": lambda: loads.constant_current(pack["capacity_ah"], 1.0, soc_span=0.98, n_series=pack["n_series"]),
    }
    if name not in makers:
        raise DataError(f"unknown built-in profile '{name}'; known: {', '.join(makers)}")
    prof = makers[name]()
    sim = make_model("thevenin", paper_params("thevenin")).simulate(prof, soc0=1.0)
    return prof.with_(voltage_v=sim.voltage_v, soc_ref=sim.soc.clip(0, 1),
                      meta=prof.meta.__class__(name=f"builtin:{name}", source=f"builtin:{name}",
                                               capacity_ah=pack["capacity_ah"], n_series=pack["n_series"],
                                               chemistry=pack["chemistry"]))
