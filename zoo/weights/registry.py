"""The weights registry: named entries (:class:`Weights`), the built-in ones and the local ``registry.json``.

A weights entry is named ``<model>.<tag>`` (``student.sim_quick``) and records its file (a local
path or a URL), the file's full sha256, the net's keyword arguments and the input recipes it
expects, the data and protocol it was trained on, its metrics (from ``results.csv``), its licence
and provenance. Entries come from two places: :data:`BUILTIN_WEIGHTS` (published files; none yet:
the original authors release no checkpoints) and the local registry file
``<cache>/registry.json`` (the cache of :mod:`zoo.weights.hub`), where ``aaute benchmark``
registers every finished job's best checkpoint and :func:`register_weights` adds others.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from datamodules.atomic import atomic_write
from zoo.registry import model_class
from zoo.weights.files import file_sha256
from zoo.weights.hub import WeightsError, is_url, weights_dir

log = logging.getLogger("zoo.weights")

REGISTRY_FILE = "registry.json"


@dataclass
class Weights:
    """One named set of weights (see the module docstring)."""

    name: str  #: ``<model>.<tag>``
    source: str  #: local path or URL of the file
    sha256: str  #: full hex digest of the file
    net_kwargs: dict[str, Any] = field(default_factory=dict)
    inputs: dict[str, str] = field(default_factory=dict)  #: input name -> recipe
    data: str = ""
    protocol: str = ""
    metrics: dict[str, float] = field(default_factory=dict)
    licence: str = ""
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def model(self) -> str:
        return self.name.split(".", 1)[0]

    @property
    def tag(self) -> str:
        return self.name.split(".", 1)[1]

    @property
    def is_url(self) -> bool:
        return is_url(self.source)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


#: published weights (file URL + sha256); the original authors release none, so the list is empty
BUILTIN_WEIGHTS: dict[str, Weights] = {}


def _registry_path() -> Path:
    return weights_dir() / REGISTRY_FILE


def _read_registry() -> dict[str, Weights]:
    path = _registry_path()
    if not path.is_file():
        return {}
    try:
        raw = json.loads(path.read_text())
        return {name: Weights(**entry) for name, entry in raw["weights"].items()}
    except (ValueError, KeyError, TypeError) as error:
        raise WeightsError(f"{path}: not a weights registry ({error}); remove it or fix it by hand") from None


def _write_registry(entries: dict[str, Weights]) -> None:
    path = _registry_path()
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps({"version": 1, "weights": {n: e.as_dict() for n, e in sorted(entries.items())}},
                                  indent=1) + "\n")


def all_weights() -> dict[str, Weights]:
    """Every known entry: built-in, then local (a local entry of the same name wins)."""
    return {**BUILTIN_WEIGHTS, **_read_registry()}


def list_weights(model: str | None = None) -> list[str]:
    """Names of the known weights (of ``model`` only, if given), sorted."""
    return sorted(name for name, entry in all_weights().items() if model is None or entry.model == model)


def get_weights(name: str, model: str | None = None) -> Weights:
    """The entry ``name`` (``<model>.<tag>``, or just ``<tag>`` with ``model``); the error lists the known ones."""
    full = name if "." in name or model is None else f"{model}.{name}"
    entries = all_weights()
    if full not in entries:
        known = list_weights(model)
        raise WeightsError(f"no weights named {full!r}; known{f' for {model}' if model else ''}: "
                           f"{', '.join(known) or 'none'} (registered in {_registry_path()})")
    entry = entries[full]
    if model is not None and entry.model != model:
        raise WeightsError(f"weights {full!r} are of model {entry.model!r}, not {model!r}")
    return entry


def register_weights(entry: Weights) -> Weights:
    """Add or replace a local entry (the file must exist; its sha256 is computed if not given)."""
    model_class(entry.model)  # an unknown model is refused with the known names
    if not entry.tag:
        raise WeightsError(f"weights name {entry.name!r} needs a tag after the model name")
    if not entry.is_url:
        path = Path(entry.source).resolve()
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such weights file to register as {entry.name}")
        entry.source = str(path)
        entry.sha256 = entry.sha256 or file_sha256(path)
    elif not entry.sha256:
        raise WeightsError(f"weights {entry.name}: a URL source needs its sha256")
    entries = _read_registry()
    if entry.name in entries and entries[entry.name].source != entry.source:
        log.info("weights %s now point to %s (were %s)", entry.name, entry.source, entries[entry.name].source)
    entries[entry.name] = entry
    _write_registry(entries)
    return entry
