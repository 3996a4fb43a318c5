"""The leaderboard study: models × estimators × scenarios × seeds, run into a resumable store, locally or on Dask.

* :mod:`.grid`     the configuration and the hashes that key fits and cells;
* :mod:`.store`    one atomically written JSON file per finished fit and cell;
* :mod:`.cell`     the work itself (fit a model, run a cell and reduce it to a leaderboard row);
* :mod:`.backends` serial, local processes, dask.distributed;
* :mod:`.runner`   ties them together: :func:`run_study`.
"""

from .backends import BACKENDS, make_backend
from .cell import LEADERBOARD_COLUMNS, METRIC_COLUMNS, Toolkit, compute_cell, compute_fit, reduce_cell
from .grid import DEFAULT_ESTIMATORS, DEFAULT_SCENARIOS, DEFAULT_SEEDS, StudyConfig, parse_names, stable_hash
from .runner import StudyResult, run_study, scenario_fingerprint
from .store import Store

__all__ = [
    "BACKENDS",
    "DEFAULT_ESTIMATORS",
    "DEFAULT_SCENARIOS",
    "DEFAULT_SEEDS",
    "LEADERBOARD_COLUMNS",
    "METRIC_COLUMNS",
    "Store",
    "StudyConfig",
    "StudyResult",
    "Toolkit",
    "compute_cell",
    "compute_fit",
    "make_backend",
    "parse_names",
    "reduce_cell",
    "run_study",
    "scenario_fingerprint",
    "stable_hash",
]
