"""The scenario catalog: declarative TOML files shipped in ``socbench/scenarios/catalog/``.

A file names its load, truth, schedule and sensors; anything not given keeps the dataclass default. ``extends =
"other"`` starts from another catalog scenario (or a path relative to the file) and deep-merges the tables over it::

    description = "hexacopter, 10 kg payload, lab instruments"
    kind = "mission"                       # mission | replay | hppc | measured
    group = "measured"                     # optional: a group `socbench leaderboard --scenarios GROUP` runs
    [mission]       payload_kg = 10.0      # socbench.scenarios.mission.Mission
    [vehicle]       ...                    # socbench.scenarios.mission.Vehicle
    [replay]        source = "template"    # socbench.scenarios.scenario.ReplaySpec
    [truth]         ...                    # socbench.scenarios.truth.TruthParams
    [schedule]      ambient_c = 25.0       # socbench.scenarios.schedule.Schedule
    [hppc]          rest_s = 540.0         # socbench.scenarios.scenario.HppcSpec
    [validation]    payloads_kg = [2.0, 8.0]   # socbench.scenarios.scenario.ValidationSpec (the recipe's flights)
    [measured]      dataset = "panasonic_18650pf", record = "...", characterisation = [...]
                                           # socbench.scenarios.scenario.MeasuredSpec (socbench.scenarios.measured)
    [sensors]       dt = 1.0, soc0_error = 0.05, capacity_mismatch = 0.03
    [sensors.current]  noise_sd = 0.2, offset = 0.1, bits = 12, range = [-200.0, 200.0]
    [[sensors.current.faults]]  kind = "offset", value = 1.0, onset_s = 600.0

An unknown key or an impossible value is a one-line :class:`ConfigError` naming the file and the key.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from ..errors import ConfigError
from .config import build
from .mission import Mission, Vehicle
from .scenario import HppcSpec, MeasuredSpec, ReplaySpec, Scenario, ScenarioSpec, ValidationSpec
from .schedule import Schedule
from .sensors import SensorSpec
from .truth import TruthParams

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

TOP_KEYS = ("name", "description", "kind", "group", "extends", "truth", "schedule", "mission", "vehicle", "replay",
            "hppc", "validation", "measured", "sensors")
SECTIONS = {"truth": TruthParams, "schedule": Schedule, "mission": Mission, "vehicle": Vehicle,
            "replay": ReplaySpec, "hppc": HppcSpec, "validation": ValidationSpec,
            "measured": MeasuredSpec}
#: list-valued fields stored as tuples (hashable, frozen specs)
TUPLE_FIELDS = {"replay": ("segments",), "validation": ("payloads_kg",), "measured": ("characterisation", "validation")}


def _catalog_dir():
    return resources.files("socbench.scenarios") / "catalog"


def scenario_names() -> list[str]:
    """Names of the shipped scenarios, sorted."""
    return sorted(p.name[:-5] for p in _catalog_dir().iterdir() if p.name.endswith(".toml"))


def _read(path, label: str) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{label}: file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{label}: is a directory, not a scenario file") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{label}: not UTF-8 text (byte {exc.start}): a scenario file is TOML") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{label}: not valid TOML ({exc})") from None


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _resolve(name_or_path) -> tuple[object, str, str]:
    """(readable path, label for messages, default name)."""
    text = str(name_or_path)
    if text.endswith(".toml") or "/" in text or "\\" in text:
        p = Path(text)
        return p, str(p), p.stem
    entry = _catalog_dir() / f"{text}.toml"
    if not entry.is_file():
        raise ConfigError(f"unknown scenario '{text}'; known: {', '.join(scenario_names())}")
    return entry, f"catalog/{text}.toml", text


def _table(name_or_path, seen: tuple = ()) -> tuple[dict, str, str]:
    path, label, default_name = _resolve(name_or_path)
    if label in seen:
        raise ConfigError(f"{label}: key 'extends': circular ({' -> '.join(seen + (label,))})")
    d = _read(path, label)
    for key in d:
        if key not in TOP_KEYS:
            raise ConfigError(f"{label}: unknown key '{key}' (known: {', '.join(TOP_KEYS)})")
    parent = d.pop("extends", None)
    if parent is not None:
        if not isinstance(parent, str):
            raise ConfigError(f"{label}: key 'extends': must be a scenario name or path")
        if isinstance(path, Path) and (path.parent / parent).exists():
            parent = str(path.parent / parent)
        base, _, _ = _table(parent, seen + (label,))
        base.pop("name", None)
        d = _merge(base, d)
    return d, label, default_name


def load_scenario(name_or_path) -> Scenario:
    """A catalog scenario by name (``flight-0kg``) or a scenario file by path (``my.toml``)."""
    if isinstance(name_or_path, Scenario):
        return name_or_path
    d, label, default_name = _table(name_or_path)
    kw = {}
    for key in ("name", "description", "kind", "group"):
        if key in d:
            if not isinstance(d[key], str):
                raise ConfigError(f"{label}: key '{key}': must be a string")
            kw[key] = d[key]
    for key, cls in SECTIONS.items():
        if key in d:
            if not isinstance(d[key], dict):
                raise ConfigError(f"{label}: key '{key}': must be a table")
            table = dict(d[key])
            for f in TUPLE_FIELDS.get(key, ()):
                if isinstance(table.get(f), list):
                    table[f] = tuple(table[f])
            kw[key] = build(cls, table, key, label, skip=("ocv",) if cls is TruthParams else ())
    if "sensors" in d:
        kw["sensors"] = SensorSpec.from_table(d["sensors"], label)
    kw.setdefault("name", default_name)
    kw["file"] = label
    spec = build(ScenarioSpec, {}, "", label, **kw)
    if spec.kind == "measured":
        from .measured import MeasuredScenario

        return MeasuredScenario(spec)
    return Scenario(spec)


def group_names(group: str) -> list[str]:
    """Catalog scenarios of a group (``measured``), sorted."""
    return [n for n in scenario_names() if load_scenario(n).group == group]
