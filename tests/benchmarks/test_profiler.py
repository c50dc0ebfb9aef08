"""The counts (benchmarks.flops): MACs per call on the executed graph, used parameters; the profile row, the CLI.

Expected MACs and parameter counts are worked out by hand from the layer shapes (baselines.md
sections 5, 6, 10 and the nets' code), never taken from the counter's own output.
"""

from __future__ import annotations

import argparse

import pandas as pd
import pytest
import torch
from torch import nn
from torch.nn import functional as F

from benchmarks import flops, profiler
from benchmarks.results import PROFILE
from zoo.registry import get_model, list_models


def linear_params(inputs: int, outputs: int) -> int:
    return (inputs + 1) * outputs


def four_branch(channels: int = 4, kernels: int = 16, n: int = 64) -> tuple[int, int]:
    """(MACs, parameters) of the four full-axis branches on a C x n x n map: kernels 3 x n, 5 x n, n x 3, n x 5.

    A branch with a k x n kernel gives ``kernels`` x (n - k + 1) outputs, each of C x k x n multiply-adds.
    """
    macs = 2 * sum(kernels * (n - k + 1) * channels * k * n for k in (3, 5))
    params = 2 * sum(kernels * channels * k * n + kernels for k in (3, 5))
    return macs, params


# ------------------------------------------------------------------------------------------ hand-built modules


class Tiny(nn.Module):
    """Conv2d -> grouped ConvTranspose2d -> Linear -> one Linear applied twice."""

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(2, 4, 3)  # 2 x 8 x 8 -> 4 x 6 x 6
        self.up = nn.ConvTranspose2d(4, 6, 2, stride=2, groups=2)  # 4 x 6 x 6 -> 6 x 12 x 12
        self.fc = nn.Linear(6 * 12 * 12, 5)
        self.shared = nn.Linear(5, 5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.fc(self.up(self.conv(x)).flatten(1))
        return self.shared(torch.relu(self.shared(x)))


def test_macs_of_a_hand_built_model():
    conv = (4 * 6 * 6) * 2 * (3 * 3)  # output elements x in_channels x kernel elements
    transposed = (6 * 12 * 12) * (4 // 2) * (2 * 2)  # by output size, in_channels / groups
    fc = 6 * 12 * 12 * 5
    shared = 2 * (5 * 5)  # called twice: counted per call
    assert flops.count_macs(Tiny(), torch.rand(1, 2, 8, 8)) == conv + transposed + fc + shared


def test_transposed_convolution_is_counted_by_output_size():
    up = nn.ConvTranspose2d(3, 5, 3, stride=2, padding=1, output_padding=1)  # 7 x 7 -> 14 x 14
    by_output = (5 * 14 * 14) * 3 * 9
    by_input = (3 * 7 * 7) * 5 * 9  # FlopCounterMode's own convention: 4 times fewer at stride 2
    macs = flops.count_macs(up, torch.rand(1, 3, 7, 7))
    assert macs == by_output and macs == 4 * by_input


class Aliased(nn.Module):
    """One Linear reachable as ``layer`` and ``alias`` (as ResNet-50 kept under two names), called 1 or 2 times."""

    def __init__(self, calls: int):
        super().__init__()
        self.calls = calls
        self.layer = nn.Linear(6, 6)
        self.alias = self.layer

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.alias(self.layer(x)) if self.calls == 2 else self.layer(x)


def test_a_module_under_two_names_is_counted_per_call_not_per_name():
    x = torch.rand(3, 6)
    assert flops.count_macs(Aliased(calls=1), x) == 3 * 6 * 6  # a module walk would count it twice
    assert flops.count_macs(Aliased(calls=2), x) == 2 * (3 * 6 * 6)
    assert flops.count_parameters(Aliased(calls=2), x) == (linear_params(6, 6), linear_params(6, 6))


def test_lstm_gates_are_counted():
    lstm = nn.LSTM(5, 7, num_layers=2, batch_first=True)
    steps, batch, hidden = 3, 2, 7
    gates = 4 * hidden
    expected = steps * batch * gates * (5 + hidden) + steps * batch * gates * (hidden + hidden)
    assert flops.count_macs(lstm, torch.rand(batch, steps, 5)) == expected
    bidirectional = nn.LSTM(5, 7, batch_first=True, bidirectional=True)
    assert flops.count_macs(bidirectional, torch.rand(batch, steps, 5)) == 2 * steps * batch * gates * (5 + hidden)


class Attention(nn.Module):
    def __init__(self, dim: int = 8, heads: int = 2):
        super().__init__()
        self.attention = nn.MultiheadAttention(dim, heads, batch_first=True)

    def forward(self, query: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        return self.attention(query, memory, memory, need_weights=False)[0]


@pytest.mark.parametrize("keys", [3, 5], ids=["self-attention (fused fast path)", "cross-attention"])
def test_attention_is_counted_alike_on_the_fused_and_the_unfused_path(keys):
    dim, queries = 8, 3
    query = torch.rand(1, queries, dim)
    memory = query if keys == queries else torch.rand(1, keys, dim)
    projections = (queries + keys + keys + queries) * dim * dim  # Q, K, V, output
    products = 2 * queries * keys * dim  # Q K^T and A V over all heads
    module = Attention(dim)
    assert flops.count_macs(module, (query, memory)) == projections + products
    assert flops.uncounted_ops(module, (query, memory)) == {}
    total, used = flops.count_parameters(module, (query, memory))
    assert used == total  # the output projection is applied functionally, never called as a module


class DeadAndFunctional(nn.Module):
    """A dead layer, a layer used twice, and a weight applied through F.linear without calling its module."""

    def __init__(self):
        super().__init__()
        self.used = nn.Linear(4, 4)
        self.dead = nn.Linear(4, 16)
        self.functional = nn.Linear(4, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(self.used(self.used(x)), self.functional.weight)


def test_used_parameters_leave_out_dead_layers_only():
    total, used = flops.count_parameters(DeadAndFunctional(), torch.rand(1, 4))
    assert total == linear_params(4, 4) + linear_params(4, 16) + linear_params(4, 2)
    assert used == linear_params(4, 4) + 4 * 2  # shared layer once; the functional weight without its bias


# ------------------------------------------------------------------------------------------ zoo models


def student_expected() -> tuple[int, int]:
    """(MACs, parameters) of the AAUTE student: four branches (k 16) -> 512 -> 256 -> 128 -> 3."""
    macs, params = four_branch()
    widths = (3904, 512, 256, 128, 3)
    for a, b in zip(widths[:-1], widths[1:], strict=True):
        macs += a * b
        params += linear_params(a, b)
    return macs, params


def audionet_expected() -> tuple[int, int]:
    """AudioNet: four branches (k 16) -> 256, DetectNet(256): 256 -> 256 -> 128 -> {3, 6, 30}."""
    macs, params = four_branch()
    macs += 3904 * 256
    params += linear_params(3904, 256)
    for out in (3, 6, 30):
        macs += 256 * 256 + 256 * 128 + 128 * out
        params += linear_params(256, 256) + linear_params(256, 128) + linear_params(128, out)
    return macs, params


def voranet_expected() -> tuple[int, int]:
    """VorasNet: three conv 3 x 3 s2 blocks (224 -> 112 -> pool 56 -> 28 -> 14 -> 7 -> 3), LSTM(128) on 3 steps."""
    convs = 64 * 112 * 112 * 4 * 9 + 64 * 28 * 28 * 64 * 9 + 64 * 7 * 7 * 64 * 9
    lstm = 3 * (4 * 128) * (128 + 128)
    heads = 128 * 32 + 32 * 3 + 32 * 6
    params = (64 * 4 * 9 + 64) + 2 * (64 * 64 * 9 + 64) + 3 * (2 * 64)  # convs and BatchNorms
    params += 4 * 128 * (128 + 128) + 2 * 4 * 128  # LSTM weights and its two bias vectors
    params += linear_params(128, 32) + linear_params(32, 3) + linear_params(32, 6)
    return convs + lstm + heads, params


@pytest.mark.parametrize("name, expected", [("student", student_expected), ("audionet", audionet_expected),
                                            ("voranet", voranet_expected)])
def test_zoo_macs_and_parameters_by_hand(name, expected):
    macs, params = expected()
    net = get_model(name)
    inputs = net.example_inputs(1)
    assert flops.count_macs(net, inputs) == macs
    assert flops.count_parameters(net, inputs) == (params, params)


#: baselines.md section 11 (params total / used, M) where the zoo builds the same modules
SECTION_11 = {"student": (2.230, 2.230), "audionet": (None, 1.366), "voranet": (0.213, 0.213),
              "visualnet": (31.18, 29.13), "avped": (None, 30.22)}


@pytest.mark.parametrize("name", sorted(SECTION_11))
def test_parameter_counts_reproduce_section_11(name):
    net = get_model(name)
    total, used = flops.count_parameters(net, net.example_inputs(1))
    reference_total, reference_used = SECTION_11[name]
    digits = 3 if reference_used < 10 else 2
    if reference_total is not None:  # audionet and avped leave out the published dead branches
        assert round(total / 1e6, digits) == reference_total
    assert round(used / 1e6, digits) == reference_used
    if name == "visualnet":  # the unused 1000-way ResNet classifier is the only unused part
        assert total - used == linear_params(2048, 1000)


#: nets built only from blocks that avfdti also runs (ResNet-50 trunk, four-branch encoder, gate, DetectNet)
SAME_BLOCKS_AS_AVFDTI = ("visualnet", "avped")


@pytest.mark.parametrize("name", [pytest.param(name, marks=pytest.mark.slow) if name in SAME_BLOCKS_AS_AVFDTI
                                  else name for name in list_models()])
def test_zoo_nets_run_no_op_the_counter_does_not_know(name):
    net = get_model(name)
    assert flops.uncounted_ops(net, net.example_inputs(1)) == {}


# ------------------------------------------------------------------------------------------ profile row


def test_profile_without_timing_has_exactly_the_schema_columns():
    row = profiler.profile_model("student", timing=False)
    macs, params = student_expected()
    assert list(row) == PROFILE
    assert row["gmacs"] == pytest.approx(macs / 1e9) and row["gflops"] == pytest.approx(2 * macs / 1e9)
    assert row["params_total_M"] == pytest.approx(params / 1e6) == row["params_used_M"]
    assert row["profile_inputs"] == "audio_mel 4x64x64"
    assert all(row[key] is None for key in profiler.TIMING_KEYS)


def test_timed_profile_returns_positive_numbers_and_restores_threads():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        row = profiler.profile_model("student", min_run_time=0.05, throughput_batch=2, all_threads=2)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(previous)
    assert row["threads_all"] == 2 and row["throughput_batch"] == 2
    for key in ("latency_ms_1t", "latency_ms_all", "throughput_1t", "throughput_all", "frontend_ms",
                "end_to_end_ms"):
        assert row[key] > 0, key
    assert all(row[key] is None or row[key] >= 0 for key in ("latency_iqr_ms_1t", "latency_iqr_ms_all"))


def test_raw_inputs_are_a_window_and_a_camera_frame():
    raw = profiler.raw_inputs(get_model("avped"))
    assert raw["audio_mel"].shape == (4, 96000)  # 2 s at 48 kHz
    assert raw["image"].shape == (720, 1280, 3) and raw["image"].dtype.name == "uint8"
    features = profiler.frontend(get_model("avped"), raw)
    assert {name: tuple(value.shape) for name, value in features.items()} == {
        "audio_mel": (4, 64, 64), "image": (3, 256, 256)}


def test_table_labels_macs_and_flops_and_marks_missing_timings():
    row = {"model": "student", **profiler.profile_model("student", timing=False)}
    table = profiler.format_profile_table([row])
    header = "\n".join(table.splitlines()[:2])
    assert "GMACs" in header and "FLOPs (G," in header and "= 2 x MACs" in header
    line = next(line for line in table.splitlines() if line.startswith("student"))
    assert f"{row['gmacs']:.4f}" in line and line.split()[-1] == "-"


# ------------------------------------------------------------------------------------------ CLI


def test_cli_prints_the_table_and_writes_the_csv(tmp_path, capsys):
    out = tmp_path / "profile.csv"
    assert profiler.main(["student", "--min-run-time", "0.02", "--batch", "2", "--threads", "2",
                          "--csv", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "student" in printed and "GMACs" in printed and "latency 2 threads" in printed
    frame = pd.read_csv(out)
    assert list(frame.columns) == ["model", *PROFILE] and list(frame["model"]) == ["student"]
    assert frame["gmacs"][0] == pytest.approx(student_expected()[0] / 1e9)
    assert frame["throughput_1t"][0] > 0


def test_cli_unknown_model_is_a_one_line_error(capsys):
    assert profiler.main(["student", "nonet", "--no-timing"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""  # checked before any model is profiled
    assert captured.err.count("\n") == 1 and "nonet" in captured.err and "student, visualnet" in captured.err
    parser = argparse.ArgumentParser()
    profiler.add_arguments(parser)
    with pytest.raises(ValueError, match="unknown model 'nonet'"):
        profiler.run(parser.parse_args(["nonet"]))
