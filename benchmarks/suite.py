"""Benchmark suites: a YAML file naming data, protocols, light conditions, models, seeds and budget.

A suite expands into jobs (:class:`JobSpec`): one per model x protocol x seed (a model trained with
``aaute fit`` and tested with ``aaute test``, through the same LightningCLI configs), one constant-
position predictor per protocol x seed and training target, and one profile per model. Every
job's LightningCLI arguments are parsed (not run) when the suite is loaded, so a wrong config key
fails before anything trains. The keys (all paths relative to the working directory)::

    name: quick
    out: demo_out/benchmark               # results.csv, one folder per job, logs
    data:
      description: simulated rooftop flights
      kind: simulated                     # simulated | real (stated in every caption)
      config: configs/data/sim.yaml
      root: demo_out/data
      simulate: {sequences: 15, seconds: 20, seed: 0}   # optional: made first, reused when complete
      label: {workers: 2}                 # optional: the LiDAR teacher on recordings without labels
      init_args: {label_rate: 5.0}        # overrides of the data config (--data.<key>)
    trainer: {config: [configs/trainer/default.yaml, configs/trainer/best_only.yaml], overrides: {max_epochs: 5}}
    protocols: {by_sequence: {seed: 0, val: 0.2, test: 0.2}}
    lights: [ideal, dark]
    seeds: [0]
    smoothing: true                       # or a smoother preset name (paper, tuned, robust) to use it
    constant: [gt, pseudo]                # constant-position rows (mean training GT / pseudo-label)
    bound: true                           # the CRLB row (benchmarks/limit.py): false | true | {band_hz: [lo, hi]};
                                          # default true for simulated data, false for real
    models:
      - {model: student, config: configs/model/student.yaml, protocols: [by_sequence],
         args: {trainer.max_epochs: 20}, budget_note: "", method: "", tag: "",   # tag: tells apart two
         memory_gb: 1.4,                  # entries of one model (job id <model>_<tag>-<protocol>-s<seed>);
                                          # memory_gb: its expected peak until a run has measured one
         seeds: [0],                      # some of the suite's seeds only (default: all of them)
         split: {train_flights: 5}}       # keys added to each protocol's split (--data.split) for this entry
    profile: {min_run_time: 0.5, throughput_batch: 64}   # or false
    launcher: {kind: local, parallel: 2, threads_per_job: 1, timeout_min: 120,
               memory_gb: 4, job_memory_gb: 1.5,   # local jobs' summed expected peaks (benchmarks/scheduling.py)
               slurm: {partition: gpu, gpus_per_node: 1, cpus_per_task: 8}}

``memory_gb``, ``job_memory_gb`` and ``budget_note`` are not part of a job's identity (its id and
configuration hash): changing them never makes a finished job run again.

On Slurm, each stage's jobs go as one job array and ``launcher.parallel`` is its concurrency limit.
A job asking for several devices trains with Lightning's DDP: under Slurm give ``ntasks_per_node``
equal to ``trainer.devices`` (Lightning reads the Slurm environment; the fitted model is then tested
in one process); in a local job use
``trainer.strategy: ddp_spawn``, which needs no re-launch of the job's command line.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from benchmarks.limit import BOUND_METHOD, BOUND_MODEL, BoundError, bound_options
from benchmarks.results import LIGHTS, PROTOCOLS
from datamodules.errors import AauteError

SUITE_KEYS = {"name", "description", "out", "data", "trainer", "protocols", "lights", "seeds", "smoothing",
              "constant", "models", "profile", "launcher", "expected_runtime", "bound"}
DATA_KEYS = {"description", "kind", "config", "root", "simulate", "label", "init_args"}
MODEL_KEYS = {"model", "config", "protocols", "args", "budget_note", "method", "tag", "memory_gb", "seeds", "split"}
LAUNCHER_KEYS = {"kind", "parallel", "threads_per_job", "timeout_min", "slurm", "memory_gb", "job_memory_gb"}
LAUNCHERS = ("local", "slurm", "debug")
CONSTANT_TARGETS = ("gt", "pseudo")

#: display names in the paper's table
METHOD_NAMES = {"student": "Ours (AAUTE student)", "audionet": "AudioNet", "voranet": "VorasNet",
                "asdnet": "ASDNet", "avped": "AV-PED", "avfdti": "AV-FDTI", "visualnet": "VisualNet",
                "darknet": "DarkNet", "srp_phat": "SRP-PHAT", "phase_student": "Phase student (GCC-PHAT)"}


class SuiteError(AauteError, ValueError):
    """A suite file that cannot run (the message names the file and the key)."""


@dataclass
class JobSpec:
    """One job of a suite: everything its process needs (picklable)."""

    job_id: str
    kind: str  #: model | constant | profile | bound
    suite: str
    model: str
    method: str
    category: str
    protocol: str | None
    seed: int | None
    cli_args: list[str]
    job_dir: str
    threads: int
    budget_note: str = ""
    memory_gb: float | None = None  #: the suite's hint of its peak memory (not part of its identity)
    target: str = ""  #: constant jobs: 'gt' or 'pseudo'
    data: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)  #: profile options
    config_hash: str = ""


@dataclass
class Suite:
    """A loaded, checked suite."""

    path: Path
    name: str
    out: Path
    raw: dict[str, Any]

    @property
    def data(self) -> dict[str, Any]:
        return self.raw["data"]

    @property
    def launcher(self) -> dict[str, Any]:
        defaults = {"kind": "local", "parallel": 1, "threads_per_job": 1, "timeout_min": 720, "slurm": {},
                    "memory_gb": None, "job_memory_gb": None}
        return {**defaults, **(self.raw.get("launcher") or {})}

    @property
    def results_path(self) -> Path:
        return self.out / "results.csv"


def _fail(path: Path, message: str) -> SuiteError:
    return SuiteError(f"{path}: {message}")


def _cli_value(value: Any) -> str:
    """A value as LightningCLI reads it from the command line (YAML/JSON for containers)."""
    if isinstance(value, dict | list | tuple):
        return json.dumps(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    return "null" if value is None else str(value)


def _as_args(prefix: str, mapping: dict[str, Any]) -> list[str]:
    args: list[str] = []
    for key, value in mapping.items():
        args += [f"--{prefix}{key}", _cli_value(value)]
    return args


def load_suite(path: str | Path, overrides: dict[str, Any] | None = None) -> Suite:
    """Read and check a suite; ``overrides`` replace top-level or ``data.*`` keys (e.g. ``{"data.root": ...}``)."""
    from zoo.registry import list_models

    path = Path(path)
    if not path.is_file():
        raise SuiteError(f"{path}: no such suite file")
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as error:
        raise _fail(path, f"not valid YAML ({str(error).splitlines()[0]})") from None
    if not isinstance(raw, dict):
        raise _fail(path, "a suite is a mapping of keys (name, data, models, ...)")
    for key, value in (overrides or {}).items():
        if value is None:
            continue
        section, _, sub = key.partition(".")
        if sub:
            raw.setdefault(section, {})[sub] = value
        else:
            raw[section] = value
    unknown = sorted(set(raw) - SUITE_KEYS)
    if unknown:
        raise _fail(path, f"unknown key(s) {unknown}; known: {sorted(SUITE_KEYS)}")
    for key in ("name", "data", "models"):
        if key not in raw:
            raise _fail(path, f"missing key {key!r}")
    data = raw["data"]
    unknown = sorted(set(data) - DATA_KEYS)
    if unknown:
        raise _fail(path, f"unknown data key(s) {unknown}; known: {sorted(DATA_KEYS)}")
    for key in ("config", "root"):
        if not data.get(key):
            raise _fail(path, f"data.{key} is required")
    if data.get("kind", "simulated") not in ("simulated", "real"):
        raise _fail(path, f"data.kind must be 'simulated' or 'real', got {data.get('kind')!r}")
    protocols = raw.setdefault("protocols", {"by_sequence": {}})
    bad = sorted(set(protocols) - set(PROTOCOLS))
    if bad:
        raise _fail(path, f"unknown protocol(s) {bad}; known: {list(PROTOCOLS)}")
    lights = raw.setdefault("lights", list(LIGHTS))
    if not lights or set(lights) - set(LIGHTS):
        raise _fail(path, f"lights must be a non-empty subset of {list(LIGHTS)}, got {lights}")
    seeds = raw.setdefault("seeds", [0])
    if (not isinstance(seeds, list) or not seeds or any(type(s) is not int for s in seeds)
            or len(set(seeds)) != len(seeds)):
        raise _fail(path, f"seeds must be a non-empty list of distinct integers, got {seeds!r}")
    constant = raw.setdefault("constant", list(CONSTANT_TARGETS))
    if constant and set(constant) - set(CONSTANT_TARGETS):
        raise _fail(path, f"constant must list targets of {list(CONSTANT_TARGETS)}, got {constant}")
    try:
        bound_options(raw.get("bound"), data.get("kind", "simulated"), str(path))
    except BoundError as error:
        raise SuiteError(str(error)) from None
    known = list_models()
    models = raw["models"]
    if not isinstance(models, list) or not models:
        raise _fail(path, "models must be a non-empty list")
    for entry in models:
        if not isinstance(entry, dict) or "model" not in entry:
            raise _fail(path, f"each models entry needs a 'model' key, got {entry!r}")
        unknown = sorted(set(entry) - MODEL_KEYS)
        if unknown:
            raise _fail(path, f"model {entry['model']!r}: unknown key(s) {unknown}; known: {sorted(MODEL_KEYS)}")
        if entry["model"] not in known:
            raise _fail(path, f"unknown model {entry['model']!r}; known models: {', '.join(known)}")
        _check_gb(path, f"model {entry['model']!r}: memory_gb", entry.get("memory_gb"))
        own_seeds = entry.get("seeds", seeds)
        if not isinstance(own_seeds, list) or not own_seeds or not set(own_seeds) <= set(seeds):
            raise _fail(path, f"model {entry['model']!r}: seeds must be a non-empty list of the suite's seeds "
                              f"{seeds}, got {own_seeds!r}")
        if not isinstance(entry.get("split", {}), dict):
            raise _fail(path, f"model {entry['model']!r}: split must be a mapping of split keys, got "
                              f"{entry['split']!r}")
        for name in entry.get("protocols") or []:
            if name not in protocols:
                raise _fail(path, f"model {entry['model']!r} names protocol {name!r}, which the suite does not "
                                  f"define (defined: {sorted(protocols)})")
    _refuse_repeated_models(path, models, list(protocols))
    launcher = raw.get("launcher") or {}
    unknown = sorted(set(launcher) - LAUNCHER_KEYS)
    if unknown:
        raise _fail(path, f"unknown launcher key(s) {unknown}; known: {sorted(LAUNCHER_KEYS)}")
    for key in ("memory_gb", "job_memory_gb"):
        _check_gb(path, f"launcher.{key}", launcher.get(key))
    if launcher.get("kind", "local") not in LAUNCHERS:
        raise _fail(path, f"launcher.kind must be one of {list(LAUNCHERS)}, got {launcher.get('kind')!r}")
    for config in _config_files(raw):
        if not Path(config).is_file():
            raise _fail(path, f"config file {config} not found")
    return Suite(path, str(raw["name"]), Path(raw.get("out") or f"benchmark_out/{raw['name']}"), raw)


def _check_gb(path: Path, what: str, value: Any) -> None:
    """A memory figure is a positive number of GB (or absent)."""
    if value is not None and (type(value) not in (int, float) or not value > 0 or value == float("inf")):
        raise _fail(path, f"{what} must be a positive number of GB, got {value!r}")


def _refuse_repeated_models(path: Path, models: list[dict[str, Any]], protocols: list[str]) -> None:
    """Two entries of one model (and tag) in one protocol would share a job id and a folder: refused."""
    seen: set[tuple[str, str, str]] = set()
    for entry in models:
        for protocol in entry.get("protocols") or protocols:
            key = (entry["model"], str(entry.get("tag") or ""), protocol)
            if key in seen:
                raise _fail(path, f"model {entry['model']!r} is listed twice for protocol {protocol!r} (its jobs "
                                  f"would share one id and folder); keep one entry, or give each its own tag")
            seen.add(key)


def _trainer_configs(raw: dict[str, Any]) -> list[str]:
    configs = (raw.get("trainer") or {}).get("config") or []
    return [configs] if isinstance(configs, str) else list(configs)


def _config_files(raw: dict[str, Any]) -> list[str]:
    return [*_trainer_configs(raw), raw["data"]["config"], *(m["config"] for m in raw["models"] if m.get("config"))]


def _job_configs(raw: dict[str, Any], entry: dict[str, Any]) -> list[str]:
    """The config files of one model job, in the order LightningCLI merges them."""
    return [str(c) for c in (*_trainer_configs(raw), raw["data"]["config"], entry.get("config")) if c]


def _file_digest(paths: list[str]) -> str:
    digest = hashlib.sha256()
    for item in paths:
        digest.update(item.encode())
        digest.update(Path(item).read_bytes())
    return digest.hexdigest()


def _hash(*parts: Any) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def model_args(suite: Suite, entry: dict[str, Any], protocol: str, seed: int) -> list[str]:
    """The LightningCLI arguments of one model job (configs, then the suite's overrides, then the job's)."""
    raw, data = suite.raw, suite.data
    block = dict(raw["protocols"].get(protocol) or {})
    explicit = any(isinstance(block.get(name), list | str) for name in ("train", "val", "test"))
    split = {"protocol": protocol, **({} if explicit else {"seed": seed}), **block, **(entry.get("split") or {})}
    args: list[str] = []
    for config in _job_configs(raw, entry):
        args += ["--config", str(config)]
    args += ["--data.root", _cli_value(data["root"]), "--data.split", _cli_value(split),
             "--data.test_lights", _cli_value(list(raw["lights"]))]
    args += _as_args("data.", data.get("init_args") or {})
    args += _as_args("trainer.", (raw.get("trainer") or {}).get("overrides") or {})
    smoothing = raw.get("smoothing", True)
    args += ["--model.smooth", _cli_value(bool(smoothing))]
    if isinstance(smoothing, str):  # a preset name: the model configs' own smoother is replaced
        args += ["--model.smoother", _cli_value({"preset": smoothing})]
    args += _as_args("", entry.get("args") or {})
    args += ["--seed_everything", str(seed)]
    return args


def expand_jobs(suite: Suite, data_fingerprint: str = "") -> list[JobSpec]:
    """Every job of the suite, in run order: models and constants first, profiles last."""
    from zoo.registry import model_class

    raw = suite.raw
    launcher = suite.launcher
    threads = int(launcher["threads_per_job"])
    seeds = list(raw["seeds"])
    data_info = {"description": suite.data.get("description", ""), "kind": suite.data.get("kind", "simulated"),
                 "root": str(suite.data["root"]), "fingerprint": data_fingerprint}
    jobs: list[JobSpec] = []
    bound = bound_options(raw.get("bound"), data_info["kind"], str(suite.path))
    # constant and bound jobs take the windows of the student's config (else the first model's), not its training
    reference = next((m for m in raw["models"] if m["model"] == "student"), raw["models"][0])
    windows = {"model": reference["model"], "config": reference.get("config")}
    for protocol in raw["protocols"]:
        for seed in seeds:
            for entry in raw["models"]:
                if (protocol not in (entry.get("protocols") or list(raw["protocols"]))
                        or seed not in entry.get("seeds", seeds)):
                    continue
                name = entry["model"]
                args = model_args(suite, entry, protocol, seed)
                job_id = f"{name}{'_' + str(entry['tag']) if entry.get('tag') else ''}-{protocol}-s{seed}"
                jobs.append(JobSpec(
                    job_id=job_id, kind="model", suite=suite.name, model=name,
                    method=entry.get("method") or METHOD_NAMES.get(name, name),
                    category=model_class(name).category, protocol=protocol, seed=seed, cli_args=args,
                    job_dir=str(suite.out / "jobs" / job_id), threads=threads,
                    budget_note=entry.get("budget_note", ""), memory_gb=entry.get("memory_gb"), data=data_info,
                    config_hash=_hash("model", args, _file_digest(_job_configs(raw, entry)), data_fingerprint)))
            for target in raw.get("constant") or []:
                args = model_args(suite, windows, protocol, seed)
                job_id = f"constant_{target}-{protocol}-s{seed}"
                jobs.append(JobSpec(
                    job_id=job_id, kind="constant", suite=suite.name, model="constant",
                    method=f"Constant (mean train {'GT' if target == 'gt' else 'pseudo-label'})",
                    category="reference", protocol=protocol, seed=seed, cli_args=args,
                    job_dir=str(suite.out / "jobs" / job_id), threads=threads, target=target, data=data_info,
                    config_hash=_hash("constant", target, args, _file_digest(_job_configs(raw, windows)),
                                      data_fingerprint)))
            if bound is not None:
                args = model_args(suite, windows, protocol, seed)
                job_id = f"bound-{protocol}-s{seed}"
                jobs.append(JobSpec(
                    job_id=job_id, kind="bound", suite=suite.name, model=BOUND_MODEL, method=BOUND_METHOD,
                    category="reference", protocol=protocol, seed=seed, cli_args=args,
                    job_dir=str(suite.out / "jobs" / job_id), threads=threads, data=data_info, options=bound,
                    config_hash=_hash("bound", bound, args, _file_digest(_job_configs(raw, windows)),
                                      data_fingerprint)))
    repeated = sorted({job.job_id for job in jobs if [j.job_id for j in jobs].count(job.job_id) > 1})
    if repeated:
        raise _fail(suite.path, f"jobs {repeated} appear twice: give the models entries of one model distinct tags")
    profile = raw.get("profile", {})
    if profile is not False:
        options = dict(profile or {})
        for name in dict.fromkeys(m["model"] for m in raw["models"]):
            job_id = f"profile-{name}"
            jobs.append(JobSpec(
                job_id=job_id, kind="profile", suite=suite.name, model=name,
                method=METHOD_NAMES.get(name, name), category=model_class(name).category, protocol=None, seed=None,
                cli_args=[], job_dir=str(suite.out / "jobs" / job_id), threads=threads, options=options,
                config_hash=_hash("profile", name, options)))
    return jobs


def check_job_args(suite: Suite, jobs: list[JobSpec]) -> None:
    """Parse every training job's LightningCLI arguments without building anything; a bad key is a SuiteError."""
    from zoo.cli import lightning_cli

    for job in jobs:
        if job.kind != "model":
            continue
        try:
            lightning_cli(job.cli_args, run=False, instantiate=False, exit_on_error=False)
        except (argparse.ArgumentError, SystemExit, ValueError) as error:
            lines = [line.strip() for line in str(error).splitlines() if line.strip()]
            specific = [line for line in lines if "not accepted" in line or "Expected" in line]
            detail = "; ".join(dict.fromkeys(specific[:2])) or (lines[0] if lines else repr(error))
            raise _fail(suite.path, f"job {job.job_id}: its configuration does not parse: {detail}") from None
