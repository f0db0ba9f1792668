"""The paper's table beside ours: its columns and which environment tasks each stands for, its
numbers (`data/paper_results.json`), and the markdown table `snac eval` and `snac train` print
(our protocol results next to the paper's row)."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

PAPER_TASKS: tuple[str, ...] = (
    "1d-static",
    "1d-dynamic",
    "2d-static-dense",
    "2d-static-sparse",
    "2d-dynamic-dense",
    "2d-dynamic-sparse",
    "3d-static-dense",
    "3d-static-sparse",
    "3d-dynamic-dense",
    "3d-dynamic-sparse",
)
"""The columns of the paper's table; `1d-static` stands for the three 1D shapes. The one list of
them: `data/paper_results.json` holds the numbers per column, each column one of these
(`load_paper_results` checks it)."""

PAPER_GROUPS = {"1d-static": ("1d-static-sin", "1d-static-gauss", "1d-static-step")}
"""Paper columns that stand for several environment tasks."""


def paper_column(task: str) -> str:
    """The paper's column of an environment task: the three 1D shapes share `1d-static`."""
    return next((column for column, tasks in PAPER_GROUPS.items() if task in tasks), task)


def paper_cell(row: dict[str, dict[str, float | None]], task: str) -> dict[str, float | None]:
    """The paper's `{"avg", "min"}` to print beside a result on `task` (`row` from `paper_row`):
    its column's, so a single 1D shape stands beside the 1d-static column, the paper's mean over
    the three shapes; {} where the row has no such column."""
    return row.get(paper_column(task), {})


def load_paper_results(path: str | Path | None = None) -> dict[str, Any]:
    """The paper's tables: `path`, or the copy shipped in the package."""
    if path is None:
        text = resources.files("snac_jax").joinpath("data/paper_results.json").read_text()
    else:
        text = Path(path).read_text()
    try:
        results = json.loads(text)
    except json.JSONDecodeError as error:
        raise ValueError(f"{path or 'paper_results.json'}: not valid JSON ({error})") from error
    if not isinstance(results, dict) or not isinstance(results.get("methods"), dict):
        raise ValueError(f"{path or 'paper_results.json'}: expected an object with a 'methods' table")
    for method, row in results["methods"].items():
        unknown = sorted(set(row) - set(PAPER_TASKS)) if isinstance(row, dict) else None
        if unknown is None or unknown:
            raise ValueError(
                f"{path or 'paper_results.json'}: methods.{method} must map the paper's columns "
                f"({', '.join(PAPER_TASKS)}) to {{avg, min}}" + (f"; unknown column(s) {unknown}" if unknown else "")
            )
    return results


def paper_row(results: dict[str, Any], method: str | None) -> dict[str, dict[str, float | None]]:
    """The paper's {task: {"avg", "min"}} for `method`, or {} when the paper has no such row."""
    if method is None:
        return {}
    return results["methods"].get(method, {})


def _fmt(value, digits: int = 3) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def markdown_table(results, paper: dict) -> str:
    """One row per `TaskResult`, with `paper[task]` (`{"avg", "min"}`) beside it."""
    lines = [
        "| task | episodes | mean IoU | 95% CI | min IoU | std | paper mean | paper min | Δ mean | mean length | mean bricks |",
        "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        row = paper.get(r.task, {})
        paper_mean, paper_min = row.get("avg"), row.get("min")
        delta = None if paper_mean is None else r.mean - paper_mean
        lines.append(
            f"| {r.task} | {r.episodes} | {r.mean:.3f} | [{r.ci95[0]:.3f}, {r.ci95[1]:.3f}] | {r.min:.3f} | "
            f"{r.std:.3f} | {_fmt(paper_mean)} | {_fmt(paper_min)} | "
            f"{'—' if delta is None else f'{delta:+.3f}'} | {r.mean_length:.1f} | {r.mean_bricks_used:.1f} |"
        )
    return "\n".join(lines)
