"""The model registry: one line per model. A new model is one file plus one line here.

Entries are ``"module:Class"`` strings, imported on first use, so that listing the registry stays cheap.
"""

from __future__ import annotations

import importlib

from ..errors import ConfigError

MODELS: dict[str, str] = {
    "rint": "socbench.models.rc_network:Rint",
    "thevenin": "socbench.models.rc_network:Thevenin",
    "pngv": "socbench.models.rc_network:PNGV",
    "dp": "socbench.models.rc_network:DP",
    "gnl": "socbench.models.rc_network:GNL",
    "improved_rc": "socbench.models.improved_rc:ImprovedRC",
    "shepherd": "socbench.models.static_terms:Shepherd",
    "unnewehr": "socbench.models.static_terms:Unnewehr",
    "nernst": "socbench.models.static_terms:Nernst",
    "fang": "socbench.models.static_terms:Fang",
    "liu": "socbench.models.tremblay:Liu",
    "tremblay1": "socbench.models.static_terms:Tremblay1",
    "tremblay2": "socbench.models.tremblay:Tremblay2",
    "plett": "socbench.models.static_terms:Plett",
    "esc": "socbench.models.esc:ESC",
    "nrc": "socbench.models.rc_network:NRC",
}


def model_names() -> list[str]:
    return list(MODELS)


def model_class(name: str):
    """The class registered as ``name``; a :class:`ConfigError` listing the known names otherwise."""
    try:
        target = MODELS[name]
    except KeyError:
        raise ConfigError(f"unknown model '{name}'; known: {', '.join(MODELS)}") from None
    module, cls = target.split(":")
    return getattr(importlib.import_module(module), cls)


def make_model(name: str, params, mode: str | None = None):
    """Instantiate model ``name`` with ``params`` (a :class:`~socbench.models.params.ModelParams`), with the effects
    the set carries (``params.effects``: an :class:`~socbench.models.effects.AugmentedModel`)."""
    model = model_class(name)(params, mode)
    if not params.effects:
        return model
    from .effects import augment, make_effect

    return augment(model, [make_effect(e["name"], **e["values"]) for e in params.effects])
