"""A finished benchmark job's best checkpoint, registered as named weights (``student.sim_quick``, ...).

The name is ``<model>.<data>_<suite>``: ``sim`` or ``real`` for the suite's data kind, then the
suite's name; a job of another protocol than the suite's first, or of another seed than its first,
adds ``_<protocol>`` / ``_s<seed>`` (``student.sim_quick_random_windows``). The entry points at the
checkpoint where the job wrote it (no copy) with its sha256, and records the job's test metrics,
data, protocol and provenance, so ``load_pretrained("student", weights="sim_quick")`` and
``aaute predict --weights student.sim_quick`` use it and ``aaute weights list`` shows it.
The runner calls :func:`register_job_weights` as each job ends.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from benchmarks.suite import JobSpec, Suite

log = logging.getLogger(__name__)

METRICS = [f"{name}_{light}" for light in ("ideal", "dark") for name in ("E", "Dx", "Dy", "Dz", "E_smooth")]
LICENCES = {"simulated": "Apache-2.0 (trained on data of the project's simulator)",
            "real": "trained on MMAUD (CC BY-NC-SA 4.0): non-commercial research use"}


def weights_name(suite: Suite, job: JobSpec) -> str:
    """``<model>.<sim|real>_<suite>[_<protocol>][_s<seed>]`` (see the module docstring)."""
    kind = "real" if suite.data.get("kind") == "real" else "sim"
    tag = f"{kind}_{suite.name}"
    protocols = list(suite.raw.get("protocols") or {})
    if protocols and job.protocol != protocols[0]:
        tag += f"_{job.protocol}"
    seeds = [int(s) for s in suite.raw.get("seeds") or [0]]
    if job.seed is not None and job.seed != seeds[0]:
        tag += f"_s{job.seed}"
    return f"{job.model}.{tag}"


def register_job_weights(suite: Suite, job: JobSpec, row: dict[str, Any]):
    """Register the best checkpoint of a finished model job; returns the entry (None when there is none)."""
    from zoo.weights import Weights, register_weights
    from zoo.weights.files import read_checkpoint

    checkpoint = row.get("checkpoint_path")
    if job.kind != "model" or row.get("status") != "ok" or not checkpoint or checkpoint == "last":
        return None
    path = Path(checkpoint)
    if not path.is_absolute():
        path = suite.out / path
    contents = read_checkpoint(path)  # refuses anything but this project's checkpoint
    if contents.net != job.model:
        raise ValueError(f"{path}: the checkpoint of job {job.job_id} holds a {contents.net!r} net, not {job.model!r}")
    from zoo.registry import model_class

    inputs = model_class(job.model).resolve_input_recipes(contents.net_kwargs.get("input_recipes"))
    metrics = {key: float(row[key]) for key in METRICS if isinstance(row.get(key), int | float)}
    entry = Weights(
        weights_name(suite, job), str(path.resolve()), "", net_kwargs=contents.net_kwargs, inputs=inputs,
        data=f"{row.get('data') or suite.data.get('description', '')} ({suite.data.get('kind', 'simulated')})",
        protocol=str(job.protocol or ""), metrics=metrics,
        licence=LICENCES["real" if suite.data.get("kind") == "real" else "simulated"],
        provenance={"suite": suite.name, "job_id": job.job_id, "results": str(suite.results_path.resolve()),
                    "seed": job.seed, "config_hash": job.config_hash, "git_commit": row.get("git_commit"),
                    "best_epoch": row.get("best_epoch"), "budget_note": row.get("budget_note")})
    return register_weights(entry)
