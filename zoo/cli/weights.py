"""The weights subcommands of ``aaute``: ``weights list|register``, ``import-checkpoint`` and ``export``."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

log = logging.getLogger("aaute")

#: the layouts of :mod:`zoo.weights.converters` (named here so that building the parser does not import torch)
FORMATS = ("aaute", "avfdti", "avfdti-comparison", "avped")


def _status(entry) -> str:
    from zoo.weights import weights_dir

    if entry.is_url:
        cached = list((weights_dir() / "files").glob(f"{entry.sha256[:12]}-*"))
        return "cached" if cached else "not cached"
    return "ok" if Path(entry.source).is_file() else "missing"


def _cmd_weights_list(args: argparse.Namespace) -> int:
    from datamodules.describe import format_table
    from zoo.weights import all_weights, weights_dir

    rows = []
    for name, entry in sorted(all_weights().items()):
        if args.model and entry.model != args.model:
            continue
        metrics = ", ".join(f"{key} {value:.2f}" for key, value in entry.metrics.items()
                            if key.startswith("E_") and value == value)
        rows.append({"name": name, "data": entry.data, "protocol": entry.protocol, "metrics (m)": metrics,
                     "status": _status(entry), "source": entry.source})
    if not rows:
        sys.stdout.write(f"no weights registered (registry: {weights_dir() / 'registry.json'}); "
                         f"'aaute benchmark' registers its jobs' best checkpoints\n")
        return 0
    sys.stdout.write(format_table(rows) + "\n")
    return 0


def _cmd_weights_register(args: argparse.Namespace) -> int:
    from zoo.weights import Weights, build_net, register_weights
    from zoo.weights.files import read_checkpoint

    contents = read_checkpoint(args.file)
    model = args.name.split(".", 1)[0]
    net = build_net(contents, model, None)  # refuses a file that does not load into that model
    entry = register_weights(Weights(args.name, str(args.file), "", net_kwargs=getattr(net, "net_kwargs", {}),
                                     inputs=dict(net.inputs), data=args.data or "", licence=args.licence or ""))
    log.info("registered %s -> %s (sha256 %s)", entry.name, entry.source, entry.sha256)
    return 0


def _cmd_import(args: argparse.Namespace) -> int:
    from zoo.weights import Weights, file_sha256, register_weights, save_weights_file
    from zoo.weights.converters import convert_state
    from zoo.weights.files import read_file

    source = Path(args.file)
    conversion = convert_state(read_file(source), args.format, str(source), args.model)
    net = conversion.net
    metadata = {"converted_from": str(source), "source_sha256": file_sha256(source), "format": args.format,
                "layout": conversion.layout.name, "original": conversion.layout.original,
                "dropped": conversion.dropped}
    out = save_weights_file(net, args.out, conversion.net_kwargs, metadata, overwrite=args.overwrite)
    log.info("%s (%s) -> %s: %s %s, %d tensors mapped, %d dead or duplicate dropped", source,
             conversion.layout.original, out, conversion.layout.model, conversion.net_kwargs,
             len(conversion.renamed), len(conversion.dropped))
    if args.register:
        name = args.register if "." in args.register else f"{conversion.layout.model}.{args.register}"
        register_weights(Weights(name, str(out), "", net_kwargs=conversion.net_kwargs, inputs=dict(net.inputs),
                                 data=args.data or "", provenance=metadata))
        log.info("registered as %s", name)
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from zoo.deploy.export import export
    from zoo.weights import build_net, resolve_weights

    contents, entry = resolve_weights(args.model, args.weights, None)
    net = build_net(contents, args.model, None, entry)
    provenance = {"source": str(contents.path), "kind": contents.kind,
                  **({"weights": entry.name, "sha256": entry.sha256, "data": entry.data, "protocol": entry.protocol,
                      "metrics": entry.metrics} if entry else {}), **contents.metadata.get("provenance", {})}
    if contents.metadata.get("audio_sample_rates"):  # the rates it was trained at: aaute track checks them
        provenance["audio_sample_rates"] = contents.metadata["audio_sample_rates"]
    hparams = contents.metadata.get("hyper_parameters")
    if hparams:
        provenance["hyper_parameters"] = {key: hparams.get(key) for key in ("alpha", "loss", "lr")}
    done = export(net, args.out, getattr(net, "net_kwargs", {}), provenance,
                  onnx=args.onnx, overwrite=args.overwrite, original_format=args.original_format)
    if done.original is not None:
        log.info("%s written (the %s code's layout)", done.original, args.original_format)
    log.info("%s written%s", done.checkpoint, f"; {done.onnx} (max |onnxruntime - torch| {done.max_difference:.2g})"
             if done.onnx else " (no ONNX: the net reads images; --onnx to try)")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    """``weights list|register``, ``import-checkpoint`` and ``export``."""
    weights = sub.add_parser("weights", help="named pretrained weights: list what is available and where, register")
    actions = weights.add_subparsers(dest="weights_command", required=True)
    listing = actions.add_parser("list", help="the registered weights, their data, metrics, status and file")
    listing.add_argument("--model", help="only this model's weights")
    listing.set_defaults(func=_cmd_weights_list)
    register = actions.add_parser("register", help="register a weights file under a name")
    register.add_argument("name", help="<model>.<tag>, e.g. student.mine")
    register.add_argument("file", type=Path, help="a .ckpt of this project, an exported or imported .pt file")
    register.add_argument("--data", help="what it was trained on")
    register.add_argument("--licence", help="its licence")
    register.set_defaults(func=_cmd_weights_register)

    imp = sub.add_parser("import-checkpoint", help="convert a checkpoint of the original authors' code to a zoo net")
    imp.add_argument("file", type=Path, help="the original state dict (.pth)")
    imp.add_argument("--format", required=True, choices=FORMATS,
                     help="aaute: AAUTE audio_net.py; avfdti: AV-FDTI nets/AVFDTI.py; avfdti-comparison: the "
                          "baselines of AV-FDTI nets/comparison/; avped: AV-PedAware network/avped.py")
    imp.add_argument("--out", required=True, type=Path, help="the converted, self-describing weights file (.pt)")
    imp.add_argument("--model", help="the zoo model, where a format has several layouts (avfdti-comparison)")
    imp.add_argument("--register", metavar="NAME", help="also register the result as weights NAME")
    imp.add_argument("--data", help="what the original was trained on (recorded when registering)")
    imp.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    imp.set_defaults(func=_cmd_import)

    exp = sub.add_parser("export", help="a self-describing checkpoint and an ONNX file checked by onnxruntime")
    exp.add_argument("--weights", required=True, help="registered weights (aaute weights list) or a weights file")
    exp.add_argument("--model", help="the model (needed for a bare state dict)")
    exp.add_argument("--out", required=True, type=Path, help="output stem: writes <out>.pt and <out>.onnx")
    exp.add_argument("--onnx", action=argparse.BooleanOptionalAction, default=None,
                     help="write ONNX (default: for nets that read audio only)")
    exp.add_argument("--original-format", choices=["aaute"],
                     help="also write <out>_<format>.pth in the original code's layout (the student as AAUTE's "
                          "AudioNet)")
    exp.add_argument("--overwrite", action="store_true", help="replace existing files")
    exp.set_defaults(func=_cmd_export)
