"""The model zoo: networks, the Lightning task, smoothing, weights, deployment and the zoo's subcommands.

The public face (like ``timm.create_model`` / ``torchgeo.models.get_weight``)::

    from zoo import get_model, list_models, load_pretrained, list_weights

    net = load_pretrained("student", weights="sim_quick")   # eval mode, weights checked

Attributes are imported on first use, so ``import zoo`` stays cheap for the command line.
"""

from __future__ import annotations

import importlib
from typing import Any

_PUBLIC = {
    "get_model": "zoo.registry",
    "list_models": "zoo.registry",
    "register_model": "zoo.registry",
    "load_pretrained": "zoo.weights",
    "list_weights": "zoo.weights",
    "get_weights": "zoo.weights",
    "load_task": "zoo.weights",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'zoo' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
