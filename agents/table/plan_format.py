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
    adopted = sum(c.status == "new" and c.adopts_from is not None for c in cells)
    counts = {s: sum(c.status == s for c in cells) for s in ("new", "partial", "done")}
    lines += [
        "",
        f"total estimate: {_total_estimate(cells)} ({counts['new'] - adopted} new, "
        + (f"{adopted} adopted, " if adopted else "")
        + f"{counts['partial']} partial, {counts['done']} done"
        + _unknown_note(cells)
        + ")",
    ]
    return "\n".join(lines)


def _total_estimate(cells: list[Cell]) -> str:
    """The plan's remaining time: the sum of its cells' estimates where every cell has one; a lower
    bound where some have none (no run of theirs has started: nothing measured them) and the others
    add up to some time; 'unknown' where they add up to none, as a plan of cells not started does
    (a sum of no estimates read as '0 min 00 s', as if nothing were left to train)."""
    known = sum(c.estimate_s for c in cells if c.estimate_s is not None)
    if all(c.estimate_s is not None for c in cells):
        return duration(known)
    return f"at least {duration(known)}" if known > 0 else "unknown"


def _unknown_note(cells: list[Cell]) -> str:
    unknown = sum(c.estimate_s is None for c in cells)
    if not unknown:
        return ""
    counted = any(c.estimate_s for c in cells)
    return f"; {unknown} {'cell' if unknown == 1 else 'cells'} of unknown time" + (" not counted" if counted else "")
