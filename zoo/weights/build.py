"""Loading weights into a ready net or task, and writing self-describing weights files.

The top of :mod:`zoo.weights`: it composes the registry (names), the hub (the cached, checked file)
and the files (safe reading, strict load). ``load_pretrained(model, weights=...)`` returns the net in
eval mode; ``weights`` is a registered name (``"sim_quick"`` or ``"student.sim_quick"``) or the path
of a weights file (a project ``.ckpt``, a file of ``aaute export`` / ``aaute import-checkpoint``, or
a bare state dict). ``load_task`` builds the whole :class:`~zoo.task.TrajectoryTask` from a project
checkpoint. A file of another model, a hash mismatch, or keys and shapes that do not fit are errors
listing the differences.
"""

from __future__ import annotations

import inspect
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from datamodules.atomic import atomic_write
from zoo.registry import get_model, model_class
from zoo.weights.files import (
    WEIGHTS_FORMAT,
    WEIGHTS_VERSION,
    CheckpointContents,
    CheckpointError,
    WeightsMismatchError,
    load_state_checked,
    read_checkpoint,
)
from zoo.weights.hub import WeightsError, cached_file
from zoo.weights.registry import Weights, get_weights, list_weights

if TYPE_CHECKING:  # the task imports Lightning: loaded only when a task is built
    from zoo.task import TrajectoryTask


def weights_file(entry: Weights, offline: bool | None = None) -> Path:
    """The local file of ``entry``, downloaded into the cache if needed, its sha256 checked."""
    return cached_file(entry.source, entry.sha256, entry.name, offline)


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


def load_task(path: str | Path, **overrides: Any) -> TrajectoryTask:
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

