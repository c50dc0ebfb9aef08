"""What ``aaute fit|validate|test|predict`` checks about ``--ckpt_path`` and ``--weights`` before it builds anything.

LightningCLI merges a checkpoint's hyperparameters over the configuration, so a student config
given an AudioNet checkpoint would silently evaluate AudioNet. Here a checkpoint (or weights
file) whose net differs from the configured one is refused with both names, unless
``--use_checkpoint_model true`` asks for the checkpoint's own model; then the data inputs follow
that net's recipes too, so it is not fed another model's features.

``--weights NAME|FILE`` (validate, test, predict) takes registered weights or any weights file
instead of ``--ckpt_path``: a project ``.ckpt`` becomes the run's ``ckpt_path``; a self-describing
or converted file sets the net and its keyword arguments, and its state dict is loaded (strict)
once the task is built.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from zoo.weights.files import (
    CheckpointContents,
    CheckpointError,
    WeightsMismatchError,
    load_state_checked,
    parse_contents,
    read_file,
)


def _checkpoint_net(path: Path) -> tuple[str | None, dict[str, Any]]:
    """The net name and kwargs a project ``.ckpt`` records (memory-mapped read, weights only)."""
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # not an mmap-able archive: the full reader gives the precise error
        obj = read_file(path)
    contents = parse_contents(path, obj)
    return contents.net, contents.net_kwargs


def _model_args(section: Any) -> Any:
    model = section.get("model")
    return model.get("init_args") if model is not None else None


def _refuse_or_follow(section: Any, source: str, net: str, net_kwargs: dict[str, Any]) -> None:
    """Refuse ``net`` if it differs from the configured one, unless the checkpoint's model was asked for."""
    from zoo.registry import model_class

    init_args = _model_args(section)
    configured = init_args.get("net") if init_args is not None else None
    if configured == net:
        return
    if not section.get("use_checkpoint_model"):
        raise WeightsMismatchError(
            f"{source} holds a {net!r} net but the configured model is {configured!r}; give that model's config "
            f"(--config configs/model/{net}.yaml) or --use_checkpoint_model true to run the checkpoint's own model")
    init_args["net"], init_args["net_kwargs"] = net, dict(net_kwargs)
    data_args = section.get("data", {}).get("init_args") if section.get("data") is not None else None
    if data_args is not None:
        data_args["inputs"] = model_class(net).resolve_input_recipes(net_kwargs.get("input_recipes"))


def check_run(subcommand: str, section: Any) -> CheckpointContents | None:
    """Check (and for ``--weights``, resolve) this run's checkpoint; return weights to load after building.

    Returns:
        The contents of a weights file whose state dict goes into the task's net once LightningCLI has built
        it (:func:`load_pending`); None when there is nothing to load (no ``--weights``, or a ``.ckpt`` that
        becomes the run's ``ckpt_path``).
    """
    from zoo.weights import resolve_weights

    ckpt_path, weights = section.get("ckpt_path"), section.get("weights")
    if weights:
        if subcommand == "fit":
            raise CheckpointError("--weights is for validate, test and predict; fit resumes with --ckpt_path")
        if ckpt_path:
            raise CheckpointError(f"give --weights or --ckpt_path, not both (got {weights} and {ckpt_path})")
        init_args = _model_args(section)
        configured = init_args.get("net") if init_args is not None else None
        contents, entry = resolve_weights(None if section.get("use_checkpoint_model") else configured, weights, None)
        net = contents.net or (entry.model if entry else configured)
        _refuse_or_follow(section, str(contents.path), net, contents.net_kwargs)
        if contents.kind == "lightning":
            section["ckpt_path"] = str(contents.path)
            return None
        if contents.net is not None:
            init_args["net_kwargs"] = dict(contents.net_kwargs)
        elif entry is not None:
            init_args["net_kwargs"] = dict(entry.net_kwargs)
        return contents
    if ckpt_path and Path(ckpt_path).is_file():
        net, net_kwargs = _checkpoint_net(Path(ckpt_path))
        if net is not None:
            _refuse_or_follow(section, str(ckpt_path), net, net_kwargs)
    return None


def load_pending(task: Any, pending: CheckpointContents | None) -> None:
    """Load the resolved ``--weights`` into the built task's net (strict: every key and shape must fit)."""
    if pending is not None:
        load_state_checked(task.net, pending.state_dict, str(pending.path), task.hparams.net)
