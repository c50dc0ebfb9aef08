"""The leaderboard's table model and its three renderings: Markdown, booktabs LaTeX and HTML (with the page's CSS).

A :class:`Table` holds what a reader sees, independent of the format: title, caption, alert, label and
numeric columns (:class:`Column`, with an optional group header above), rows of :class:`Cell` (mean, std
over seeds, rank mark) and notes. :mod:`benchmarks.leaderboard` builds the tables from ``results.csv``;
this module only renders them, so a format's details never reach the statistics.
"""

from __future__ import annotations

import html
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

MISSING = "–"  #: a cell without a value (Markdown and HTML)


@dataclass(frozen=True)
class Column:
    """A numeric column: ``key`` in the method statistics, its header and the group header above it."""

    key: str
    label: str
    group: str = ""
    digits: int | None = 2  #: decimals; None: about three significant digits
    aggregated: bool = True  #: a per-seed metric (mean and std) rather than a per-model profile value
    flat: str = ""  #: the header without a group header above it (default: label and group)

    @property
    def flat_label(self) -> str:
        """The header in formats without grouped headers (Markdown)."""
        return self.flat or f"{self.label} {self.group}".strip()


@dataclass
class Cell:
    """A number with its spread over seeds and its rank mark ('best', 'second' or '')."""

    mean: float
    std: float
    digits: int | None
    mark: str = ""

    def parts(self) -> tuple[str, str] | None:
        """(mean, std) as displayed (std '' when there is one seed), or None when there is no value."""
        if not np.isfinite(self.mean):
            return None
        decimals = _decimals(self.mean, self.digits)
        std = f"{self.std:.{decimals}f}" if np.isfinite(self.std) else ""
        return f"{self.mean:.{decimals}f}", std


@dataclass
class Row:
    """One method of a table: its label cells (method, category) and numeric cells by column key."""

    labels: list[str]
    cells: dict[str, Cell]
    reference: bool  #: the constant-position predictor (shown, never ranked)


@dataclass
class Table:
    """A rendered-format-independent table: title, caption, alert, rows and notes (failed jobs)."""

    anchor: str
    title: str
    caption: str
    label_headers: list[str]
    columns: list[Column]
    rows: list[Row]
    alert: str = ""
    notes: list[str] = field(default_factory=list)


def _decimals(value: float, digits: int | None) -> int:
    if digits is not None:
        return digits
    if not np.isfinite(value) or value == 0:
        return 2
    return int(min(4, max(0, 2 - math.floor(math.log10(abs(value))))))


# ----------------------------------------------------------------------------------------------- formats


def _groups(columns: Sequence[Column]) -> list[tuple[str, int]]:
    """Runs of consecutive columns that share a group header: (group, width)."""
    runs: list[tuple[str, int]] = []
    for column in columns:
        if runs and runs[-1][0] == column.group:
            runs[-1] = (column.group, runs[-1][1] + 1)
        else:
            runs.append((column.group, 1))
    return runs


def markdown_escape(text: str) -> str:
    return re.sub(r"([\\`*|<>\[\]])", r"\\\1", text)


def _format_cell(cell: Cell, missing: str, plus_minus: str, best: str, second: str) -> str:
    """A cell in one output format: ``missing`` without a value, ``best`` / ``second`` wrap ("{}") a ranked one."""
    parts = cell.parts()
    if parts is None:
        return missing
    text = f"{parts[0]}{plus_minus}{parts[1]}" if parts[1] else parts[0]
    return {"best": best, "second": second}.get(cell.mark, "{}").format(text)


def _md_cell(cell: Cell) -> str:
    return _format_cell(cell, MISSING, " ± ", "**{}**", "<u>{}</u>")


def markdown_table(table: Table) -> str:
    """A table as GitHub Markdown: heading, caption, the grid and its notes."""
    lines = [f"## {markdown_escape(table.title)}", ""]
    if table.alert:
        lines += [f"**{markdown_escape(table.alert)}**", ""]
    lines += [f"*{markdown_escape(table.caption)}*", ""]
    headers = [*table.label_headers, *(column.flat_label for column in table.columns)]
    lines.append("| " + " | ".join(headers) + " |")
    lines.append("|" + "|".join([":--"] * len(table.label_headers) + ["--:"] * len(table.columns)) + "|")
    for row in table.rows:
        cells = [markdown_escape(label) for label in row.labels] + [_md_cell(row.cells[c.key]) for c in table.columns]
        lines.append("| " + " | ".join(cells) + " |")
    if table.notes:
        lines += ["", "Failed jobs (no numbers):", ""] + [f"- {markdown_escape(note)}" for note in table.notes]
    return "\n".join(lines) + "\n"


LATEX_SPECIAL = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
                 "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}",
                 "<": r"\textless{}", ">": r"\textgreater{}", "±": r"$\pm$", "×": r"$\times$", "α": r"$\alpha$",
                 "–": "--", "—": "---", "≥": r"$\geq$", "≤": r"$\leq$"}
_LATEX_PATTERN = re.compile("|".join(re.escape(char) for char in LATEX_SPECIAL))


def latex_escape(text: str) -> str:
    """``text`` safe in LaTeX text mode (special characters escaped, a few Unicode signs as math)."""
    return _LATEX_PATTERN.sub(lambda match: LATEX_SPECIAL[match.group()], text)


def _latex_cell(cell: Cell) -> str:
    return _format_cell(cell, "--", " $\\pm$ ", "\\textbf{{{}}}", "\\underline{{{}}}")


def latex_table(table: Table) -> str:
    """A table as a booktabs ``table*`` (needs ``\\usepackage{booktabs}``)."""
    lines = ["\\begin{table*}[t]", "\\centering", "\\small",
             f"\\caption{{{latex_escape(table.title)}. {latex_escape(table.alert + ' ' if table.alert else '')}"
             f"{latex_escape(table.caption)}}}",
             f"\\label{{tab:leaderboard-{table.anchor}}}",
             f"\\begin{{tabular}}{{{'l' * len(table.label_headers)}{'r' * len(table.columns)}}}", "\\toprule"]
    groups = _groups(table.columns)
    if any(group for group, _ in groups):
        cells, rules, start = [""] * len(table.label_headers), [], len(table.label_headers) + 1
        for group, span in groups:
            cells.append(f"\\multicolumn{{{span}}}{{c}}{{{latex_escape(group)}}}" if group else " & ".join([""] * span))
            if group:
                rules.append(f"\\cmidrule(lr){{{start}-{start + span - 1}}}")
            start += span
        lines += [" & ".join(cells) + " \\\\", "".join(rules)]
        headers = [*table.label_headers, *(column.label for column in table.columns)]
    else:
        headers = [*table.label_headers, *(column.flat_label for column in table.columns)]
    lines += [" & ".join(latex_escape(header) for header in headers) + " \\\\", "\\midrule"]
    previous_reference = False
    for index, row in enumerate(table.rows):
        if row.reference and not previous_reference and index:
            lines.append("\\midrule")
        previous_reference = row.reference
        cells = [latex_escape(label) for label in row.labels] + [_latex_cell(row.cells[c.key]) for c in table.columns]
        lines.append(" & ".join(cells) + " \\\\")
    lines += ["\\bottomrule", "\\end{tabular}"]
    if table.notes:
        lines.append(f"\\par\\smallskip\\footnotesize Failed jobs (no numbers): "
                     f"{'; '.join(latex_escape(note) for note in table.notes)}.")
    lines.append("\\end{table*}")
    return "\n".join(lines) + "\n"


def _html_cell(cell: Cell) -> str:
    return _format_cell(cell, MISSING, "&nbsp;±&nbsp;", "<b>{}</b>", "<u>{}</u>")


def html_table(table: Table) -> str:
    """A table as an HTML ``<table>`` with grouped headers, preceded by its heading and caption."""
    esc = html.escape
    out = [f'<h2 id="table-{esc(table.anchor)}">{esc(table.title)}</h2>']
    if table.alert:
        out.append(f'<p class="alert">{esc(table.alert)}</p>')
    out += [f'<p class="caption">{esc(table.caption)}</p>', "<table>", "<thead>"]
    groups = _groups(table.columns)
    if any(group for group, _ in groups):
        top = [f'<th rowspan="2">{esc(header)}</th>' for header in table.label_headers]
        below, start = [], 0
        for group, span in groups:
            run = table.columns[start:start + span]
            start += span
            if group:
                top.append(f'<th colspan="{span}" class="group">{esc(group)}</th>')
                below += [f"<th>{esc(column.label)}</th>" for column in run]
            else:
                top += [f'<th rowspan="2">{esc(column.label)}</th>' for column in run]
        out += ["<tr>" + "".join(top) + "</tr>", "<tr>" + "".join(below) + "</tr>"]
    else:
        headers = [*table.label_headers, *(column.flat_label for column in table.columns)]
        out.append("<tr>" + "".join(f"<th>{esc(header)}</th>" for header in headers) + "</tr>")
    out += ["</thead>", "<tbody>"]
    for row in table.rows:
        cells = "".join(f'<td class="label">{esc(label)}</td>' for label in row.labels)
        cells += "".join(f"<td>{_html_cell(row.cells[column.key])}</td>" for column in table.columns)
        out.append(f'<tr class="{"reference" if row.reference else "method"}">{cells}</tr>')
    out += ["</tbody>", "</table>"]
    if table.notes:
        out.append('<p class="failed">Failed jobs (no numbers):</p><ul class="failed">'
                   + "".join(f"<li>{esc(note)}</li>" for note in table.notes) + "</ul>")
    return "\n".join(out)


CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 2em auto; max-width: 1400px;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.6em; } h2 { font-size: 1.2em; margin-top: 2.2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.88em; font-variant-numeric: tabular-nums; }
th, td { padding: 0.25em 0.6em; border-bottom: 1px solid #e4e4e4; white-space: nowrap; }
th { background: #f3f5f7; text-align: center; } th.group { border-bottom: 1px solid #999; }
td { text-align: right; } td.label { text-align: left; }
tbody tr:nth-child(even) { background: #fafbfc; }
tr.reference td { font-style: italic; color: #555; border-top: 2px solid #bbb; background: #f6f6f0; }
p.caption { font-size: 0.9em; color: #444; max-width: 100em; }
p.alert { color: #a00; font-weight: bold; border-left: 4px solid #a00; padding-left: 0.6em; }
ul.failed, p.failed { color: #8a4b00; font-size: 0.9em; }
figure { margin: 1.2em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.85em; color: #555; }
.warnings { color: #8a4b00; font-size: 0.9em; }
"""
