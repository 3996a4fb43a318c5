"""Identification: HPPC analysis (rests, pulses, OCV points, pulse resistances) and parameter fitting.

* :func:`analyze_hppc`, :func:`ocv_from_hppc`, :func:`ocv_from_slow_test`, :func:`rest_level` (the current sensor's
  offset, noise and rest thresholds), :func:`slow_test_count_error` (the offset a slow test's branches show) —
  :mod:`socbench.identify.hppc`
* :func:`fit_model` — any registered model in the paper's modes (``paper``, ``constant``, ``lookup``)
* :func:`fit_parameters` — the generic bounded least-squares building block (batched finite-difference Jacobian)
* :func:`compress_profile` — exact merging of constant-current steps before fitting
* :func:`select_fit`, :func:`select_temperature_fit` — choose the fit setting by validation on other records
  (:mod:`socbench.identify.select`)
"""

from .compress import Compression, compress_profile
from .fit import MODES, FitProblem, FitResult, fit_model, model_parameter_names, setup_fit
from .hppc import (
    HPPCAnalysis,
    Pulse,
    Rest,
    RestLevel,
    SlowOCV,
    analyze_hppc,
    discharged_ah,
    edge_resistance,
    ocv_from_hppc,
    ocv_from_slow_test,
    rest_level,
    slow_test_count_error,
    unrecorded_charge,
)
from .lsq import LsqResult, covariance, fit_parameters, simulate_voltage
from .select import (
    FIT_CANDIDATES,
    FIT_SETTINGS,
    CampaignSelection,
    Selection,
    select_fit,
    select_temperature_fit,
    validation_rmse,
)

__all__ = [
    "Compression",
    "compress_profile",
    "MODES",
    "FitProblem",
    "FitResult",
    "fit_model",
    "model_parameter_names",
    "setup_fit",
    "HPPCAnalysis",
    "Pulse",
    "Rest",
    "RestLevel",
    "SlowOCV",
    "analyze_hppc",
    "discharged_ah",
    "edge_resistance",
    "ocv_from_hppc",
    "ocv_from_slow_test",
    "rest_level",
    "slow_test_count_error",
    "unrecorded_charge",
    "LsqResult",
    "covariance",
    "fit_parameters",
    "simulate_voltage",
    "FIT_CANDIDATES",
    "Selection",
    "select_fit",
    "select_temperature_fit",
    "CampaignSelection",
    "FIT_SETTINGS",
    "validation_rmse",
]
