"""The plan of `snac table` as printed before anything starts (`format_plan`): one line per cell,
the budgets' sources and the total estimate. The cells themselves come from `agents.table.plan`.
"""

from __future__ import annotations

from pathlib import Path

from agents.table.plan import Cell


def duration(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    return f"{hours} h {rest // 60:02d} min" if hours else f"{rest // 60} min {rest % 60:02d} s"


def _seed_counts(cells: list[Cell]) -> str:
    counts = sorted({c.config.seeds for c in cells})
    if len(counts) == 1:
        return f"{counts[0]} seeds each"
    cheap = cells[0].preset.cheap_minutes
    return (
        f"{counts[0]} seeds each, {counts[-1]} on cheap columns (each cell estimated under {cheap:g} min at that "
        f"count when the column was first planned; {sum(c.config.seeds == counts[-1] for c in cells)} cells)"
    )


def format_plan(cells: list[Cell], runs_dir: str | Path) -> str:
    """The plan as printed before anything starts: one line per cell, then the budgets' sources
    and the total."""
    if not cells:
        return "nothing to run"
    preset = cells[0].preset
    width = max(18, *(len(c.directory.name) for c in cells))
    own = sorted(
        {
            f"{c.algorithm} {preset.wall_limit(c.algorithm) / 60:g}"
            for c in cells
            if preset.wall_limit(c.algorithm) is not None and preset.wall_limit(c.algorithm) != preset.wall_limit_s
        }
    )
    limit = (
        ""
        if preset.wall_limit_s is None
        else (
            f"; budgets capped to fit ~{preset.wall_limit_s / 60:g} min per cell"
            + (f" ({', '.join(own)})" if own else "")
        )
    )
    lines = [
        f"snac table, preset {preset.name!r}: {preset.description}{limit}",
        f"{len(cells)} cells, {_seed_counts(cells)} (vmapped), under {Path(runs_dir) / preset.name}/",
        "",
        f"{'algorithm':<10} {'task':<{width}} {'env steps/seed':>24} {'seeds':>5} {'status':<9} {'estimate':>13}  estimate from",
    ]
    for c in cells:
        status = (
            f"{c.done_steps / max(c.total_steps, 1):.0%} done"
            if c.status == "partial"
            else "adopt"
            if c.adopts_from is not None
            else c.status
        )
        lines.append(
            f"{c.algorithm:<10} {c.directory.name:<{width}} {c.budget.describe():>24} {c.config.seeds:>5} {status:<9} "
            f"{duration(c.estimate_s):>13}  {c.estimate_from}"
        )
    lines += ["", "budgets:"]
    for source in dict.fromkeys(f"{c.algorithm}: {c.budget.source}" for c in cells):
        lines.append(f"  {source}")
    for algorithm in dict.fromkeys(c.algorithm for c in cells if c.budget.capped):
        lines.append(
            f"  {algorithm} capped: the largest budget (two significant figures) whose estimate fits "
            f"{preset.wall_limit(algorithm) / 60:g} min with every seed's evaluation"
        )
    known = [c.estimate_s for c in cells if c.estimate_s is not None]
    unknown = len(cells) - len(known)
    adopted = sum(c.status == "new" and c.adopts_from is not None for c in cells)
    counts = {s: sum(c.status == s for c in cells) for s in ("new", "partial", "done")}
    lines += [
        "",
        f"total estimate: {duration(sum(known))} ({counts['new'] - adopted} new, "
        + (f"{adopted} adopted, " if adopted else "")
        + f"{counts['partial']} partial, "
        f"{counts['done']} done" + (f"; {unknown} cells without a measured rate not counted)" if unknown else ")"),
    ]
    return "\n".join(lines)
