"""The paper's table beside ours: which paper column an environment task belongs to, and the
markdown table `snac eval` and `snac train` print (our protocol results next to the paper's row)."""

from __future__ import annotations


def paper_column(task: str) -> str:
    """The paper's column of an environment task: the three 1D shapes share `1d-static`."""
    return "1d-static" if task.startswith("1d-static") else task


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
