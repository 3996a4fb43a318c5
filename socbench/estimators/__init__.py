"""SOC estimators as batched numpy engines — coulomb counting, EKF, UKF, particle filter, adaptive EKF (Sage–Husa),
cubature KF, square-root UKF, H∞ filter, a joint SOC–capacity–R0 EKF (``dual``), the iterated EKF (``iekf``) and the
Rao–Blackwellised PF (``rbpf``: SOC particles, a Kalman filter for the other states) — plus
per-run references (filterpy where it has the filter, textbook forms otherwise; docs/estimators.md compares them).

``make_estimator(name, model, noise=None, **options)`` builds one; ``estimator.run(profile, soc0=None, P0=None,
seed=None) -> Estimate`` runs it over every Monte Carlo run of the profile at once; ``scoring.score(estimate,
profile)`` scores it. A new filter is one module plus one registry line here.
"""

from __future__ import annotations

import importlib

from ..errors import ConfigError
from .base import Estimator
from .estimate import Estimate
from .noise import DEFAULT_NOISE, SensorNoise

#: name -> "module:Class" (imported on first use)
ESTIMATORS: dict[str, str] = {
    "coulomb": "socbench.estimators.coulomb:CoulombCounter",
    "ekf": "socbench.estimators.ekf:EKF",
    "ukf": "socbench.estimators.ukf:UKF",
    "pf": "socbench.estimators.pf:ParticleFilter",
    "aekf": "socbench.estimators.aekf:AdaptiveEKF",
    "ckf": "socbench.estimators.ckf:CKF",
    "srukf": "socbench.estimators.srukf:SRUKF",
    "hinf": "socbench.estimators.hinf:HInfinityFilter",
    "dual": "socbench.estimators.dual:JointEKF",
    "iekf": "socbench.estimators.iekf:IteratedEKF",
    "rbpf": "socbench.estimators.rbpf:RaoBlackwellPF",
}


def estimator_names() -> list[str]:
    return list(ESTIMATORS)


def estimator_class(name: str):
    """The class registered as ``name``; a :class:`ConfigError` listing the known names otherwise."""
    try:
        module, cls = ESTIMATORS[name].split(":")
    except (KeyError, AttributeError):
        raise ConfigError(f"unknown estimator '{name}'; known: {', '.join(ESTIMATORS)}") from None
    return getattr(importlib.import_module(module), cls)


def make_estimator(name: str, model, noise: SensorNoise | None = None, **options) -> Estimator:
    """Estimator ``name`` on ``model`` with sensor noise ``noise`` (default :data:`DEFAULT_NOISE`) and options."""
    return estimator_class(name)(model, noise, **options)


def make_reference(name: str, model, noise: SensorNoise | None = None, **options) -> Estimator:
    """The reference backend of ``name`` (every estimator but ``coulomb``): one trajectory at a time."""
    from .reference import REFERENCES

    if name not in REFERENCES:
        raise ConfigError(f"no reference backend for '{name}'; known: {', '.join(REFERENCES)}")
    return REFERENCES[name](model, noise, **options)


__all__ = [
    "ESTIMATORS",
    "DEFAULT_NOISE",
    "Estimate",
    "Estimator",
    "SensorNoise",
    "estimator_class",
    "estimator_names",
    "make_estimator",
    "make_reference",
]
