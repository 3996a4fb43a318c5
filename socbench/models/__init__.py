"""The ECMs of Jung & Tullu (IEEE Access 2023) and friends, as batched state-space models with analytic Jacobians."""

from .base import Model, Simulation
from .blocks import GuardLog
from .paper import paper_ocv, paper_pack, paper_params
from .params import Constant, Lookup, ModelParams, Polynomial, load_params, save_params
from .registry import MODELS, make_model, model_class, model_names

__all__ = [
    "Model",
    "Simulation",
    "GuardLog",
    "ModelParams",
    "Constant",
    "Polynomial",
    "Lookup",
    "load_params",
    "save_params",
    "paper_params",
    "paper_ocv",
    "paper_pack",
    "MODELS",
    "make_model",
    "model_class",
    "model_names",
]
