"""The result store: one small JSON file per finished fit and per finished cell, written atomically when it is done.

Layout under the store folder (``<out>/store`` for the CLI)::

    study.json            the configuration of the latest study run into this store
    fits/<key>.json       a fitted parameter set (or the fit's error), keyed by the fit's configuration hash
    cells/<key>.json      a finished cell: its leaderboard row, a compact trace for the figures, errors, timing
    runs/<run_id>.json    which cells each invocation computed and which it reused (the audit trail of resumes)

Every file goes through :func:`socbench.io.atomic_write_text` (temporary file, fsync, rename), so a study killed at any
instant leaves either the whole file or none of it. A record is only trusted when it parses and its ``key`` and
``schema`` match; anything else (including a stray temporary file of a killed writer) is ignored and recomputed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from ..io import atomic_write_text
from .grid import STORE_SCHEMA


def _clean(obj):
    """JSON-safe copy: NaN/inf become None (JSON has no NaN, and the leaderboard must never carry one)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    return obj


class Store:
    """A folder of per-fit and per-cell JSON records (see the module docstring)."""

    def __init__(self, root):
        self.root = Path(root)
        for sub in ("fits", "cells", "runs"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self._remove_stale_temporaries()

    def _remove_stale_temporaries(self) -> None:
        # A writer killed between mkstemp and rename leaves ".<name>.<random>.tmp"; it was never a result.
        for sub in ("fits", "cells", "runs", "."):
            for tmp in (self.root / sub).glob(".*.tmp"):
                try:
                    tmp.unlink()
                except FileNotFoundError:
                    pass

    # ------------------------------------------------------------------ paths
    def fit_path(self, key: str) -> Path:
        return self.root / "fits" / f"{key}.json"

    def cell_path(self, key: str) -> Path:
        return self.root / "cells" / f"{key}.json"

    # ------------------------------------------------------------------ records
    def _read(self, path: Path, key: str) -> dict | None:
        try:
            rec = json.loads(path.read_text())
        except (FileNotFoundError, json.JSONDecodeError, UnicodeDecodeError):
            return None
        if not isinstance(rec, dict) or rec.get("key") != key or rec.get("schema") != STORE_SCHEMA:
            return None
        return rec

    def _write(self, path: Path, key: str, record: dict) -> dict:
        rec = _clean({**record, "key": key, "schema": STORE_SCHEMA})
        atomic_write_text(path, json.dumps(rec, separators=(",", ":"), allow_nan=False))
        return rec

    def get_fit(self, key: str) -> dict | None:
        return self._read(self.fit_path(key), key)

    def put_fit(self, key: str, record: dict) -> dict:
        return self._write(self.fit_path(key), key, record)

    def get_cell(self, key: str) -> dict | None:
        return self._read(self.cell_path(key), key)

    def put_cell(self, key: str, record: dict) -> dict:
        return self._write(self.cell_path(key), key, record)

    def cell_keys(self) -> set[str]:
        return {p.stem for p in (self.root / "cells").glob("*.json")}

    # ------------------------------------------------------------------ study-level files
    def write_config(self, config: dict) -> None:
        atomic_write_text(self.root / "study.json", json.dumps(_clean(config), indent=2, allow_nan=False))

    def write_run_log(self, run_id: str, log: dict) -> None:
        atomic_write_text(self.root / "runs" / f"{run_id}.json", json.dumps(_clean(log), indent=2, allow_nan=False))

    def run_logs(self) -> list[dict]:
        """Every invocation's log, oldest first."""
        logs = []
        for p in sorted((self.root / "runs").glob("*.json")):
            try:
                logs.append(json.loads(p.read_text()))
            except (json.JSONDecodeError, UnicodeDecodeError):
                continue
        return sorted(logs, key=lambda d: d.get("started", ""))
