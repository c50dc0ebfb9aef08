"""What one benchmark job does in its own process, returning one ``results.csv`` row.

- ``model``: builds the job's LightningCLI (the same configs and code path as ``aaute fit`` /
  ``aaute test``), fits, tests the checkpoint with the lowest ``val_loss`` under every light
  condition, and writes the per-window test predictions (raw and smoothed) beside its checkpoints;
- ``constant``: the constant-position predictor, the mean training target (ground truth or
  pseudo-label) of the same split, scored on the same test windows;
- ``profile``: :func:`benchmarks.profiler.profile_model` at the model's reference shapes;
- ``bound``: the Cramér–Rao bound of the same test windows (:mod:`benchmarks.limit`).
"""

from __future__ import annotations

import datetime
import logging
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from benchmarks.jobfolder import hold
from benchmarks.results import DRONES, PREDICTION_COLUMNS, RANGES, range_name
from benchmarks.suite import JobSpec
from datamodules.atomic import atomic_write

log = logging.getLogger(__name__)

def provenance(threads: int) -> dict[str, Any]:
    """Where and with what a row was made: commit, versions, machine."""
    import lightning
    import torch

    repo = Path(__file__).resolve().parents[1]

    def git(*args: str) -> str:
        try:
            return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, timeout=10,
                                  check=True).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    commit = git("rev-parse", "HEAD")
    dirty = bool(git("status", "--porcelain", "--untracked-files=no")) if commit else None
    try:
        from importlib.metadata import version

        aaute = version("aaute")
    except Exception:  # not installed as a distribution
        aaute = "unknown"
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else ""
    array = os.environ.get("SLURM_ARRAY_JOB_ID"), os.environ.get("SLURM_ARRAY_TASK_ID")
    slurm_job_id = f"{array[0]}_{array[1]}" if all(array) else os.environ.get("SLURM_JOB_ID", "")
    return {"git_commit": commit or "unknown", "git_dirty": dirty, "cpu": f"{cpu} ({os.cpu_count()} cores)",
            "gpu": gpu, "threads": threads, "node": os.environ.get("SLURMD_NODENAME") or platform.node(),
            "slurm_job_id": slurm_job_id,
            "versions": f"aaute={aaute};torch={torch.__version__};lightning={lightning.__version__};"
                        f"python={platform.python_version()}"}


def base_row(job: JobSpec) -> dict[str, Any]:
    """The columns every row of ``job`` has, whatever its outcome."""
    return {"kind": job.kind, "suite": job.suite, "job_id": job.job_id, "status": "ok", "model": job.model,
            "method": job.method, "category": job.category, "protocol": job.protocol, "seed": job.seed,
            "budget_note": job.budget_note, "config_hash": job.config_hash, "data": job.data.get("description"),
            "data_kind": job.data.get("kind"), "data_root": job.data.get("root"),
            "data_fingerprint": job.data.get("fingerprint"),
            "started_at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}


def run_job(job: JobSpec) -> dict[str, Any]:
    """Run ``job`` in this process and return its result row (raises on failure)."""
    import torch

    torch.set_num_threads(job.threads)
    sys.argv = sys.argv[:1]  # the launcher's own arguments are not LightningCLI's
    Path(job.job_dir).mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    row = base_row(job)
    with hold(job.job_dir):  # the folder is this job's while it runs (benchmarks.jobfolder)
        if job.kind == "model":
            row.update(_train_and_test(job))
        elif job.kind == "constant":
            row.update(_constant(job))
        elif job.kind == "bound":
            row.update(_bound(job))
        elif job.kind == "profile":
            from benchmarks.profiler import profile_model

            row.update(profile_model(job.model, **job.options))
        else:
            raise ValueError(f"unknown job kind {job.kind!r}")
    row.update(provenance(job.threads))
    row["wall_time_s"] = time.perf_counter() - start
    row["peak_rss_mb"] = _peak_rss_mb()
    return row


def _peak_rss_mb() -> float:
    """The peak resident memory of this process so far, in MiB (Linux reports ``ru_maxrss`` in KiB)."""
    import resource

    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 1024 if sys.platform != "darwin" else kib / 2**20  # macOS reports bytes


# ---------------------------------------------------------------------------------------------- data


def split_counts(datamodule) -> dict[str, Any]:
    """Recordings and windows per split (the DataModule's own summary), and what the data holds, as result columns."""
    summary = datamodule.split_summary()
    row: dict[str, Any] = {}
    for split in ("train", "val", "test"):
        row[f"n_{split}_sequences"] = summary[split]["sequences"]
        row[f"n_{split}_windows"] = summary[split]["windows"]
    drones = {p.drone for pieces in datamodule.sequences.values() for p in pieces if p.drone}
    row["drones"] = ",".join(sorted(drones))
    row["lights"] = ",".join(datamodule.test_lights)
    return row


def _sequence_table(datamodule) -> list[tuple[str, str, str]]:
    """(sequence id, recording id, drone) in the order batches index sequences."""
    return [(p.sequence_id, p.recording_id, p.drone or "")
            for split in ("train", "val", "test") for p in datamodule.sequences.get(split, [])]


def breakdown(frame: pd.DataFrame) -> dict[str, float]:
    """E per light x drone and per light x range band (the drone's distance from the rig origin)."""
    row: dict[str, float] = {}
    valid = frame[frame["gt_valid"] == 1]
    gt = valid[["gt_x", "gt_y", "gt_z"]].to_numpy()
    error = np.linalg.norm(valid[["x", "y", "z"]].to_numpy() - gt, axis=1)
    distance = np.linalg.norm(gt, axis=1)
    for light in valid["light"].unique():
        in_light = (valid["light"] == light).to_numpy()
        for drone in DRONES:
            rows = in_light & (valid["drone"] == drone).to_numpy()
            if rows.any():
                row[f"E_{light}_{drone}"] = float(error[rows].mean())
        for low, high in RANGES:
            rows = in_light & (distance >= low) & (distance < (np.inf if high is None else high))
            if rows.any():
                row[f"E_{light}_{range_name(low, high)}"] = float(error[rows].mean())
    return row


def _write_predictions(path: Path, frame: pd.DataFrame) -> str:
    from zoo.smoothing import DETECTION_COLUMNS

    columns = PREDICTION_COLUMNS + [column for column in DETECTION_COLUMNS if column in frame.columns]
    with atomic_write(path) as tmp:
        frame[columns].to_csv(tmp, index=False, float_format="%.4f")
    return str(path)


# ---------------------------------------------------------------------------------------------- jobs


def _train_and_test(job: JobSpec) -> dict[str, Any]:
    from zoo.cli import lightning_cli
    from zoo.smoothing import DEFAULT_PRESET

    job_dir = Path(job.job_dir)
    args = [*job.cli_args, "--trainer.default_root_dir", str(job_dir), "--trainer.enable_progress_bar", "false",
            "--trainer.logger", "lightning.pytorch.loggers.CSVLogger",
            "--trainer.logger.save_dir", str(job_dir), "--trainer.logger.name", "",
            "--trainer.logger.version", ""]  # metrics.csv and checkpoints/ directly in the job folder
    cli = lightning_cli(args, run=False)
    trainer, task, datamodule = cli.trainer, cli.model, cli.datamodule
    tester = trainer
    if task.learns:
        trainer.fit(task, datamodule=datamodule)
        best = getattr(trainer.checkpoint_callback, "best_model_path", "") or ""
        ckpt_path = best or None  # no validation loss to choose by: the weights of the last epoch, in memory
        if trainer.world_size > 1:  # tested in one process, so no metric or prediction is split between ranks
            if trainer.global_rank != 0:
                _leave_process_group()
                return {}  # rank 0's row is the job's
            _leave_process_group()
            tester = _single_process_tester(trainer, job_dir)
    else:  # a non-learned net (srp_phat) is tested as built
        best, ckpt_path = "", None
    epochs_run = trainer.current_epoch
    tester.test(task, datamodule=datamodule, ckpt_path=ckpt_path, verbose=False)
    metrics = {name: float(value) for name, value in tester.callback_metrics.items()}
    reduced = task.net.reduced_settings() if hasattr(task.net, "reduced_settings") else {}
    notes = [job.budget_note] if job.budget_note else []
    if reduced:
        notes.append("reduced-size adapters: " + ", ".join(f"{k} {v}" for k, v in reduced.items()))
    limit = trainer.limit_train_batches
    row: dict[str, Any] = {"alpha": task.hparams.alpha, "max_epochs": trainer.max_epochs,
                           "limit_train_batches": None if limit == 1.0 else limit, "epochs_run": epochs_run,
                           "batch_size": datamodule.hparams.batch_size, "checkpoint_path": best or ckpt_path or "",
                           "budget_note": "; ".join(notes),
                           "smoother": ((task.hparams.smoother or {}).get("preset") or DEFAULT_PRESET
                                        if task.hparams.smooth else "")}
    if best:
        import torch

        row["best_epoch"] = torch.load(best, map_location="cpu", weights_only=True, mmap=True)["epoch"]  # no full read
    for light in datamodule.test_lights:
        for name in ("Dx", "Dy", "Dz", "E", "RMSE"):
            row[f"{name}_{light}"] = metrics.get(f"test_{name}_{light}")
        row[f"E_smooth_{light}"] = metrics.get(f"test_E_smooth_{light}")
    row.update(split_counts(datamodule))
    frame = _prediction_frame(task, datamodule)
    row.update(breakdown(frame))
    row["predictions_path"] = _write_predictions(job_dir / "predictions.csv", frame)
    return row


def _leave_process_group() -> None:
    """End this process's part in a distributed (DDP) run once every rank has finished fitting."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def _single_process_tester(trainer, job_dir: Path):
    """A one-device Trainer on the fitted trainer's device, for the test stage after a DDP fit."""
    from lightning.pytorch import Trainer
    from lightning.pytorch.plugins.environments import LightningEnvironment

    device = trainer.strategy.root_device
    return Trainer(accelerator="gpu" if device.type == "cuda" else "cpu", devices=1, num_nodes=1,
                   precision=trainer.precision, logger=False, enable_checkpointing=False,
                   enable_progress_bar=False, enable_model_summary=False, default_root_dir=str(job_dir),
                   plugins=[LightningEnvironment()])  # not the cluster's: its task count is the fit's


def _prediction_frame(task, datamodule) -> pd.DataFrame:
    """Every test window of the last test run: prediction, ground truth and smoothed position (and for a net
    that detects, its :func:`~zoo.callbacks.detection_columns`)."""
    from zoo.callbacks import detection_columns

    sequences = _sequence_table(datamodule)
    parts = []
    for index, light in enumerate(datamodule.test_lights):
        smoothed = task.smoothed_predictions.get(index, {})
        for seq_index, seq in task.sequence_predictions(index).items():
            sequence_id, recording_id, drone = sequences[seq_index]
            part = pd.DataFrame({"sequence_id": sequence_id, "recording_id": recording_id, "drone": drone,
                                 "light": light, "timestamp": seq["time"], "gt_valid": seq["gt_valid"].astype(int)})
            part[["x", "y", "z"]] = seq["position"]
            part[["gt_x", "gt_y", "gt_z"]] = seq["gt"]
            part[["smooth_x", "smooth_y", "smooth_z"]] = smoothed.get(seq_index, np.full_like(seq["position"], np.nan))
            for column, values in detection_columns(seq).items():  # srp_phat: which windows it detected
                part[column] = values
            parts.append(part)
    if not parts:
        raise ValueError("the test run produced no predictions")
    return pd.concat(parts, ignore_index=True)


def _constant(job: JobSpec) -> dict[str, Any]:
    """The mean training target (``job.target``: gt or pseudo) predicted for every test window."""
    import torch

    from zoo.cli import lightning_cli
    from zoo.metrics import TrajectoryMetrics

    cli = lightning_cli(job.cli_args, run=False)
    datamodule = cli.datamodule
    datamodule.prepare_data()
    datamodule.setup("fit")
    datamodule.setup("test")
    train = datamodule.sequences["train"]
    target = np.concatenate([getattr(p, job.target) for p in train])
    valid = np.concatenate([getattr(p, f"{job.target}_valid") for p in train])
    if not valid.any():
        raise ValueError(f"no valid training {job.target} target to average")
    mean = target[valid].mean(axis=0)
    parts = []
    for light in datamodule.test_lights:
        for piece in datamodule.sequences["test"]:
            part = pd.DataFrame({"sequence_id": piece.sequence_id, "recording_id": piece.recording_id,
                                 "drone": piece.drone or "", "light": light, "timestamp": piece.times,
                                 "gt_valid": piece.gt_valid.astype(int)})
            part[["x", "y", "z"]] = np.broadcast_to(mean, (len(piece), 3))
            part[["gt_x", "gt_y", "gt_z"]] = piece.gt
            part[["smooth_x", "smooth_y", "smooth_z"]] = np.nan
            parts.append(part)
    frame = pd.concat(parts, ignore_index=True)
    row: dict[str, Any] = {"alpha": 1.0 if job.target == "pseudo" else 0.0}
    for light in datamodule.test_lights:  # the metric the trained models are scored with
        rows = frame[frame["light"] == light]
        metric = TrajectoryMetrics()
        metric.update(torch.from_numpy(rows[["x", "y", "z"]].to_numpy()),
                      torch.from_numpy(rows[["gt_x", "gt_y", "gt_z"]].to_numpy()),
                      torch.from_numpy(rows["gt_valid"].to_numpy() == 1))
        row.update({f"{name}_{light}": float(value) for name, value in metric.compute().items()})
    row.update(split_counts(datamodule))
    row.update(breakdown(frame))
    row["predictions_path"] = _write_predictions(Path(job.job_dir) / "predictions.csv", frame)
    return row


def _bound(job: JobSpec) -> dict[str, Any]:
    """The physical limit of the split's test windows (``job.options["band_hz"]``: None for the full band)."""
    from benchmarks.limit import bound_frame, bound_metrics
    from zoo.cli import lightning_cli

    datamodule = lightning_cli(job.cli_args, run=False).datamodule
    datamodule.prepare_data()
    datamodule.setup("fit")
    datamodule.setup("test")
    frame = bound_frame(datamodule, job.options.get("band_hz"))
    row = bound_metrics(frame, job.options.get("band_hz"))
    row.update(split_counts(datamodule))
    path = Path(job.job_dir) / "bounds.csv"
    with atomic_write(path) as tmp:
        frame[[*PREDICTION_COLUMNS, "bound_m", "snr_source"]].to_csv(tmp, index=False, float_format="%.6f")
    row["predictions_path"] = str(path)
    return row
