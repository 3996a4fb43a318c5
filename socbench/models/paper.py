"""The paper's Table 3 parameter sets (as data files) on the built-in "paper pack".

``socbench/data/paper/pack.json`` is a stand-in for the 6S 22 Ah LiPo pack of Jung & Tullu: the paper publishes no OCV
curve, so the pack's curve is six times a published single-cell LiPo OCV fit (the file names its source).
``socbench/data/paper/<model>.json`` holds Table 3 for each model, with the ECM_SPEC typo fixes marked in ``notes``.
Models without a Table 3 set (``esc``, ``nrc``) have stand-in sets marked as such.
"""

from __future__ import annotations

import json
from functools import cache
from importlib import resources

from ..errors import ConfigError
from ..ocv import OCVCurve
from .params import ModelParams, params_from_dict


@cache
def _read(name: str) -> dict:
    path = resources.files("socbench") / "data" / "paper" / f"{name}.json"
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"no paper parameter set for model '{name}'") from None


def paper_pack() -> dict:
    """The stand-in pack description (capacity, cells in series, OCV points, voltage limits)."""
    return dict(_read("pack"))


def paper_ocv() -> OCVCurve:
    return OCVCurve.from_dict(_read("pack")["ocv"])


def paper_params(model: str, **options) -> ModelParams:
    """Table 3 parameters of ``model`` on the paper pack; ``options`` override the file's (e.g. ``mode='strict'``)."""
    d = dict(_read(model))
    pack = _read("pack")
    d.setdefault("capacity_ah", pack["capacity_ah"])
    d["options"] = {**d.get("options", {}), **options}
    name, params = params_from_dict(d, ocv=paper_ocv(), file=f"paper/{model}.json")
    if name != model:
        raise ConfigError(f"paper/{model}.json declares model '{name}'")
    return params
