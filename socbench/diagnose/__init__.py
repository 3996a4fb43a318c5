"""Residual diagnosis: find the effect a fitted model lacks from its residual on measured data, add it, refit.

* :func:`diagnose` — the whole loop (:mod:`socbench.diagnose.core`);
* :mod:`~socbench.diagnose.signatures` — residual signatures of the effects of ECM_SPEC §9;
* :mod:`~socbench.diagnose.data` — averaging and the blocked cross-validation folds;
* :mod:`~socbench.diagnose.cv` — one bounded fit per fold and the held-out residual;
* :mod:`~socbench.diagnose.search` — ranking, augmentation and refit with held-out scoring;
* :mod:`~socbench.diagnose.report` — ``diagnosis.json``, ``diagnosis.md`` and figures;
* :mod:`~socbench.diagnose.synthetic` — fixed cases with one effect hidden in them (the unit tests);
* :mod:`~socbench.diagnose.randomized` — the randomised undeclared-effect benchmark's own generator and rates.
"""

from .core import Diagnosis, diagnose, fit_base
from .data import Folds, bin_average, make_folds

__all__ = ["Diagnosis", "diagnose", "fit_base", "Folds", "bin_average", "make_folds"]
