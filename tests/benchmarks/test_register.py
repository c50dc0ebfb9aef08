"""A finished job's best checkpoint becomes named weights, loadable by name and listed by ``aaute weights list``."""

from __future__ import annotations

import logging
from pathlib import Path

import torch

from benchmarks.jobs import base_row
from benchmarks.register import weights_name
from benchmarks.runner import register_finished_job
from benchmarks.suite import expand_jobs, load_suite
from zoo.cli import main
from zoo.task import TrajectoryTask
from zoo.weights import get_weights, list_weights, load_pretrained

REPO = Path(__file__).resolve().parents[2]


def _finished(suite, job, net: str = "student", seed: int = 0) -> tuple[dict, TrajectoryTask]:
    """The row and checkpoint a finished model job leaves (Lightning's layout: net. keys + hyper_parameters)."""
    torch.manual_seed(seed)
    task = TrajectoryTask(net, net_kwargs={"kernels": 8, "feature_dim": 32} if net == "student" else {})
    relative = Path("jobs") / job.job_id / "checkpoints" / "epoch=3-step=40.ckpt"
    path = suite.out / relative
    path.parent.mkdir(parents=True)
    torch.save({"epoch": 3, "global_step": 40, "state_dict": task.state_dict(),
                "hyper_parameters": dict(task.hparams)}, path)
    row = base_row(job)
    row.update(checkpoint_path=str(relative), E_ideal=4.25, E_dark=4.5, Dx_ideal=1.0, best_epoch=3,
               data="simulated MMAUD-like rooftop flights", git_commit="abc123")
    return row, task


def test_finished_jobs_register_their_best_checkpoints(tmp_path, monkeypatch, capsys, caplog):
    monkeypatch.setenv("AAUTE_CACHE", str(tmp_path / "cache"))
    suite = load_suite(REPO / "configs" / "benchmark" / "quick.yaml", {"out": str(tmp_path / "benchmark")})
    jobs = {job.job_id: job for job in expand_jobs(suite)}
    by_sequence, leaky = jobs["student-by_sequence-s0"], jobs["student-random_windows-s0"]
    assert weights_name(suite, by_sequence) == "student.sim_quick"
    assert weights_name(suite, leaky) == "student.sim_quick_random_windows"

    row, task = _finished(suite, by_sequence)
    register_finished_job(suite, by_sequence, row)
    register_finished_job(suite, leaky, {**_finished(suite, leaky, seed=1)[0], "status": "failed"})  # not registered
    assert list_weights() == ["student.sim_quick"]
    entry = get_weights("student.sim_quick")
    assert entry.metrics == {"E_ideal": 4.25, "E_dark": 4.5, "Dx_ideal": 1.0} and entry.protocol == "by_sequence"
    assert entry.inputs == {"audio_mel": "aaute"} and entry.provenance["job_id"] == "student-by_sequence-s0"
    assert Path(entry.source).is_absolute() and Path(entry.source).is_file()

    net = load_pretrained("student", weights="sim_quick")
    mel = net.example_inputs(2)
    with torch.no_grad():
        assert torch.equal(net(mel)["position"], task.net.eval()(mel)["position"])

    assert main(["weights", "list"]) == 0
    listing = capsys.readouterr().out
    assert "student.sim_quick" in listing and "E_ideal 4.25" in listing and entry.source in listing

    audionet = jobs["audionet-by_sequence-s0"]
    wrong_row, _ = _finished(suite, audionet)  # a student checkpoint under an AudioNet job
    with caplog.at_level(logging.WARNING):
        register_finished_job(suite, audionet, wrong_row)
    assert "holds a 'student' net, not 'audionet'" in caplog.text and list_weights("audionet") == []
