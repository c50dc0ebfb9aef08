"""The caption of a comparison table: what a reader needs to judge it.

Protocol, data, training budget, the compute convention, seeds, smoothers, the physical limit, the learning
curves of the table's models (another suite's results) and the machine, each as a sentence built from the
table's rows of ``results.csv``; and the plain-text forms of results cells these sentences (and the
leaderboard's tables) use.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pandas as pd

from benchmarks.limit import bound_sentence

PROTOCOL_NOTES = {
    "by_sequence": "whole flights are held out (no test flight is seen in training)",
    "time_blocks": "contiguous time blocks of each flight are held out, with a purge gap of at least one window",
    "random_windows": ("LEAKY, the papers' protocol: random windows are held out, so test windows overlap "
                       "training windows and the errors are optimistic; not comparable with the other protocols"),
}
TRUE = {"true", "1", "yes", "y"}  #: how results.csv spells a true flag


def plain_text(value: object) -> str:
    """A cell of results.csv as text: NaN and empty as '', whole floats without decimals."""
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return ""
    if isinstance(value, (float, np.floating)):
        return f"{value:g}"
    return str(value).strip()


def distinct_values(rows: pd.DataFrame, column: str) -> list[str]:
    """The distinct non-empty values of ``column`` in order of appearance."""
    return list(dict.fromkeys(text for text in map(plain_text, rows[column]) if text))


def value_span(rows: pd.DataFrame, column: str) -> str:
    """'5' or '3–5' for a numeric column, '' when it is empty."""
    values = rows[column].dropna()
    if values.empty:
        return ""
    low, high = values.min(), values.max()
    return f"{low:g}" if low == high else f"{low:g}–{high:g}"


def _seeds_sentence(stats: pd.DataFrame, rows: pd.DataFrame) -> str:
    seeds = [plain_text(seed) for seed in sorted(rows["seed"].dropna().unique())]
    listed = f"Seed{'s' if len(seeds) > 1 else ''} {', '.join(seeds) or 'not recorded'}"
    counts = Counter(stats["n_seeds"])
    if set(counts) == {1}:
        return f"{listed}: one run per method, so no standard deviation."
    usual = counts.most_common(1)[0][0]
    others = "; ".join(f"{stat.display} {stat.n_seeds}" for stat in stats.itertuples() if stat.n_seeds != usual)
    spread = f"{usual} seed{'s' if usual > 1 else ''} per method" + (f", except {others}" if others else "")
    return f"{listed}: mean ± sample standard deviation over seeds ({spread})."


def _joined(rows: pd.DataFrame, column: str, empty: str = "not recorded") -> str:
    return "; ".join(distinct_values(rows, column)) or empty


def _split_counts(rows: pd.DataFrame, what: str) -> str:
    """'6/2/2' (train/val/test) per distinct combination in ``rows``."""
    columns = [f"n_{split}_{what}" for split in ("train", "val", "test")]
    combos = ("/".join(plain_text(value) or "?" for value in counts)
              for counts in rows[columns].itertuples(index=False))
    return "; ".join(dict.fromkeys(combos))


SMOOTHER_NAMES = {"robust": "the robust Student-t state-space smoother (preset robust)",
                  "paper": "the paper's GP smoother (preset paper)", "tuned": "the tuned Matérn GP (preset tuned)"}


def _smoother_sentence(rows: pd.DataFrame) -> str:
    """Which smoother made the smoothed E of which methods ('' where no row says)."""
    smoothed = rows[(rows["smoother"] != "") & (rows["kind"] == "model")]
    groups = smoothed.groupby("smoother", sort=True)["method"].agg(lambda methods: ", ".join(dict.fromkeys(methods)))
    if groups.empty:
        return ""
    if len(groups) == 1:
        return f"Smoothed E: {SMOOTHER_NAMES.get(groups.index[0], f'preset {groups.index[0]}')}."
    return "Smoothed E: " + "; ".join(f"{SMOOTHER_NAMES.get(name, f'preset {name}')} for {methods}"
                                      for name, methods in groups.items()) + "."


def table_caption(rows: pd.DataFrame, stats: pd.DataFrame, protocol: str, learning: str = "") -> str:
    """What a reader needs to judge the table: protocol, data, budget, compute convention, seeds, machine.

    ``learning``: the sentence on the table's models' learning curves (another suite's results), if given.
    """
    parts = [f"Protocol {protocol}: {PROTOCOL_NOTES.get(protocol, 'not a known protocol')}."]
    if suites := distinct_values(rows, "suite"):
        parts.append(f"Suite {', '.join(suites)}.")
    data = _joined(rows, "data", "")
    parts.append(f"Data: {'/'.join(distinct_values(rows, 'data_kind')) or 'unknown'}{f' ({data})' if data else ''}, "
                 f"fingerprint {', '.join(distinct_values(rows, 'data_fingerprint')) or 'not recorded'}; flights "
                 f"train/val/test {_split_counts(rows, 'sequences')}, windows {_split_counts(rows, 'windows')}; "
                 f"drones {_joined(rows, 'drones')}; light conditions {_joined(rows, 'lights')}.")
    budget = [f"{label} {value}" for label, column in (
        ("max epochs", "max_epochs"), ("train batches per epoch at most", "limit_train_batches"),
        ("batch size", "batch_size"), ("epochs run", "epochs_run"), ("best epoch", "best_epoch"))
        if (value := value_span(rows, column))]
    notes = distinct_values(rows, "budget_note")
    parts.append(f"Training budget: {', '.join(budget) or 'not recorded'}{'; ' + '; '.join(notes) if notes else ''}.")
    parts.append("GMACs (multiply-accumulates at batch 1; FLOPs = 2 × MACs), params and latency (median at "
                 "batch 1, 1 thread) are profiled at each model's reference input shapes, whatever the training "
                 "budget.")
    parts.append(_seeds_sentence(stats, rows))
    if smoothers := _smoother_sentence(rows):
        parts.append(smoothers)
    if limit := bound_sentence(rows):
        parts.append(limit)
    if learning:
        parts.append(learning)
    commit = ", ".join(value[:12] for value in distinct_values(rows, "git_commit")) or "not recorded"
    dirty = " (dirty working tree)" if rows["git_dirty"].str.lower().isin(TRUE).any() else ""
    parts.append(f"Machine: cpu {_joined(rows, 'cpu')}; gpu {_joined(rows, 'gpu', 'none')}; "
                 f"threads {_joined(rows, 'threads')}. Commit {commit}{dirty}. "
                 f"Software: {_joined(rows, 'versions')}.")
    parts.append("Errors in metres: Dx, Dy, Dz mean absolute error per axis, E mean Euclidean error; "
                 "mean E = (E ideal + E dark) / 2. Best per column in bold, second underlined, lower is better; "
                 "the constant row does not compete.")
    return " ".join(parts)


def learning_sentence(learning: pd.DataFrame | None, stats: pd.DataFrame, protocol: str, source: str) -> str:
    """The caption's sentence on the learning curves (read from ``source``) of the table's trained models."""
    if learning is None:
        return ""
    from benchmarks.learning import learning_evidence  # matplotlib only where learning curves are given

    trained = stats[stats["kind"] == "model"]
    methods = dict(zip(trained["model"], trained["display"], strict=True))
    return learning_evidence(learning, protocol, methods, source=source)
