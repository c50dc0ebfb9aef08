"""A tiny benchmark suite on the session's labelled fixture flights, written at test time."""

from __future__ import annotations

from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[2]
SPLIT = {"train": ["sim11-0000-avata"], "val": ["sim11-0001-m300"], "test": ["sim11-0002-mavic2"]}


def write_suite(path: Path, **changes) -> Path:
    """A suite YAML of one student and the GT constant on the three fixture flights; `changes` replace keys."""
    suite = {
        "name": "tiny",
        "out": str(path.parent / "out"),
        "data": {"description": "three 4 s simulated flights", "kind": "simulated",
                 "config": str(REPO / "configs/data/sim.yaml"), "root": changes.pop("root"),
                 "init_args": {"window_seconds": 1.0, "batch_size": 4, "cache_dir": changes.pop("cache")}},
        "trainer": {"config": [str(REPO / "configs/trainer" / name) for name in ("default.yaml", "best_only.yaml")],
                    "overrides": {"accelerator": "cpu", "max_epochs": 1, "limit_train_batches": 2,
                                  "limit_val_batches": 1, "enable_model_summary": False}},
        "protocols": {"by_sequence": SPLIT},
        "lights": ["ideal", "dark"],
        "seeds": [0],
        "smoothing": False,
        "constant": ["gt"],
        "bound": False,
        "models": [{"model": "student", "config": str(REPO / "configs/model/student.yaml"),
                    "args": {"model.lr": changes.pop("lr", 1e-4)}}],
        "profile": False,
        "launcher": {"kind": "local", "parallel": 2, "threads_per_job": 1, "timeout_min": 10},
    }
    suite.update(changes)
    path.write_text(yaml.safe_dump(suite))
    return path
