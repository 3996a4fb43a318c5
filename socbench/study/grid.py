"""The study grid: models × estimators × scenarios × seeds, and the keys that name its pieces in the store.

A study has two kinds of work:

* a **fit**: one model fitted on one characterisation test (``identify.fit_model(model, hppc, mode)``). Its key
  hashes the model name, the fit mode and the characterisation's bytes, so scenarios that share a
  truth cell and a characterisation share the fit;
* a **cell**: one estimator run on one model over every seed of one scenario, as one batch. Its key hashes the cell's
  full configuration: model, estimator, scenario name and fingerprint, seeds, the fit key, the store schema and the
  package version. A cell is a deterministic function of that configuration
  (the particle filter's random stream is seeded from the key), so the same key always means the same result, on any
  backend.
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..profile import samples_fingerprint

#: bump when the meaning of a stored record changes (old records are then ignored, never misread)
STORE_SCHEMA = 1

#: the default study (DESIGN.md): every registered model, these four filters, these three scenarios, 10 seeds
DEFAULT_ESTIMATORS = ("coulomb", "ekf", "ukf", "pf")
DEFAULT_SCENARIOS = ("flight-0kg", "flight-10kg", "dji-m100-replay")
DEFAULT_SEEDS = 10


#: the package parts a fit's result depends on (its data is hashed separately), and a cell's
FIT_CODE = ("models", "identify", "ocv.py", "profile.py", "segments.py", "data", "scenarios/measured.py")
CELL_CODE = ("models", "estimators", "scenarios", "metrics.py", "ocv.py", "profile.py", "segments.py", "domain.py",
             "data", "study/cell.py", "socaxis.py")


@functools.cache
def code_fingerprint(parts: tuple) -> str:
    """SHA-256 of the source and data files of the named parts of socbench.

    Stored in every record (not in the key): a result computed by other code is reported as stale, and recomputed on
    request (``recompute_stale``). Editing a filter makes the cells stale (not the fits); editing the identification
    makes both stale. Not in the key, so that an edit elsewhere never throws away an interrupted study's progress.
    """
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for part in parts:
        path = root / part
        files = sorted(path.rglob("*")) if path.is_dir() else [path]
        for f in files:
            if f.is_file() and f.suffix in (".py", ".json", ".toml", ".csv") and "__pycache__" not in f.parts:
                h.update(str(f.relative_to(root)).encode())
                h.update(f.read_bytes())
    return h.hexdigest()


def stable_hash(obj) -> str:
    """SHA-256 (hex) of the canonical JSON of ``obj`` (sorted keys; floats written exactly)."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=_json_default)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return repr(o)


def profile_fingerprint(profile) -> str:
    """SHA-256 of a profile's samples and metadata (:func:`socbench.profile.samples_fingerprint`): two
    characterisations with this hash are the same test. A characterisation made of several records (a measured
    scenario's) brings its own ``fingerprint()``."""
    if hasattr(profile, "fingerprint"):
        return profile.fingerprint()
    return samples_fingerprint(profile)


def parse_names(text: str | None, known: list[str], kind: str, default) -> tuple[str, ...]:
    """``"a,b"`` -> ``("a", "b")`` checked against ``known``; ``None`` -> ``default``. Unknown -> ConfigError."""
    if text is None:
        names = tuple(default)
    else:
        names = tuple(n.strip() for n in str(text).split(",") if n.strip())
        if not names:
            raise ConfigError(f"--{kind}s is empty")
    for n in names:
        if n not in known:
            raise ConfigError(f"unknown {kind} '{n}'; known: {', '.join(known)}")
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise ConfigError(f"{kind} '{dup}' is listed twice")
    return names


@dataclass(frozen=True)
class StudyConfig:
    """What to run. ``seeds`` are the Monte Carlo seeds handed to ``scenario.realize``."""

    models: tuple[str, ...]
    estimators: tuple[str, ...]
    scenarios: tuple[str, ...]
    seeds: tuple[int, ...]
    fit_mode: str = "paper"
    #: extra keyword options per estimator name, part of the cell key (e.g. {"pf": {"n_particles": 200}})
    estimator_options: dict = field(default_factory=dict)
    #: filter covariances: "model" (the noise recipe, socbench.estimators.model_error) or "sensor" (sensor noise only)
    noise: str = "model"

    def __post_init__(self):
        for kind in ("models", "estimators", "scenarios", "seeds"):
            if not getattr(self, kind):
                raise ConfigError(f"a study needs at least one of {kind}")
        if self.noise not in ("model", "sensor"):
            raise ConfigError(f"noise must be 'model' or 'sensor', got {self.noise!r}")
        if len(set(self.seeds)) != len(self.seeds):
            raise ConfigError("seeds must be distinct")

    @property
    def n_cells(self) -> int:
        return len(self.models) * len(self.estimators) * len(self.scenarios)

    def to_dict(self) -> dict:
        return {
            "models": list(self.models),
            "estimators": list(self.estimators),
            "scenarios": list(self.scenarios),
            "seeds": list(self.seeds),
            "fit_mode": self.fit_mode,
            "estimator_options": {k: dict(v) for k, v in self.estimator_options.items()},
            "noise": self.noise,
        }


def fit_config(model: str, char_hash: str, fit_mode: str, version: str) -> dict:
    """The configuration that determines a fit (its key is the hash of this)."""
    return {"kind": "fit", "schema": STORE_SCHEMA, "version": version, "model": model, "mode": fit_mode,
            "characterisation": char_hash}


def cell_config(model: str, estimator: str, scenario: str, scenario_fp: str, seeds, fit_key: str,
                options: dict, version: str, noise: str = "model") -> dict:
    """The configuration that determines a cell (its key is the hash of this)."""
    return {"kind": "cell", "schema": STORE_SCHEMA, "version": version, "model": model,
            "estimator": estimator,
            "scenario": scenario, "scenario_fingerprint": scenario_fp, "seeds": [int(s) for s in seeds],
            "fit": fit_key, "estimator_options": dict(options), "noise": noise}


def seed_from_key(key: str) -> int:
    """A 32-bit seed for the estimator's own random stream (the particle filter), derived from the cell key."""
    return int(key[:8], 16)
