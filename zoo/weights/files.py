"""Reading weights files safely, telling their kind apart, and loading state dicts with a readable diff.

The bottom of :mod:`zoo.weights`: it knows files and state dicts, not the registry or the cache.

Every file is read with ``torch.load(weights_only=True)``: tensors and plain containers only. A
pickle that needs code to rebuild (a whole pickled model, a custom class) is refused with an error
that names the file and the global it asked for. Three kinds of file are understood:

- this project's Lightning checkpoints (``.ckpt``: ``state_dict`` with ``net.`` keys and
  ``hyper_parameters`` holding ``net`` and ``net_kwargs``);
- self-describing weights files (``format: aaute-weights``, written by ``aaute export`` and
  ``aaute import-checkpoint``): net name, its keyword arguments, input recipes, provenance and the
  net's state dict, loadable without any training config;
- bare state dicts (name -> tensor), whose net and keyword arguments the caller must give.

A state dict that does not fit a net is never loaded in part: :func:`load_state_checked` lists the
missing and unexpected keys and the shape differences (first :data:`SHOWN` names and shapes, each
written by :func:`shape_text`) in one line. :func:`file_sha256` is the digest the registry and the
cache check files against.
"""

from __future__ import annotations

import hashlib
import pickle
import re
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from datamodules.errors import AauteError

WEIGHTS_FORMAT = "aaute-weights"  #: the ``format`` value of a self-describing weights file
WEIGHTS_VERSION = 1
SHOWN = 5  #: names listed per kind of difference (here and in the converters' errors)


class CheckpointError(AauteError, ValueError):
    """A weights file that cannot be used as asked (the message names the file and the reason)."""


class UnsafeCheckpointError(CheckpointError):
    """A pickle that needs code to load: refused."""


class WeightsMismatchError(CheckpointError):
    """A state dict whose keys or shapes do not fit the net (the message lists the differences)."""


def shape_text(value: Any) -> str:
    """A tensor's shape as ``64x4x3x3`` (anything else: its type's name), for error messages."""
    return "x".join(map(str, value.shape)) if isinstance(value, torch.Tensor) else type(value).__name__


def file_sha256(path: str | Path) -> str:
    """The full hex sha256 digest of the file at ``path`` (read in 1 MiB blocks)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


ZIP_MAGIC = b"PK\x03\x04"  #: torch.save's archive (since torch 1.6)
PICKLE_PROTOCOL = 0x80  #: first byte of torch's legacy (pre-1.6) format, a pickle of protocol >= 2
LFS_POINTER = b"version https://git-lfs.github.com/spec/"


def not_torch_file(path: Path) -> str | None:
    """What ``path`` is when its first bytes show it is not a torch file (``None``: it may be one).

    Tells apart the usual mistakes: a Git LFS pointer (the repository was cloned without ``git lfs``),
    an HTML page (a download that returned a web page), another text file, other bytes.
    """
    with open(path, "rb") as handle:
        head = handle.read(512)
    if head.startswith(ZIP_MAGIC) or head[:1] == bytes([PICKLE_PROTOCOL]):
        return None
    if not head:
        return "an empty file"
    if head.startswith(LFS_POINTER):
        size = re.search(rb"\nsize (\d+)", head)
        return (f"a Git LFS pointer{f' to {int(size.group(1)):,} bytes' if size else ''}, not the weights "
                f"themselves (fetch them with 'git lfs pull')")
    lowered = head.lstrip().lower()
    if lowered.startswith((b"<!doctype html", b"<html", b"<?xml", b"<head", b"<body")):
        return "an HTML page (a download that returned a web page instead of the file?)"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        text = None
    if text is not None and all(c.isprintable() or c in "\r\n\t" for c in text.rstrip("\x00")):
        first = text.strip().splitlines()[0][:60] if text.strip() else ""
        return f"a text file (it starts {first!r})"
    return f"not a torch file (it starts with bytes {head[:8].hex(' ')})"


def read_file(path: str | Path) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU, with one-line errors naming the file.

    Raises:
        FileNotFoundError: no such file.
        UnsafeCheckpointError: the pickle needs code (a class or function outside torch's allow-list).
        CheckpointError: a truncated, corrupt or non-torch file (a Git LFS pointer, an HTML page or another
            text file is named as such: :func:`not_torch_file`).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such weights file")
    what = not_torch_file(path)
    if what is not None:
        raise CheckpointError(f"{path}: {what}; expected weights written by torch.save (a zip archive)")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        text = str(error)
        found = re.search(r"Unsupported global: GLOBAL (\S+)", text)
        operand = re.search(r"Unsupported operand \S+", text)
        if "Weights only load failed" in text or found or operand:
            reason = (f"it asks for {found.group(1)}" if found else operand.group(0) if operand
                      else text.splitlines()[0][:160])
            raise UnsafeCheckpointError(
                f"{path}: refused: its pickle needs code to load ({reason}); only tensors and plain containers "
                f"are read, so a file holding a pickled model or custom objects must be re-saved as a state dict "
                f"(torch.save(model.state_dict(), ...)) by the code that made it") from None
        raise CheckpointError(f"{path}: not a readable torch file ({text.splitlines()[0][:200]})") from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, KeyError, IndexError, ValueError, OSError) as error:
        first = str(error).splitlines()[0].split(". ")[0][:160] if str(error) else type(error).__name__
        raise CheckpointError(f"{path}: truncated or corrupt weights file, expected a complete torch.save archive "
                              f"({first})") from None


@dataclass
class CheckpointContents:
    """What a weights file holds: the net's state dict and, where the file says so, its description."""

    path: Path
    kind: str  #: 'lightning', 'aaute-weights' or 'state_dict'
    state_dict: dict[str, torch.Tensor]
    net: str | None = None
    net_kwargs: dict[str, Any] = field(default_factory=dict)
    inputs: dict[str, str] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)  #: provenance, hyperparameters, ...


def _tensors(path: Path, mapping: Mapping, what: str) -> dict[str, torch.Tensor]:
    bad = [key for key, value in mapping.items() if not isinstance(key, str) or not isinstance(value, torch.Tensor)]
    if bad:
        raise CheckpointError(f"{path}: {what} must map parameter names to tensors; "
                              f"entries {bad[:SHOWN]} are not tensors")
    return dict(mapping)


def parse_contents(path: str | Path, obj: Any) -> CheckpointContents:
    """Tell a loaded file's kind apart and return its net state dict (``net.`` prefix removed) and description."""
    path = Path(path)
    if not isinstance(obj, Mapping):
        raise CheckpointError(f"{path}: expected a dict (a state dict or a checkpoint), got {type(obj).__name__}")
    if obj.get("format") == WEIGHTS_FORMAT:
        for key in ("net", "state_dict"):
            if key not in obj:
                raise CheckpointError(f"{path}: {WEIGHTS_FORMAT} file without its {key!r} entry")
        return CheckpointContents(path, "aaute-weights", _tensors(path, obj["state_dict"], "state_dict"),
                                  str(obj["net"]), dict(obj.get("net_kwargs") or {}), dict(obj.get("inputs") or {}),
                                  dict(obj.get("metadata") or {}))
    if "state_dict" in obj and isinstance(obj["state_dict"], Mapping):
        hparams = dict(obj.get("hyper_parameters") or {})
        state = _tensors(path, obj["state_dict"], "state_dict")
        net_state = {key[len("net."):]: value for key, value in state.items() if key.startswith("net.")}
        if not net_state or "net" not in hparams:
            raise CheckpointError(f"{path}: a Lightning checkpoint, but not of this project's TrajectoryTask "
                                  f"(expected hyper_parameters.net and 'net.' keys; first keys {list(state)[:SHOWN]})")
        return CheckpointContents(path, "lightning", net_state, str(hparams["net"]),
                                  dict(hparams.get("net_kwargs") or {}), {},
                                  {"hyper_parameters": hparams, "epoch": obj.get("epoch"),
                                   "global_step": obj.get("global_step"),
                                   "audio_sample_rates": (obj.get("MMAUDDataModule") or {}).get("audio_sample_rates")})
    return CheckpointContents(path, "state_dict", _tensors(path, obj, "a state dict"))


def read_checkpoint(path: str | Path) -> CheckpointContents:
    """Read a weights file safely and tell its kind apart (see the module docstring)."""
    return parse_contents(path, read_file(path))


def state_differences(expected: Mapping[str, torch.Tensor], given: Mapping[str, torch.Tensor]) -> str:
    """'' when ``given`` fits ``expected`` key for key and shape for shape, else a one-line list of differences."""
    missing = [key for key in expected if key not in given]
    unexpected = [key for key in given if key not in expected]
    reshaped = [key for key in expected if key in given and tuple(expected[key].shape) != tuple(given[key].shape)]
    parts = []
    if missing:
        parts.append(f"{len(missing)} missing (" + ", ".join(
            f"{key} [{shape_text(expected[key])}]" for key in missing[:SHOWN])
            + (", ..." if len(missing) > SHOWN else "") + ")")
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected (" + ", ".join(
            f"{key} [{shape_text(given[key])}]" for key in unexpected[:SHOWN])
            + (", ..." if len(unexpected) > SHOWN else "") + ")")
    if reshaped:
        parts.append(f"{len(reshaped)} of another shape (" + ", ".join(
            f"{key}: file {shape_text(given[key])}, net {shape_text(expected[key])}" for key in reshaped[:SHOWN])
            + (", ..." if len(reshaped) > SHOWN else "") + ")")
    return "; ".join(parts)


def load_state_checked(module: nn.Module, state: Mapping[str, torch.Tensor], source: str, what: str = "") -> None:
    """Load ``state`` into ``module`` only if every key and shape fits; else raise with the differences.

    Raises:
        WeightsMismatchError: missing or unexpected keys, or shapes that differ (nothing is loaded).
    """
    differences = state_differences(module.state_dict(), state)
    if differences:
        name = what or getattr(module, "model_name", "") or type(module).__name__
        raise WeightsMismatchError(f"{source}: the weights do not fit {name}: {differences}")
    module.load_state_dict(state, strict=True)
