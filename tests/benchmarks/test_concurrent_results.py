"""Many processes appending to one ``results.csv`` at once lose and duplicate no row."""

from __future__ import annotations

import multiprocessing
from pathlib import Path

from benchmarks.results import append_rows, read_results

WRITERS = 4
ROWS_EACH = 15


def _append_many(path: str, writer: int, start) -> None:
    start.wait()  # every writer begins together, so their appends overlap
    for index in range(ROWS_EACH):
        append_rows(path, [{"kind": "constant", "suite": "concurrent", "job_id": f"w{writer}-{index}",
                            "status": "ok", "seed": index}])


def test_concurrent_appenders_lose_and_duplicate_nothing(tmp_path: Path):
    path = tmp_path / "results.csv"
    context = multiprocessing.get_context("spawn")
    start = context.Barrier(WRITERS)
    writers = [context.Process(target=_append_many, args=(str(path), writer, start)) for writer in range(WRITERS)]
    for process in writers:
        process.start()
    for process in writers:
        process.join(timeout=120)
    assert [process.exitcode for process in writers] == [0] * WRITERS
    rows = read_results(path)
    expected = {f"w{writer}-{index}" for writer in range(WRITERS) for index in range(ROWS_EACH)}
    assert len(rows) == WRITERS * ROWS_EACH
    assert set(rows["job_id"]) == expected
