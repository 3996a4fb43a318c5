"""Residual diagnosis: find the effect a fitted model lacks from its residual on measured data, add it, refit.

* :func:`diagnose` — the whole loop (:mod:`socbench.diagnose.core`);
* :mod:`~socbench.diagnose.signatures` — residual signatures of the effects of ECM_SPEC §9;
* :mod:`~socbench.diagnose.search` — ranking, augmentation and refit with held-out scoring;
* :mod:`~socbench.diagnose.report` — ``diagnosis.json``, ``diagnosis.md`` and figures;
* :mod:`~socbench.diagnose.synthetic` — data with one effect hidden in it (tests, benchmark).
"""

from .core import Diagnosis, diagnose, fit_base
from .data import Folds, bin_average, make_folds

__all__ = ["Diagnosis", "diagnose", "fit_base", "Folds", "bin_average", "make_folds"]
