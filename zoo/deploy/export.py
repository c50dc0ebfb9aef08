"""``aaute export``: a self-describing checkpoint and an ONNX file of a net, for deployment.

The checkpoint (``<out>.pt``, :func:`zoo.weights.save_weights_file`) holds the net's name, keyword
arguments, input recipes and provenance beside its state dict, so ``load_pretrained(model, path)``
needs no training config. The ONNX file (``<out>.onnx``, torch's exporter, batch axis dynamic) takes
the net's inputs as named tensors (e.g. ``audio_mel``, B x 4 x 64 x 64) and returns its outputs by
name (``position``, ...). The mel front-end stays in Python (:mod:`datamodules.features`); the
file's metadata names the recipe each input needs. Before the file is kept, onnxruntime runs it on
example inputs and every output must equal PyTorch's within :func:`tolerance`: ``1e-4`` of the
output's largest magnitude plus ``1e-6``. Both runtimes compute in float32 (a relative rounding of
about 6e-8 per operation) but fuse and order the sums differently; across the dozens of layers of a
net these roundings add up to some 1e-6 to 1e-5 of the output's scale (positions of tens of metres
differ by about 1e-5 m), so the bound leaves a margin of ten while a wrong graph (a dropped bias, a
swapped axis) is off by far more. Otherwise nothing is kept: a failed export removes every file
it wrote. ONNX is made by default for nets that read audio only (the student, AudioNet, VorasNet);
``onnx=True`` tries any net.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from datamodules.atomic import atomic_write
from zoo.weights.build import save_weights_file
from zoo.weights.converters import to_original
from zoo.weights.files import CheckpointError

log = logging.getLogger(__name__)

RELATIVE_TOLERANCE = 1e-4  #: of the largest |PyTorch output|: float32 rounding accumulated over the layers
ABSOLUTE_TOLERANCE = 1e-6  #: for outputs near zero


class ExportError(CheckpointError):
    """A net that could not be exported, or whose ONNX file disagrees with PyTorch (nothing is kept)."""


class _Positional(nn.Module):
    """The net with positional tensor inputs and a tuple of outputs, as ONNX needs."""

    def __init__(self, net: nn.Module, inputs: list[str], outputs: list[str]):
        super().__init__()
        self.net, self.input_names, self.output_names = net, inputs, outputs

    def forward(self, *tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
        outputs = self.net(dict(zip(self.input_names, tensors, strict=True)))
        return tuple(outputs[name] for name in self.output_names)


@dataclass
class Exported:
    """What :func:`export` wrote."""

    checkpoint: Path
    onnx: Path | None
    max_difference: float | None  #: largest |onnxruntime - PyTorch| over the outputs on example inputs
    original: Path | None = None  #: the state dict in an original code's layout, if asked for


def audio_only(net: nn.Module) -> bool:
    return set(getattr(net, "inputs", {})) == {"audio_mel"}


def onnx_metadata(net: nn.Module, net_kwargs: dict[str, Any], provenance: dict[str, Any]) -> dict[str, str]:
    """The ONNX file's metadata: net, kwargs, each input's recipe and shape, and where the front-end lives."""
    shapes = net.input_shapes()
    return {
        "aaute.net": net.model_name, "aaute.net_kwargs": json.dumps(net_kwargs, sort_keys=True),
        "aaute.inputs": json.dumps({name: {"recipe": recipe, "shape": ["B", *shapes[name]]}
                                    for name, recipe in net.inputs.items()}, sort_keys=True),
        "aaute.frontend": "not in this file: compute each input with datamodules.features "
                          "(mel_recipe / image_recipe of the named recipe) before running it",
        "aaute.provenance": json.dumps(provenance, sort_keys=True, default=str),
    }


def tolerance(expected: torch.Tensor, relative: float = RELATIVE_TOLERANCE) -> float:
    """The largest |onnxruntime - PyTorch| accepted for an output whose PyTorch value is ``expected``."""
    scale = float(expected.abs().max()) if expected.numel() else 0.0
    return relative * scale + ABSOLUTE_TOLERANCE


def export_onnx(net: nn.Module, path: Path, metadata: dict[str, str], relative: float = RELATIVE_TOLERANCE
                ) -> float:
    """Write ``net`` as ONNX to ``path`` (atomically) after checking it with onnxruntime; the largest difference.

    Every output must equal PyTorch's within :func:`tolerance` (``relative`` of its largest magnitude
    plus 1e-6), else :class:`ExportError` and nothing is written.
    """
    try:
        import onnx
        import onnxruntime
    except ImportError as error:
        raise ExportError(f"ONNX export needs onnx and onnxruntime ({error}); pip install -e '.[export]'") from None
    net = net.eval()
    inputs = list(net.inputs)
    example = net.example_inputs(2)
    with torch.no_grad():
        reference = net(example)
    outputs = sorted(name for name, value in reference.items() if isinstance(value, torch.Tensor))
    wrapper = _Positional(net, inputs, outputs).eval()
    batch = torch.export.Dim("batch", min=1)
    for name in ("onnxscript", "onnx_ir"):  # their pass-by-pass INFO lines are not this command's messages
        logging.getLogger(name).setLevel(logging.WARNING)
    with atomic_write(path) as tmp:
        onnx_tmp = tmp.with_suffix(".onnx")
        try:
            torch.onnx.export(wrapper, tuple(example[name] for name in inputs), str(onnx_tmp), input_names=inputs,
                              output_names=outputs, dynamo=True, external_data=False, verbose=False,
                              dynamic_shapes=(tuple({0: batch} for _ in inputs),))
            model = onnx.load(str(onnx_tmp))
        except Exception as error:  # the exporter's own failure: named, not a traceback
            raise ExportError(f"{net.model_name}: torch.onnx.export failed ({str(error).splitlines()[0][:200]})"
                              ) from None
        finally:
            onnx_tmp.unlink(missing_ok=True)
        for key, value in metadata.items():
            entry = model.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(model, str(tmp))
        session = onnxruntime.InferenceSession(str(tmp), providers=["CPUExecutionProvider"])
        check = net.example_inputs(3)  # another batch size than the traced one
        with torch.no_grad():
            expected = net(check)
        got = session.run(outputs, {name: check[name].numpy() for name in inputs})
        worst, excess = 0.0, None
        for value, name in zip(got, outputs, strict=True):
            difference = float((torch.from_numpy(value) - expected[name]).abs().max())
            bound = tolerance(expected[name], relative)
            worst = max(worst, difference)
            if difference > bound and excess is None:
                excess = f"{name}: {difference:.3g} > {bound:.3g}"
        if excess:
            raise ExportError(f"{path}: onnxruntime's outputs differ from PyTorch's beyond float32 rounding "
                              f"({excess}, {relative:g} of the output's scale + {ABSOLUTE_TOLERANCE:g}); "
                              f"the file was not kept")
    return worst


def export(net: nn.Module, out: str | Path, net_kwargs: dict[str, Any], provenance: dict[str, Any],
           onnx: bool | None = None, overwrite: bool = False, original_format: str | None = None) -> Exported:
    """Write ``<out>.pt`` and, for audio-only nets (or ``onnx=True``), ``<out>.onnx`` checked by onnxruntime.

    ``original_format`` (``aaute``) also writes ``<out>_aaute.pth``: a plain state dict in the original
    code's layout (:func:`zoo.weights.converters.to_original`).
    """
    out = Path(out)
    stem = out.with_suffix("") if out.suffix in (".pt", ".onnx") else out
    checkpoint, onnx_path = stem.with_suffix(".pt"), stem.with_suffix(".onnx")
    original_path = stem.with_name(f"{stem.name}_{original_format}.pth") if original_format else None
    want_onnx = audio_only(net) if onnx is None else onnx
    targets = (checkpoint, *([onnx_path] if want_onnx else []), *([original_path] if original_path else []))
    for path in targets:
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} already exists; pass --overwrite to replace it")
    written: list[Path] = []
    try:
        worst = None
        if want_onnx:  # first: the check most likely to refuse
            worst = export_onnx(net, onnx_path, onnx_metadata(net, net_kwargs, provenance))
            written.append(onnx_path)
            log.info("%s written; onnxruntime agrees with PyTorch within %.2g", onnx_path, worst)
        if original_path is not None:
            state = to_original(net, original_format)
            with atomic_write(original_path) as tmp:
                torch.save(state, tmp)
            written.append(original_path)
        save_weights_file(net, checkpoint, net_kwargs, {"provenance": provenance}, overwrite=True)
    except BaseException:  # a failed export keeps nothing of itself
        for path in written:
            path.unlink(missing_ok=True)
        raise
    return Exported(checkpoint, onnx_path if want_onnx else None, worst, original_path)
