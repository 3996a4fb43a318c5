"""Run a study into a store: fit each model once per characterisation, then every cell, each saved the moment it ends.

Order of work: for every scenario the runner builds its characterisation test and fingerprints it; every (model,
characterisation) pair not yet in the store becomes a fit task; as each fit lands (or is found in the store) the cells
that need it are submitted. Finished cells are never recomputed: a cell whose key is in the store is reused as is.
Work that raised (a fit that threw, a cell whose estimator threw) is stored for the report but retried by the next
invocation, so a transient failure never sticks; runs an estimator flags as diverged are results and are kept.
On an interrupt the runner stops the workers, records what this invocation computed, and re-raises.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone

from .. import __version__
from .backends import make_backend
from .cell import LEADERBOARD_COLUMNS, Toolkit, _scenario, compute_cell, compute_fit
from .grid import (
    CELL_CODE,
    FIT_CODE,
    StudyConfig,
    cell_config,
    code_fingerprint,
    fit_config,
    profile_fingerprint,
    seed_from_key,
    stable_hash,
)
from .store import Store


@dataclass
class StudyResult:
    """The finished study: cell records in grid order (scenario, model, estimator) and the fits they used."""

    config: StudyConfig
    cells: list[dict]
    fits: dict = field(default_factory=dict)  # (scenario, model) -> fit record
    computed: list[str] = field(default_factory=list)
    reused: list[str] = field(default_factory=list)
    stale: list[str] = field(default_factory=list)  # reused fits and cells computed by other code
    seconds: float = 0.0
    backend: str = "serial"
    jobs: int = 1
    missing: list[str] = field(default_factory=list)  # cells not in the store (a read-only look: compute=False)

    def frame(self):
        """The leaderboard as a DataFrame with exactly the DESIGN.md columns (empty metrics are None)."""
        import pandas as pd

        rows = [{c: rec["row"].get(c) for c in LEADERBOARD_COLUMNS} for rec in self.cells]
        return pd.DataFrame(rows, columns=list(LEADERBOARD_COLUMNS))


def scenario_fingerprint(scenario, name: str) -> str:
    """A stable description of a scenario for the cell key: its ``to_dict()`` or dataclass fields, else its name."""
    desc = None
    to_dict = getattr(scenario, "to_dict", None)
    if callable(to_dict):
        desc = to_dict()
    elif dataclasses.is_dataclass(scenario):
        desc = {f.name: getattr(scenario, f.name) for f in dataclasses.fields(scenario)}
    text = json.dumps({"name": name, "desc": desc}, sort_keys=True, default=repr)
    text = re.sub(r" at 0x[0-9a-fA-F]+", "", text)  # object addresses change from run to run
    return stable_hash(text)


def _progress(total: int, enabled: bool | None):
    from tqdm.auto import tqdm

    if enabled is None:
        enabled = sys.stderr.isatty()
    return tqdm(total=total, desc="leaderboard", unit="task", disable=not enabled, leave=False, file=sys.stderr)


def run_study(config: StudyConfig, store: Store | str, backend: str = "serial", jobs: int | None = None,
              scheduler: str | None = None, toolkit: Toolkit | None = None, progress: bool | None = None,
              log=None, recompute_stale: bool = False, compute: bool = True) -> StudyResult:
    """Run (or resume) ``config`` into ``store``; see the module docstring. ``log(msg)`` receives progress lines.

    Records computed by other code (see :func:`~.grid.code_fingerprint`) are reused and listed in ``stale``, or
    recomputed when ``recompute_stale``. ``compute=False`` only reads: the result holds the cells already in the
    store (a study still running, or interrupted) and lists the others in ``missing``; nothing is written.
    """
    t_start = time.perf_counter()
    toolkit = toolkit or Toolkit()
    store = store if isinstance(store, Store) else Store(store)
    say = log or (lambda msg: None)
    run_id = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ") + f"-{os.getpid()}"
    if compute:
        store.write_config({**config.to_dict(), "version": __version__, "run_id": run_id})

    # ---- the grid: characterisations, fit keys, cell keys
    char_profiles: dict[str, object] = {}  # fit key -> characterisation profile
    fit_cfg: dict[str, dict] = {}  # fit key -> its configuration
    fit_of: dict[tuple, str] = {}  # (scenario, model) -> fit key
    cells: list[tuple] = []  # (cell key, job)
    for scen_name in config.scenarios:
        scen = _scenario(toolkit, scen_name)
        char = scen.characterisation()
        char_hash = profile_fingerprint(char)
        scen_fp = scenario_fingerprint(scen, scen_name)
        for model in config.models:
            fcfg = fit_config(model, char_hash, config.fit_mode, __version__)
            fkey = stable_hash(fcfg)
            fit_cfg[fkey] = fcfg
            fit_of[(scen_name, model)] = fkey
            char_profiles.setdefault(fkey, char)
            for est in config.estimators:
                opts = dict(config.estimator_options.get(est, {}))
                ckey = stable_hash(cell_config(model, est, scen_name, scen_fp, config.seeds, fkey, opts, __version__,
                                               config.noise))
                job = {"model": model, "estimator": est, "scenario": scen_name, "seeds": list(config.seeds),
                       "options": opts, "seed": seed_from_key(ckey), "fit_key": fkey, "noise": config.noise}
                cells.append((ckey, job))

    fit_code, cell_code = code_fingerprint(FIT_CODE), code_fingerprint(CELL_CODE)
    records: dict[str, dict] = {}
    reused: list[str] = []
    stale: list[str] = []
    todo: list[tuple] = []
    for ckey, job in cells:
        rec = store.get_cell(ckey)
        if rec is not None and not rec.get("error") and not (recompute_stale and rec.get("code") != cell_code):
            records[ckey] = rec
            reused.append(ckey)
            if rec.get("code") != cell_code:
                stale.append(ckey)
        else:
            todo.append((ckey, job))

    fits: dict[str, dict] = {}
    for fkey in dict.fromkeys(fit_of.values()):
        rec = store.get_fit(fkey)
        if rec is not None and rec.get("params") is not None:
            if rec.get("code") != fit_code:
                if recompute_stale and any(job["fit_key"] == fkey for _, job in todo):
                    continue
                stale.append(fkey)
            fits[fkey] = rec
    missing = [ckey for ckey, _ in todo]
    if not compute:
        todo = []
    fit_tasks = [k for k in dict.fromkeys(job["fit_key"] for _, job in todo) if k not in fits]
    say(f"{len(cells)} cells: {len(reused)} in the store, {len(todo)} to run; {len(fit_tasks)} fits to compute")
    if stale:
        say(f"warning: {len(stale)} stored fits/cells were computed by other code; reusing them "
            "(recompute them with --recompute-stale)")

    computed: list[str] = []
    waiting: dict[str, list] = {}  # fit key -> cells waiting for it
    for ckey, job in todo:
        waiting.setdefault(job["fit_key"], []).append((ckey, job))

    bk = make_backend(backend, jobs, scheduler) if todo else None
    bar = _progress(len(todo) + len(fit_tasks), progress) if todo else None
    pending: dict = {}
    # The backend only ever holds a few tasks, so that cells whose fit is done run before the remaining fits: results
    # reach the store early (an interrupt loses little) while every worker stays busy.
    ready_cells: deque = deque()
    ready_fits: deque = deque(fit_tasks)
    in_flight = 2 * bk.jobs if bk is not None else 0

    def submit_cells(fkey):
        ready_cells.extend(waiting.pop(fkey, []))

    def top_up():
        while len(pending) < in_flight and (ready_cells or ready_fits):
            if ready_cells:
                ckey, job = ready_cells.popleft()
                task = {**job, "fit": fits[job["fit_key"]]}
                pending[bk.submit(compute_cell, toolkit, task)] = ("cell", ckey, job)
            else:
                fkey = ready_fits.popleft()
                model = fit_cfg[fkey]["model"]
                pending[bk.submit(compute_fit, toolkit, model, char_profiles[fkey], config.fit_mode)] = \
                    ("fit", fkey, model)

    def write_log(interrupted: bool):
        if not compute:
            return
        store.write_run_log(run_id, {"run_id": run_id, "started": run_id, "interrupted": interrupted,
                                     "backend": backend, "jobs": None if bk is None else bk.jobs,
                                     "computed": computed, "reused": reused, "stale": stale,
                                     "seconds": time.perf_counter() - t_start})

    try:
        if bk is not None:
            for fkey in list(waiting):
                if fkey in fits:
                    submit_cells(fkey)
            top_up()
            while pending:
                for handle in bk.wait(pending):
                    kind, key, info = pending.pop(handle)
                    result = bk.result(handle)
                    if kind == "fit":
                        fits[key] = store.put_fit(key, {**result, "config": fit_cfg[key], "code": fit_code})
                        if result.get("error"):
                            say(f"fit of {info} failed: {result['error']}")
                        submit_cells(key)
                    else:
                        records[key] = store.put_cell(key, {**result, "config": {**info, "seeds": list(config.seeds)},
                                                            "run_id": run_id, "code": cell_code,
                                                            "finished": datetime.now(timezone.utc).isoformat()})
                        computed.append(key)
                    bar.update(1)
                top_up()
    except BaseException:
        if bk is not None:
            bk.close(cancel=True)
        if bar is not None:
            bar.close()
        write_log(interrupted=True)
        raise
    if bk is not None:
        bk.close()
    if bar is not None:
        bar.close()
    write_log(interrupted=False)

    fits_by_cell = {sm: fits.get(k) for sm, k in fit_of.items()}
    return StudyResult(config=config, cells=[records[k] for k, _ in cells if k in records], fits=fits_by_cell,
                       computed=computed, reused=reused, stale=stale, seconds=time.perf_counter() - t_start,
                       backend=backend, jobs=1 if bk is None else bk.jobs, missing=[] if compute else missing)

