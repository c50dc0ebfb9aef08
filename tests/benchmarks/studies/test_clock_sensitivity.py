"""The clock sensitivity study: its settings, the clocks it gives a recording, its table, the identifiability check."""

from __future__ import annotations

import numpy as np
import pandas as pd

from benchmarks.studies.clock_sensitivity import identifiability, markdown, settings, with_clocks
from datamodules.formats import discover_recordings
from datamodules.formats.mcap_file import read_mcap


def test_settings_and_table():
    names = [name for name, _ in settings()]
    assert names[0] == "shared clock" and "offset 3 ms" in names and names[-1] == "drift 50 ppm"
    table = pd.DataFrame({"quiet": [1.0, 2.5]}, index=["shared clock", "offset 1 ms"])
    assert markdown(table).splitlines()[3] == "| offset 1 ms | 2.50 m |"


def test_with_clocks_moves_each_node_by_its_offset(simulated_dir, tmp_path):
    source = discover_recordings(simulated_dir)[0]
    with_clocks(source, tmp_path / "late.mcap", dict(settings())["offset 1 ms"])
    before, after = read_mcap(source).audio, read_mcap(tmp_path / "late.mcap").audio
    shared, late = before.read(0, before.num_samples), after.read(0, after.num_samples)
    assert np.array_equal(late[0], shared[0])
    for node in (1, 2, 3):  # node n samples n ms late: it holds what the shared clock has 48 n samples later
        lag = 48 * node
        assert np.abs(late[node, :-lag] - shared[node, lag:]).max() < 1e-3
    assert read_mcap(tmp_path / "late.mcap").meta["clocks_truth"]["offsets_s"][3] == 3e-3


def test_direct_paths_alone_explain_offsets_by_other_positions():
    line = identifiability(offsets_ms=(1.0,), trials=10)
    share = int(line.split(": ")[1].split("%")[0])
    assert share >= 50  # four single-microphone nodes cannot tell an offset ramp from a move
