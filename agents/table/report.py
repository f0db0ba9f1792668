"""`snac table --report`: the benchmark table from the record alone (`agents.table.files`: one
raw copy per finished cell, so that every page can be rebuilt from the repository): table.md and
table.json, one section per preset found there, and `table-<preset>.png`. An ablation preset's
section is `agents.table.ablation`'s.

A column's per-seed value is that seed's protocol mean on the task; for `1d-static`, the mean
over the three shapes of the same seed index. A cell shows the mean over seeds with its 95%
bootstrap interval across seeds; a learner's IQM pools its runs of every finished column (the seed
indices every column has), with a stratified bootstrap interval (`agents.table.statistics`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agents.table import ablation, statistics
from agents.table.files import (
    PAGE_TEXT,
    budget_record,
    budget_text,
    copies,
    interval,
    load_raw,
    number,
    refuse_links,
    seed_means,
)
from agents.table.plan import TRAIN_SEED
from agents.table.presets import load_presets
from agents.training import schemas
from agents.training.plotting import pyplot, save_png
from snac_jax.atomic import atomic_write_json, atomic_write_text
from snac_jax.evaluation import REPORT_EVAL_SEED, TUNING_EVAL_SEED
from snac_jax.paper import PAPER_GROUPS, PAPER_TASKS, load_paper_results, paper_row


def _paper_method(algorithm: str) -> str | None:
    from agents.training.registry import ALGORITHMS, config_class

    return config_class(algorithm).paper_method if algorithm in ALGORITHMS else None


def _paper_values(paper: dict, method: str | None) -> dict[str, float | None]:
    """The paper's average IoU of `method` on every column (None where it reports none)."""
    row = paper_row(paper, method)
    return {column: row.get(column, {}).get("avg") for column in PAPER_TASKS}


def build(
    raw: dict,
    *,
    paper: dict | None = None,
    handcrafted: dict | None = None,
    preset: str = "",
    reps: int = statistics.DEFAULT_REPS,
) -> dict[str, Any]:
    """table.json's content from the copied cells (`load_raw`)."""
    paper = load_paper_results() if paper is None else paper
    learners, iqms, paper_rows, paper_methods = {}, {}, {}, {}
    for algorithm, tasks in raw.items():
        method = _paper_method(algorithm)
        theirs = _paper_values(paper, method)
        ours, per_column = {}, []
        for column in PAPER_TASKS:
            cells = [tasks.get(task) for task in PAPER_GROUPS.get(column, (column,))]
            if None in cells:
                continue
            per_task = [seed_means(c) for c in cells]
            if len({len(v) for v in per_task}) != 1:
                raise ValueError(
                    f"{algorithm} {column}: its tasks have different seed counts {[len(v) for v in per_task]}"
                )
            values = np.mean(per_task, axis=0)
            summary = statistics.cell_summary(values, reps=reps)
            ours[column] = {**summary, "budget": budget_record(cells), "paper": theirs[column]}
            per_column.append(values)
        if ours:
            # (seeds, columns) over the seed indices every column has: a column with five seeds
            # (a cheap one) beside columns with three adds its extra seeds to its cell, not to the IQM
            common = min(len(v) for v in per_column)
            scores = np.stack([v[:common] for v in per_column], axis=1)
            # the paper's IQM over the columns ours has, so that the two compare
            reported = [theirs[c] for c in ours if theirs[c] is not None]
            iqms[algorithm] = {
                **statistics.iqm_summary(scores, reps=reps),
                "columns": list(ours),
                "paper_iqm": statistics.iqm(reported) if reported else None,
                "paper_columns": len(reported),
            }
        learners[algorithm], paper_rows[algorithm], paper_methods[algorithm] = ours, theirs, method
    hand_paper, handcrafted = _paper_values(paper, "handcrafted"), handcrafted or {}
    hand = {
        column: {
            "mean": handcrafted[column]["mean"],
            "ci95": None,
            "seeds": [handcrafted[column]["mean"]],
            "budget": None,
            "eval_seed": handcrafted[column].get("seed"),
            "paper": hand_paper[column],
        }
        for column in PAPER_TASKS
        if column in handcrafted
    }
    return {
        "preset": preset,
        "columns": list(PAPER_TASKS),
        "train_seed": TRAIN_SEED,
        "eval_seed": REPORT_EVAL_SEED,
        "bootstrap": statistics.bootstrap_record(reps),
        "human": {column: {"paper": value} for column, value in _paper_values(paper, "human").items()},
        "handcrafted": hand,
        "handcrafted_eval_seeds": sorted({h["eval_seed"] for h in hand.values()}, key=str),
        "learners": learners,
        "iqm": iqms,
        "paper_rows": paper_rows,  # each learner's paper row on every column (None: not reported)
        "paper_methods": paper_methods,  # whose row of the paper that is (a new learner: its base's)
    }


def _header(table: dict) -> list[str]:
    """What every preset's section shares: how the numbers were made, which keys scored them."""
    hand_keys = ", ".join(map(str, table.get("handcrafted_eval_seeds", []))) or "—"
    fields = {"hand_keys": hand_keys, "tuning_eval_seed": TUNING_EVAL_SEED}
    return PAGE_TEXT["header"].format(**table, **fields).split("\n")


def _columns(count: int) -> str:
    return f"{count} column" if count == 1 else f"{count} columns"


def _reference_row(name: str, values: list) -> str:
    """A row without seeds: its numbers, and their IQM over the columns that have one."""
    reported = [v for v in values if v is not None]
    iqm = f"{statistics.iqm(reported):.3f} ({_columns(len(reported))})" if reported else "—"
    return f"| {name} | " + " | ".join(number(v) for v in values) + f" | {iqm} |"


def paper_base(table: dict, learner: str) -> str | None:
    """For a learner the paper does not have (a privileged or auxiliary variant), the paper
    learner whose row stands beside it; None where that row is the learner's own."""
    method = table.get("paper_methods", {}).get(learner)
    return None if method is None or method.replace("_", "-") == learner else method.replace("_", "-")


def _paper_label(table: dict, learner: str) -> str:
    """The paper row's name, so that a base's row never reads as the new learner's paper result."""
    base = paper_base(table, learner)
    return f"{learner} (paper)" if base is None else f"{learner}: its base, the paper's {base}"


def _section(table: dict, description: str) -> list[str]:
    columns = table["columns"]
    lines = [
        f"## Preset `{table['preset']}`" + (f": {description}" if description else ""),
        "",
        "| row | " + " | ".join(columns) + " | IQM [95% CI] |",
        "|---|" + "---:|" * len(columns) + "---:|",
        _reference_row("human (paper)", [table["human"][c]["paper"] for c in columns]),
        _reference_row("handcrafted (ours)", [table["handcrafted"].get(c, {}).get("mean") for c in columns]),
        _reference_row("handcrafted (paper)", [table["handcrafted"].get(c, {}).get("paper") for c in columns]),
    ]
    for learner, cells in table["learners"].items():
        iqm, ours_iqm, paper_iqm = table["iqm"].get(learner), "—", "—"
        if iqm:
            some = "" if iqm["tasks"] == len(columns) else f" ({iqm['tasks']} of {len(columns)} columns)"
            ours_iqm = interval(iqm["iqm"], iqm["ci95"]) + some
            if iqm["paper_iqm"] is not None:
                paper_iqm = f"{iqm['paper_iqm']:.3f} (ours' {_columns(iqm['paper_columns'])})"
        ours = [interval(cells[c]["mean"], cells[c]["ci95"]) if c in cells else "—" for c in columns]
        theirs = [number(table["paper_rows"][learner].get(c)) for c in columns]
        lines.append(f"| **{learner}** (ours) | " + " | ".join(ours) + f" | {ours_iqm} |")
        lines.append(f"| {_paper_label(table, learner)} | " + " | ".join(theirs) + f" | {paper_iqm} |")
    if not table["learners"]:
        return lines + [
            "",
            "No finished cells yet: `snac table --preset "
            f"{table['preset']} --dry-run` shows the plan, `snac table --preset {table['preset']}` runs it.",
            "",
        ]
    lines += [
        "",
        "Env steps per seed (`*`: below the requested budget):",
        "",
        "| learner | seeds | " + " | ".join(columns) + " |",
        "|---|---:|" + "---:|" * len(columns),
    ]
    for learner, cells in table["learners"].items():
        seeds = ", ".join(map(str, sorted({len(v["seeds"]) for v in cells.values()})))
        budgets = [budget_text(cells[c]["budget"]) if c in cells else "—" for c in columns]
        lines.append(f"| {learner} | {seeds} | " + " | ".join(budgets) + " |")
    walls = {
        learner: [cells[c]["budget"]["training_wall_s"] if c in cells else None for c in columns]
        for learner, cells in table["learners"].items()
    }
    if any(w is not None for row in walls.values() for w in row):
        lines += [
            "",
            PAGE_TEXT["walls"],
            "",
            "| learner | " + " | ".join(columns) + " |",
            "|---|" + "---:|" * len(columns),
        ]
        for learner, row in walls.items():
            lines.append(f"| {learner} | " + " | ".join(number(None if w is None else w / 60, 1) for w in row) + " |")
    return lines + [""]


def markdown(tables: dict[str, dict], descriptions: dict[str, str] | None = None) -> str:
    """table.md: the shared header, then one section per preset."""
    descriptions = descriptions or {}
    lines = _header(next((t for t in tables.values() if t.get("kind") != "ablation"), next(iter(tables.values()))))
    for name, table in tables.items():
        write = ablation.section if table.get("kind") == "ablation" else _section
        lines += write(table, descriptions.get(name, ""))
    return "\n".join(lines)


def figure(table: dict, path: str | Path) -> None:
    """Every learner's per-column interval (mean and 95% CI), the paper's value as a marker."""
    plt = pyplot()
    columns, learners = table["columns"], list(table["learners"])
    fig, axes = plt.subplots(2, 5, figsize=(17, 6.5), sharey=True)
    for ax, column in zip(axes.flat, columns):
        for x, learner in enumerate(learners):
            cell = table["learners"][learner].get(column)
            if cell is None:
                continue
            mean, (low, high) = cell["mean"], cell["ci95"]
            label = "ours: mean, 95% CI" if x == 0 else None
            ax.errorbar(x, mean, yerr=[[mean - low], [high - mean]], fmt="o", color="C0", capsize=4, label=label)
            if cell["paper"] is not None:
                ax.plot(x, cell["paper"], "x", color="C3", markersize=8, mew=2, label="paper")
        hand = table["handcrafted"].get(column)
        if hand is not None:
            ax.axhline(hand["mean"], color="0.5", linestyle="--", linewidth=1, label="handcrafted (ours)")
        ax.set_title(column, fontsize=10)
        ax.set_xticks(range(len(learners)), learners, rotation=45, fontsize=8)
        ax.set_ylim(0, 1.02)
        ax.set_xlim(-0.5, max(len(learners), 1) - 0.5)
        ax.grid(axis="y", alpha=0.3)
    for ax in axes[:, 0]:
        ax.set_ylabel("final IoU")
    handles = {}
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    fig.suptitle(f"snac table, preset {table['preset']!r}", y=0.99, fontsize=11)
    if handles:
        legend = {"loc": "upper center", "bbox_to_anchor": (0.5, 0.955), "ncol": len(handles), "frameon": False}
        fig.legend(list(handles.values()), list(handles), **legend)
    fig.tight_layout(rect=(0, 0, 1, 0.9))
    save_png(fig, path, dpi=110)


def write_report(
    preset: str,
    runs_dir: str | Path | None,
    results_dir: str | Path,
    *,
    reps: int = statistics.DEFAULT_REPS,
    dry_run: bool = False,
) -> dict[str, Path]:
    """Copy `preset`'s finished cells from `runs_dir` (None: none) into the record, then rebuild
    table.md and table.json from every preset's copies under `results_dir/table/`, and per preset
    `table-<preset>.png` (an ablation's: its arms' learning curves). Every copy, written or to be
    written, is read and checked before the first file is written, and no file is written through
    a symbolic link. `dry_run`: check all that and return what would be written (the copies as
    `copy:<cell directory>`), writing nothing."""
    results_dir = Path(results_dir)
    planned = copies(None if runs_dir is None else Path(runs_dir), results_dir, preset)
    pending = {destination: text for _, destination, text in planned}
    presets = load_presets()
    folders = {p.name for p in (results_dir / "table").glob("*") if p.is_dir()}
    if unknown := sorted(folders - set(presets)):
        raise ValueError(
            f"{results_dir / 'table'} holds cells of {unknown}, no preset of budgets.toml: move them out of the results"
        )
    found = [n for n in presets if n in folders or (n == preset and planned)] or [preset]
    hand_path = results_dir / "handcrafted.json"
    handcrafted = schemas.load(hand_path, schemas.EVAL_JSON) if hand_path.is_file() else None
    raws = {n: load_raw(results_dir, n, pending) for n in found}
    arms = {n: [v.name for v in presets[n].variants] for n in found}
    figures = {n: results_dir / (ablation.curves_name(n) if arms[n] else f"table-{n}.png") for n in found}
    paths = {"md": results_dir / "table.md", "json": results_dir / "table.json"}
    for path in [*paths.values(), *figures.values()]:
        refuse_links(results_dir, path)
    if dry_run:
        copied = {f"copy:{source}": destination for source, destination, _ in planned}
        return {**copied, **paths, **{f"png:{n}": path for n, path in figures.items()}}
    for path, text in pending.items():
        atomic_write_text(path, text)
    tables = {}
    for name in found:
        if arms[name]:  # the arms' curves first: the section says whether they were drawn
            drawn = ablation.curves(raws[name], arms=arms[name], path=figures[name], preset=name)
            tables[name] = ablation.build(raws[name], arms=arms[name], preset=name, reps=reps, curves=drawn)
            if drawn:
                paths[f"png:{name}-curves"] = figures[name]
        else:
            tables[name] = build(raws[name], handcrafted=handcrafted, preset=name, reps=reps)
    atomic_write_text(paths["md"], markdown(tables, {n: p.description for n, p in presets.items()}))
    atomic_write_json(paths["json"], tables)
    for name in found:
        if not arms[name]:
            paths[f"png:{name}"] = figures[name]
            figure(tables[name], figures[name])
    return paths
