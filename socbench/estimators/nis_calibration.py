"""NIS calibration of the noise recipe on its validation records.

The recipe (:mod:`socbench.estimators.model_error`) measures a fitted model's voltage error — its size, its SOC and
temperature profile, its correlation times — and puts it in the filters' covariances. How *large* the filter should
take it is then a single number the records can check directly: run the filter on the validation records (loads of
the same cell the model was not fitted on, with a known SOC), and its normalised innovation squared should average 1
there::

    NIS_k = ν_k² / S_k,        ν_k = v_k − ŷ_k^−,   S_k = H P_k^− Hᵀ + R_k
    α_{j+1} = α_j · mean_k NIS_k(α_j),   α_0 = 1,   two rounds,   α ∈ [ALPHA_MIN, ALPHA_MAX]

``α`` scales every model-error variance the recipe gives the filter (the slow, mid-period, fast and resistive states'
scales, and the white part, which never falls below the sensor's own noise; :attr:`ModelErrorStats.nis_scale`). One
factor per form the recipe takes (:data:`~socbench.estimators.model_error.FORMS`): the coloured states (calibrated with
the EKF, and used by every filter that carries them) and the inflated white R (calibrated with the bootstrap particle
filter, the estimator that takes it). NIS is not linear in α (the filter's own SOC spread is part of S), hence the
second round.

Why it is needed: the recipe pools the error of every record it is given, and where those records are of different
kinds the pooled size fits none of them exactly. On the default flight scenarios the recipe's records are the lab
tests and a 5 kg flight; the resistive error of a model without RC branches is set by the HPPC's pulses (rint: 0.77 mΩ
on the HPPC, 0.13 mΩ on the flight), and its EKF's NIS mean on the 5 kg flight was 0.38 (the 0 kg flight: 0.20; the
10 kg: 0.91). The validation records say by how much the pooled error over- or understates what a filter meets on a
load of the kind scored.

Resolution: the records are run bin-averaged to :data:`~socbench.estimators.model_error.RESOLUTION_S` (1 s), the
resolution the recipe measures the error at: at a faster step the recipe's white part is inflated on purpose (a 10 Hz
sample holds a tenth of a second's information), and a per-sample NIS is not 1 there by design (the Panasonic Cycle
runs at 10 Hz: 0.12–0.21; at 1 s: 0.34–1.47).

Where it applies: :func:`socbench.estimators.model_error.nis_factor` — a factor above 1 everywhere, one below 1 only on
a record at the calibration records' temperatures (elsewhere the error met is larger than the one measured, and a
shrinking factor would narrow the band where nothing checked it).

Where the factor stays 1: no validation records (the recipe measured on the identification records only: the filter
met nothing the model was not fitted on, so its NIS there says nothing of a new load), or a filter that failed on
them.
"""

from __future__ import annotations

import numpy as np

from .model_error import RESOLUTION_S, ModelErrorStats, apply, bin_average
from .noise import SensorNoise

#: the calibration never shrinks the measured model-error variances below this share of the recipe's, nor grows them
#: beyond ALPHA_MAX times: the recipe's measurement stays the anchor, a factor beyond these says the recipe is wrong
#: for these records (reported, not hidden)
ALPHA_MIN = 0.25
ALPHA_MAX = 4.0
#: rounds of α_{j+1} = α_j · NIS(α_j)
ROUNDS = 2
#: the estimator each form of the recipe is calibrated with
CALIBRATED_WITH = {"states": "ekf", "inflated": "pf"}


def nis_mean(model, sensor: SensorNoise, stats: ModelErrorStats, records, form: str = "states",
             seed: int = 0) -> float | None:
    """Mean NIS over the samples of ``records`` (each bin-averaged to :data:`RESOLUTION_S`, filtered from its
    reference SOC) of the estimator :data:`CALIBRATED_WITH` ``[form]`` with the recipe ``stats``; None when no record
    gave a finite one."""
    from ..socaxis import run_on_data_axis, soc_axis
    from . import make_estimator
    from .scoring import normalized_error_squared

    total, n = 0.0, 0
    for record in records:
        if record.soc_ref is None or record.voltage_v is None or record.n < 3:
            continue
        prof = bin_average(record, RESOLUTION_S) if np.median(record.dt) < RESOLUTION_S else record
        run_model, noise = apply(model, sensor, stats, prof, form=form)
        est = make_estimator(CALIBRATED_WITH[form], run_model, noise)
        z0 = float(np.ravel(prof.soc_ref)[0])
        try:
            r = run_on_data_axis(est, prof, soc_axis(model.params, prof), soc0=z0, seed=seed)
        except Exception:  # a filter that cannot run the record says nothing of its consistency
            continue
        if bool(np.any(r.failed)):
            continue
        nis = normalized_error_squared(r.innovation, r.innovation_var)
        nis = nis[np.isfinite(nis)]
        total += float(np.sum(nis))
        n += nis.size
    return total / n if n else None


def calibrate(model, sensor: SensorNoise, stats: ModelErrorStats, records, form: str = "states") -> ModelErrorStats:
    """``stats`` with its NIS scale for ``form`` set so that the form's estimator has a NIS mean of 1 on ``records``
    (module docstring); ``stats`` unchanged without records or where the filter gave no NIS."""
    records = list(records)
    if stats.measured_on != "validation" or not records:
        return stats
    alpha = 1.0
    out = stats.with_nis_scale(form, 1.0)
    for _ in range(ROUNDS):
        nis = nis_mean(model, sensor, out, records, form)
        if nis is None or not np.isfinite(nis) or nis <= 0:
            return stats
        alpha = float(np.clip(alpha * nis, ALPHA_MIN, ALPHA_MAX))
        out = stats.with_nis_scale(form, alpha)
    return out


def calibrate_forms(model, sensor: SensorNoise, stats: ModelErrorStats, records, forms=tuple(CALIBRATED_WITH)):
    """:func:`calibrate` for each of ``forms`` in turn (each factor measured with the others' as set)."""
    for form in forms:
        stats = calibrate(model, sensor, stats, records, form)
    return stats


__all__ = ["ALPHA_MAX", "ALPHA_MIN", "CALIBRATED_WITH", "calibrate", "calibrate_forms", "nis_mean"]
