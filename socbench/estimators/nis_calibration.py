"""NIS calibration of the noise recipe on its validation records.

The recipe (:mod:`socbench.estimators.model_error`) measures a fitted model's voltage error — its size, its SOC and
temperature profile, its correlation times — and puts it in the filters' covariances. How *large* the filter should
take it is then a single number the records can check directly: run the filter on the validation records (loads of
the same cell the model was not fitted on, with a known SOC), and its normalised innovation squared should average 1
there::

    NIS_k = ν_k² / S_k,        ν_k = v_k − ŷ_k^−,   S_k = H P_k^− Hᵀ + R_k
    α_{j+1} = α_j · N_j^{1/s_j},   N_j = mean_k NIS_k(α_j),   α_0 = 1,   two rounds,   α ∈ [ALPHA_MIN, ALPHA_MAX]
    s_0 = 1,   s_j = −ln(N_j/N_{j−1}) / ln(α_j/α_{j−1}) within SLOPE_RANGE      (N ∝ α^{−s}: a secant step in logs)

``α`` scales every model-error variance the recipe gives the filter (the slow, mid-period, fast and resistive states'
scales, and the white part, which never falls below the sensor's own noise; :attr:`ModelErrorStats.nis_scale`). One
factor per form the recipe takes (:data:`~socbench.estimators.model_error.FORMS`): the coloured states (calibrated with
the EKF, and used by every filter that carries them) and the inflated white R (calibrated with the bootstrap particle
filter, the estimator that takes it). NIS is not linear in α (the filter's own SOC spread is part of S), hence the
second round, whose step uses the steepness the first one measured: an EKF's NIS falls about as 1/α, the particle
filter's about as 1/α² (its particles' spread narrows with R; on the 2 kg validation flight of improved_rc 5.1, 1.1
and 0.24 at α = ¼, ½, 1), where the plain step α·N overshoots and swings (the factor it gave there: 1.28 against
0.52 with the secant step).

**Load.** A model's error need not grow with the current as the recipe's scales do (they hold the SOC and the
temperature, and the resistive part grows as ``I``): where the truth's resistance falls with the current (charge
transfer, heating), a model fitted at one load misses the voltage as about ``I²`` at another. Where the validation
records are at loads at least :data:`LOAD_LEVER` apart in mean-square current ``L`` (and at one temperature, within
:data:`LOAD_TEMPERATURE_SPREAD_K`: else the pooled factor), each record gives its own factor ``α_j``, and the
calibration keeps ``α(L) = α·(L/L_ref)^q`` (:attr:`ModelErrorStats.nis_load`), fitted through them
in logs, ``q ∈ [0, LOAD_EXPONENT_MAX]``, ``L`` held within the calibrated loads (never extrapolated). The default
flight scenarios validate at 2 and 8 kg of payload: with one 5 kg validation flight the EKF's NIS mean ran from 0.35
on the 0 kg flight to 0.9 on the 10 kg one for the models without RC branches, and the particle filter's from 0.06
to 2.7 for the RC models (``docs/flight_consistency.md``).

Why it is needed: the recipe pools the error of every record it is given, and where those records are of different
kinds the pooled size fits none of them exactly. On the default flight scenarios, when the recipe's records were the
lab tests and one 5 kg flight, the resistive error of a model without RC branches was set by the HPPC's pulses (rint:
0.77 mΩ on the HPPC, 0.13 mΩ on the flight), and its EKF's NIS mean on the 5 kg flight was 0.38 (the 0 kg flight:
0.20; the 10 kg: 0.91). The validation records say by how much the pooled error over- or understates what a filter
meets on a load of the kind scored.

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
#: rounds of the update α_{j+1} = α_j · N_j^{1/s_j} (module docstring)
ROUNDS = 2
#: the steepness s of NIS ∝ α^(−s) the update assumes after its first round (measured between the rounds), held within
#: this range: an EKF's NIS falls about as 1/α, a bootstrap particle filter's about as 1/α² (its particles' spread
#: shrinks with R), where α·NIS would overshoot and swing
SLOPE_RANGE = (0.5, 3.0)
#: records whose mean-square currents differ by this factor calibrate the factor's load dependence (a factor per load)
LOAD_LEVER = 1.5
#: the load dependence is calibrated only on records whose median cell temperatures lie within this spread [K]
LOAD_TEMPERATURE_SPREAD_K = 10.0
#: the factor of one record alone, where the records differ in load: the recipe pools the loads, so each departs
#: from it further than their pooled factor may (the factor at the reference load stays within ALPHA_MIN…ALPHA_MAX)
LOAD_ALPHA_RANGE = (ALPHA_MIN / 4.0, ALPHA_MAX * 4.0)
#: the load exponent q of the factor (α·(L/L_ref)^q) is held within [0, LOAD_EXPONENT_MAX]
LOAD_EXPONENT_MAX = 3.0
#: the estimator each form of the recipe is calibrated with
CALIBRATED_WITH = {"states": "ekf", "inflated": "pf"}


def _usable(records) -> list:
    """The records a filter can be checked on (a reference SOC, a voltage, three samples), at
    :data:`RESOLUTION_S`."""
    return [bin_average(r, RESOLUTION_S) if np.median(r.dt) < RESOLUTION_S else r for r in records
            if r.soc_ref is not None and r.voltage_v is not None and r.n >= 3]


def _nis_sum(model, sensor: SensorNoise, stats: ModelErrorStats, prof, form: str, seed: int):
    """``(Σ NIS, samples)`` of the form's estimator on one record, or None where it cannot run it."""
    from ..socaxis import run_on_data_axis, soc_axis
    from . import make_estimator
    from .scoring import normalized_error_squared

    run_model, noise = apply(model, sensor, stats, prof, form=form)
    est = make_estimator(CALIBRATED_WITH[form], run_model, noise)
    z0 = float(np.ravel(prof.soc_ref)[0])
    try:
        r = run_on_data_axis(est, prof, soc_axis(model.params, prof), soc0=z0, seed=seed)
    except Exception:  # a filter that cannot run the record says nothing of its consistency
        return None
    if bool(np.any(r.failed)):
        return None
    nis = normalized_error_squared(r.innovation, r.innovation_var)
    nis = nis[np.isfinite(nis)]
    return (float(np.sum(nis)), nis.size) if nis.size else None


def nis_mean(model, sensor: SensorNoise, stats: ModelErrorStats, records, form: str = "states",
             seed: int = 0) -> float | None:
    """Mean NIS over the samples of ``records`` (each bin-averaged to :data:`RESOLUTION_S`, filtered from its
    reference SOC) of the estimator :data:`CALIBRATED_WITH` ``[form]`` with the recipe ``stats``; None when no record
    gave a finite one."""
    sums = [x for x in (_nis_sum(model, sensor, stats, p, form, seed) for p in _usable(records)) if x is not None]
    n = sum(k for _, k in sums)
    return sum(t for t, _ in sums) / n if n else None


def calibrate(model, sensor: SensorNoise, stats: ModelErrorStats, records, form: str = "states") -> ModelErrorStats:
    """``stats`` with its NIS scale for ``form`` set so that the form's estimator has a NIS mean of 1 on ``records``
    (module docstring); ``stats`` unchanged without records or where the filter gave no NIS."""
    records = _usable(records)
    if stats.measured_on != "validation" or not records:
        return stats
    loads = np.array([float(np.mean(np.square(p.current_a))) for p in records])
    temps = np.array([np.nan if p.temperature_c is None else float(np.median(p.temperature_c)) for p in records])
    # records at other temperatures differ for that reason too: a load exponent through them would take it for load
    same_temperature = bool(np.all(np.isnan(temps)) or np.ptp(temps) <= LOAD_TEMPERATURE_SPREAD_K)
    if len(records) > 1 and same_temperature and loads.min() > 0 and loads.max() >= LOAD_LEVER * loads.min():
        return _calibrate_over_load(model, sensor, stats, records, loads, form)
    alpha = _factor(model, sensor, stats, records, form)
    return stats if alpha is None else stats.with_nis_scale(form, alpha)


def _factor(model, sensor: SensorNoise, stats: ModelErrorStats, records, form: str,
            bounds=(ALPHA_MIN, ALPHA_MAX)) -> float | None:
    """α that brings the NIS mean over ``records`` to 1 (:data:`ROUNDS` rounds, within ``bounds``); None where the
    filter gave no NIS."""
    alpha, slope, last = 1.0, 1.0, None
    for _ in range(ROUNDS):
        nis = nis_mean(model, sensor, stats.with_nis_scale(form, alpha), records, form)
        if nis is None or not np.isfinite(nis) or nis <= 0:
            return None
        if last is not None and last[0] != alpha:
            slope = float(np.clip(-np.log(nis / last[1]) / np.log(alpha / last[0]), *SLOPE_RANGE))
        last = (alpha, nis)
        alpha = float(np.clip(alpha * nis ** (1.0 / slope), *bounds))
    return alpha


def _calibrate_over_load(model, sensor: SensorNoise, stats: ModelErrorStats, records, loads, form: str):
    """Records at loads ``L_j`` (mean-square currents) at least :data:`LOAD_LEVER` apart: the factor of each record
    alone, ``α_j``, then ``ln α_j = ln α + q ln(L_j/L_ref)`` by least squares weighted by the records' samples
    (``α_j`` within :data:`LOAD_ALPHA_RANGE`, ``L_ref`` their weighted geometric mean, ``q`` within ``[0,
    LOAD_EXPONENT_MAX]``, ``α`` within the bounds), followed between the lowest and the highest load calibrated and
    held beyond them."""
    alphas, logs, weights = [], [], []
    for prof, load in zip(records, loads):
        a = _factor(model, sensor, stats, [prof], form, LOAD_ALPHA_RANGE)
        if a is not None:
            alphas.append(a)
            logs.append(np.log(load))
            weights.append(prof.n)
    if not alphas:
        return stats
    y, x, w = np.log(alphas), np.asarray(logs), np.asarray(weights, dtype=float)
    ref = float(np.sum(w * x) / np.sum(w))
    span = np.sum(w * (x - ref) ** 2)
    q = float(np.clip(np.sum(w * (x - ref) * (y - np.sum(w * y) / np.sum(w))) / span, 0.0, LOAD_EXPONENT_MAX)) \
        if len(alphas) > 1 and span > 0 else 0.0
    alpha = float(np.clip(np.exp(np.sum(w * (y - q * (x - ref))) / np.sum(w)), ALPHA_MIN, ALPHA_MAX))
    if q == 0.0:
        return stats.with_nis_scale(form, alpha)
    return stats.with_nis_scale(form, alpha, (q, float(np.exp(ref)), float(loads.min()), float(loads.max())))


def calibrate_forms(model, sensor: SensorNoise, stats: ModelErrorStats, records, forms=tuple(CALIBRATED_WITH)):
    """:func:`calibrate` for each of ``forms`` in turn (each factor measured with the others' as set)."""
    for form in forms:
        stats = calibrate(model, sensor, stats, records, form)
    return stats


__all__ = ["ALPHA_MAX", "ALPHA_MIN", "CALIBRATED_WITH", "LOAD_EXPONENT_MAX", "LOAD_LEVER", "calibrate",
           "calibrate_forms", "nis_mean"]
