"""Named pretrained weights: the registry, the cache, and loading them into a ready net or task.

A weights entry (:class:`Weights`) is named ``<model>.<tag>`` (``student.sim_quick``) and records
its file (a local path or a URL), the file's full sha256, the net's keyword arguments and the input
recipes it expects, the data and protocol it was trained on, its metrics (from ``results.csv``), its
licence and provenance. Entries come from two places: :data:`BUILTIN_WEIGHTS` (published files;
none yet: the original authors release no checkpoints) and the local registry file
``<cache>/registry.json``, where ``aaute benchmark`` registers every finished job's best checkpoint
and :func:`register_weights` adds others.

The cache folder is ``$AAUTE_CACHE/weights`` (the features live beside it in ``$AAUTE_CACHE``), or
``~/.cache/aaute/weights``. Files named by a URL are downloaded there once, checked against their
sha256 and renamed into place only when complete. In offline mode (``offline=True`` or
``AAUTE_OFFLINE=1``) nothing touches the network: a file that is not cached is an error saying which
file is needed and where to put it.

``load_pretrained(model, weights=...)`` returns the net in eval mode; ``weights`` is a registered name
(``"sim_quick"`` or ``"student.sim_quick"``) or the path of a weights file (a project ``.ckpt``, a
file of ``aaute export`` / ``aaute import-checkpoint``, or a bare state dict). ``load_task`` builds
the whole :class:`~zoo.task.TrajectoryTask` from a project checkpoint. A file of another model, a
hash mismatch, or keys and shapes that do not fit are errors listing the differences.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import logging
import os
import urllib.parse
import urllib.request
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from datamodules.atomic import atomic_write
from zoo.checkpoints import (
    WEIGHTS_FORMAT,
    WEIGHTS_VERSION,
    CheckpointContents,
    CheckpointError,
    load_state_checked,
    read_checkpoint,
)
from zoo.registry import get_model, model_class

log = logging.getLogger(__name__)

REGISTRY_FILE = "registry.json"
URL_SCHEMES = ("http", "https", "file")


class WeightsError(CheckpointError):
    """Weights that cannot be found, fetched or trusted (the message says what to do)."""


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
        return urllib.parse.urlparse(self.source).scheme in URL_SCHEMES

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


#: published weights (file URL + sha256); the original authors release none, so the list is empty
BUILTIN_WEIGHTS: dict[str, Weights] = {}


# ---------------------------------------------------------------------------------------------- cache, registry


def weights_dir() -> Path:
    """``$AAUTE_CACHE/weights`` or ``~/.cache/aaute/weights``."""
    root = os.environ.get("AAUTE_CACHE")
    return Path(root) / "weights" if root else Path.home() / ".cache" / "aaute" / "weights"


def offline_mode(offline: bool | None = None) -> bool:
    """``offline`` if given, else whether ``$AAUTE_OFFLINE`` is set to 1 / true / yes."""
    if offline is not None:
        return offline
    return os.environ.get("AAUTE_OFFLINE", "").strip().lower() in ("1", "true", "yes", "on")


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


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


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


def _download(url: str, target: Path, sha256: str) -> None:
    """Fetch ``url`` into ``target`` atomically; a wrong sha256 leaves nothing behind."""
    log.info("downloading %s to %s", url, target)
    with atomic_write(target) as tmp:
        digest = hashlib.sha256()
        with urllib.request.urlopen(url, timeout=60) as response, open(tmp, "wb") as out:  # noqa: S310 (scheme checked)
            for block in iter(lambda: response.read(1 << 20), b""):
                digest.update(block)
                out.write(block)
        if digest.hexdigest() != sha256:
            raise WeightsError(f"{url}: downloaded file has sha256 {digest.hexdigest()}, the registry expects "
                               f"{sha256}; nothing was kept")


def weights_file(entry: Weights, offline: bool | None = None) -> Path:
    """The local file of ``entry``, downloaded into the cache if needed, its sha256 checked."""
    if entry.is_url:
        name = Path(urllib.parse.urlparse(entry.source).path).name or f"{entry.name}.pt"
        path = weights_dir() / "files" / f"{entry.sha256[:12]}-{name}"
        if not path.is_file():
            if offline_mode(offline):
                raise WeightsError(f"weights {entry.name}: offline mode, and {path} is not cached; download "
                                   f"{entry.source} (sha256 {entry.sha256}) and put it at {path}")
            _download(entry.source, path, entry.sha256)
            return path
    else:
        path = Path(entry.source)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: the file of weights {entry.name} is gone (re-run the job that made it "
                                    f"or register the weights again)")
    actual = file_sha256(path)
    if actual != entry.sha256:
        raise WeightsError(f"{path}: sha256 {actual} differs from {entry.sha256} registered for {entry.name} (the file "
                           f"was replaced or damaged; re-register it or delete it to download it again)")
    return path


# ---------------------------------------------------------------------------------------------- loading


def resolve_weights(model: str | None, weights: str | Path, offline: bool | None
             ) -> tuple[CheckpointContents, Weights | None]:
    """The file contents named by ``weights`` (a registered name or a path) and its registry entry, if any."""
    path = Path(weights)
    if path.is_file() or path.suffix in (".ckpt", ".pt", ".pth", ".bin") or os.sep in str(weights):
        return read_checkpoint(path), None
    entry = get_weights(str(weights), model)
    return read_checkpoint(weights_file(entry, offline)), entry


def build_net(contents: CheckpointContents, model: str | None = None, net_kwargs: dict[str, Any] | None = None,
              entry: Weights | None = None) -> nn.Module:
    """The net that ``contents`` describe, with its weights loaded (strict), in eval mode.

    Raises:
        WeightsMismatchError: the file is of another model than ``model``, or its keys or shapes do not fit.
    """
    from zoo.checkpoints import WeightsMismatchError

    name = contents.net or (entry.model if entry else None) or model
    if name is None:
        raise CheckpointError(f"{contents.path}: a bare state dict does not name its model; give the model name")
    if model is not None and name != model:
        raise WeightsMismatchError(f"{contents.path}: the weights are of model {name!r}, not {model!r} "
                                   f"(load them with load_pretrained({name!r}, ...))")
    kwargs = {**(entry.net_kwargs if entry else {}), **contents.net_kwargs, **(net_kwargs or {})}
    net = get_model(name, **kwargs)
    load_state_checked(net, contents.state_dict, str(contents.path), f"{name} {kwargs or ''}".strip())
    net.net_kwargs = kwargs  #: what it was built with (exports and registrations record it)
    return net.eval()


def load_pretrained(model: str, weights: str | Path | None = None, *, offline: bool | None = None,
                    net_kwargs: dict[str, Any] | None = None) -> nn.Module:
    """The net ``model`` with ``weights`` loaded, in eval mode (see the module docstring).

    Args:
        model: a registered model name (``zoo.list_models()``).
        weights: a registered weights name (``sim_quick`` or ``student.sim_quick``) or a file path;
            None: the model's only registered weights (an error lists them when there are several).
        offline: never touch the network (default: ``$AAUTE_OFFLINE``).
        net_kwargs: keyword arguments of a bare state dict's net (files of this project carry their own).
    """
    model_class(model)
    if weights is None:
        names = list_weights(model)
        if len(names) != 1:
            raise WeightsError(f"load_pretrained({model!r}) needs weights=...: {len(names)} registered for it "
                               f"({', '.join(names) or 'none'})")
        weights = names[0]
    contents, entry = resolve_weights(model, weights, offline)
    net = build_net(contents, model, net_kwargs, entry)
    net.pretrained = entry.as_dict() if entry else {"source": str(contents.path), **contents.metadata}
    return net


def task_arguments(hparams: dict[str, Any]) -> dict[str, Any]:
    """The hyperparameters that :class:`~zoo.task.TrajectoryTask` accepts (others are dropped)."""
    from zoo.task import TrajectoryTask

    accepted = set(inspect.signature(TrajectoryTask.__init__).parameters) - {"self"}
    return {key: value for key, value in hparams.items() if key in accepted}


def load_task(path: str | Path, **overrides: Any):
    """A :class:`~zoo.task.TrajectoryTask` from one of this project's ``.ckpt`` files (read safely, strict keys).

    ``overrides`` replace hyperparameters of the run (e.g. ``predictions_dir``).
    """
    from zoo.task import TrajectoryTask

    contents = read_checkpoint(path)
    if contents.kind != "lightning":
        hparams = {"net": contents.net, "net_kwargs": contents.net_kwargs}
        if contents.net is None:
            raise CheckpointError(f"{path}: a bare state dict does not name its model; use load_pretrained(model, ...)")
    else:
        hparams = dict(contents.metadata["hyper_parameters"])
    task = TrajectoryTask(**{**task_arguments(hparams), **overrides})
    load_state_checked(task.net, contents.state_dict, str(path), task.hparams.net)
    return task.eval()


def save_weights_file(net: nn.Module, path: str | Path, net_kwargs: dict[str, Any] | None = None,
                      metadata: dict[str, Any] | None = None, overwrite: bool = False) -> Path:
    """Write a self-describing weights file (net name, kwargs, input recipes, metadata, state dict), atomically."""
    path = Path(path)
    payload = {
        "format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "net": net.model_name,
        "net_kwargs": dict(net_kwargs or {}), "inputs": dict(getattr(net, "inputs", {})),
        "metadata": dict(metadata or {}),
        "state_dict": {key: value.detach().cpu().contiguous() for key, value in net.state_dict().items()},
    }
    with atomic_write(path, overwrite=overwrite) as tmp:
        torch.save(payload, tmp)
    return path

