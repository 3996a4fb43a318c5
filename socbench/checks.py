"""Cross-checks between a data file and a parameter set, before any simulation runs on them."""

from __future__ import annotations

import numpy as np

from .errors import DataError
from .models.params import ModelParams
from .profile import Profile


def check_voltage_level(profile: Profile, params: ModelParams, params_name: str = "parameters") -> None:
    """Refuse data whose voltage level cannot belong to the parameter set's cell or pack.

    A single-cell file against a 6S pack's parameters gives errors of 20 V that look like a model failure; the real
    cause is a mismatch (cells in series, wrong file). The measured median voltage must lie within the OCV range of the
    parameter set widened by 30 % (which leaves room for any realistic over-potential).
    """
    if profile.voltage_v is None:
        return
    lo, hi = float(params.ocv(0.0)), float(params.ocv(1.0))
    med = float(np.median(profile.voltage_v))
    if not (0.7 * lo <= med <= 1.3 * hi):
        raise DataError(
            f"measured voltage (median {med:.2f} V) does not match {params_name} (OCV {lo:.2f}–{hi:.2f} V): "
            "use parameters fitted for this cell or pack (socbench fit)",
            file=profile.meta.source or profile.meta.name,
            column="voltage_v",
        )
