"""The plan of `snac table` as printed before anything starts (`format_plan`): one line per cell,
the budgets' sources, the cells whose runs are below their preset's budget, and the total
estimate. The cells themselves come from `agents.table.plan`.
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


def format_plan(cells: list[Cell], runs_dir: str | Path) -> str:
    """The plan as printed before anything starts: one line per cell, then the budgets' sources,
    the cells below them, and the total."""
    if not cells:
        return "nothing to run"
    preset = cells[0].preset
    width = max(18, *(len(c.directory.name) for c in cells))
    seeds = "/".join(map(str, sorted({c.config.seeds for c in cells})))
    lines = [
        f"snac table, preset {preset.name!r}: {preset.description}",
        f"{len(cells)} cells, {seeds} seeds each (vmapped), under {Path(runs_dir) / preset.name}/",
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
    below = [f"{c.algorithm}/{c.directory.name}" for c in cells if c.budget.below]
    if below:
        lines.append(
            f"  below the preset's budget, a run kept at its own: {', '.join(below)} (to train the preset's "
            "budget, move that directory away or choose another --runs-dir)"
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
        f"{counts['done']} done" + (f"; {unknown} cells of unknown time not counted)" if unknown else ")"),
    ]
    return "\n".join(lines)
