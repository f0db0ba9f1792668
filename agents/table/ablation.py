"""The ablation section of `snac table --report`: an ablation preset's arms (`budgets.toml`,
`variants`) against its base arm, beside the paper's ablation table.

The paper reports its DRQN ablation as the base IoU and, for each switch, the change from it
(`paper_results.json`, "ablation_drqn"). Ours is the same shape: each arm's mean over seeds with
its 95% bootstrap interval across seeds, and for every arm but the base, its difference from the
base with the interval of that difference (`statistics.difference_summary`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from agents.table import statistics
from agents.table.files import PAGE_TEXT, budget_record, budget_text, interval, seed_means
from agents.table.plan import TRAIN_SEED
from agents.table.presets import BASE_ARM as BASE
from agents.training.plotting import pyplot, save_png
from snac_jax.evaluation import REPORT_EVAL_SEED
from snac_jax.paper import load_paper_results

PAPER_TABLE = "ablation_drqn"
PAPER_LEARNER = "drqn"  # the paper's ablation table is DRQN's


def arm_changes(switches: str, settings: dict[str, Any], evaluation: dict[str, Any] | None = None) -> str:
    """An arm's changes as the table prints them: switches, settings, then evaluation-only settings."""
    return ", ".join(
        ([switches] if switches else [])
        + [f"{k}={json.dumps(v)}" for k, v in sorted(settings.items())]
        + [f"{k}={json.dumps(v)} at evaluation" for k, v in sorted((evaluation or {}).items())]
    )


def curves_name(preset: str) -> str:
    """The file name of an ablation preset's learning-curve figure, beside table.md."""
    return f"table-{preset}-curves.png"


def _arms(raw: dict, arms: list[str]) -> dict[tuple[str, str], dict[str, dict]]:
    """(learner, task) -> arm -> its copied cell, in the order of `raw`; the arms in the preset's
    order (`arms`), then arms it no longer names (their copies are still reported), by name."""
    grouped: dict[tuple[str, str], dict[str, dict]] = {}
    for algorithm, cells in raw.items():
        for files in cells.values():
            grouped.setdefault((algorithm, files["cell"]["task"]), {})[files["cell"]["variant"]] = files
    order = {arm: index for index, arm in enumerate(arms)}
    return {
        key: {arm: found[arm] for arm in sorted(found, key=lambda arm: (order.get(arm, len(arms)), arm))}
        for key, found in grouped.items()
    }


def build(
    raw: dict,
    *,
    arms: list[str],
    paper: dict | None = None,
    preset: str = "",
    reps: int = statistics.DEFAULT_REPS,
    curves: bool = False,
) -> dict[str, Any]:
    """table.json's section of an ablation preset from its copied cells (`files.load_raw`);
    `arms`: the preset's arm names in the order the table lists them; `curves`: whether the arms'
    learning-curve figure was drawn. The paper's values stand beside the learner it ablated (DRQN)
    only, not beside drqn-aux, which shares DRQN's paper row but is another learner."""
    paper = (load_paper_results() if paper is None else paper).get(PAPER_TABLE, {})
    learners: dict[str, dict] = {}
    for (algorithm, task), found in _arms(raw, arms).items():
        base, rows = found.get(BASE), {}
        for arm, files in found.items():
            cell, scores = files["cell"], seed_means(files)
            theirs = paper.get(task, {}).get(cell["paper_variant"], {}) if algorithm == PAPER_LEARNER else {}
            rows[arm] = {
                **statistics.cell_summary(scores, reps=reps),
                "paper_variant": cell["paper_variant"],
                "changes": arm_changes(cell["switches"], cell.get("settings", {}), cell.get("evaluation")),
                "budget": budget_record([files]),
                "paper": theirs.get("avg"),  # the base arm's IoU, or another arm's change from the base
                "adopted_from": cell.get("adopted_from"),
                **({"evaluation": cell["evaluation"]} if cell.get("evaluation") else {}),
            }
            if arm != BASE:
                # A change is read only against a base trained as long: an arm kept at a smaller
                # budget than a retrained base would show the budget, not the arm.
                comparable = base is not None and base["config"]["total_steps"] == files["config"]["total_steps"]
                delta = statistics.difference_summary(scores, seed_means(base), reps=reps) if comparable else None
                rows[arm]["delta"] = delta
        learners.setdefault(algorithm, {})[task] = rows
    return {
        "preset": preset,
        "kind": "ablation",
        "train_seed": TRAIN_SEED,
        "eval_seed": REPORT_EVAL_SEED,
        "bootstrap": statistics.bootstrap_record(reps),
        "ablation": learners,
        "curves": curves,
    }


def _rows(table: dict):
    """(learner, task, arm, row) of every row of an ablation section, in order."""
    for learner, tasks in table["ablation"].items():
        for task, rows in tasks.items():
            for arm, row in rows.items():
                yield learner, task, arm, row


def section(table: dict, description: str) -> list[str]:
    """table.md's section of an ablation preset."""
    scored_otherwise = any(row.get("evaluation") for *_, row in _rows(table))
    evaluation = PAGE_TEXT["ablation_evaluation"] if scored_otherwise else ""
    lines = [
        f"## Preset `{table['preset']}`" + (f": {description}" if description else ""),
        "",
        PAGE_TEXT["ablation"].format(evaluation=evaluation),
        "",
    ]
    if not table["ablation"]:
        return lines + [f"No finished cells yet: `snac table --preset {table['preset']} --dry-run` shows the plan.", ""]
    lines += [
        "| learner | task | arm (paper's name) | switches, settings | ours: IoU [95% CI] | ours: Δ vs base [95% CI] | paper: IoU or Δ | env steps/seed |",
        "|---|---|---|---|---:|---:|---:|---:|",
    ]
    copied = []
    for learner, task, arm, row in _rows(table):
        ours = interval(row["mean"], row["ci95"])
        delta = "—" if row.get("delta") is None else interval(row["delta"]["delta"], row["delta"]["ci95"], True)
        paper = "—" if row["paper"] is None else f"{row['paper']:+.3f}" if arm != BASE else f"{row['paper']:.3f}"
        paper_name = f" ({row['paper_variant']})" if row["paper_variant"] else ""
        lines.append(
            f"| {learner} | {task} | {arm}{paper_name} | `{row['changes'] or '—'}` | {ours} | "
            f"{delta} | {paper} | {budget_text(row['budget'])} |"
        )
        if row.get("adopted_from"):
            copied.append(f"{learner} on {task} ({arm}): `{row['adopted_from']}`")
    if copied:
        lines += ["", PAGE_TEXT["copied"].format(arms="; ".join(copied))]
    if table.get("curves"):
        lines += ["", PAGE_TEXT["curves"].format(name=curves_name(table["preset"]))]
    return lines + [""]


def curves(raw: dict, *, arms: list[str], path: str | Path, preset: str = "") -> bool:
    """The arms' learning curves, one panel per (learner, task): each arm's sampled training IoU
    (metrics.jsonl) against env steps, the mean over seeds with a band from the lowest to the
    highest seed. The table scores the greedy policy once at the end; the curves show whether
    an arm's gap was there all along or opened late. Returns False (and writes nothing) where no
    copied cell kept its curve."""
    panels = {
        key: {arm: files["metrics"] for arm, files in found.items() if files.get("metrics")}
        for key, found in sorted(_arms(raw, arms).items())
    }
    panels = {key: found for key, found in panels.items() if found}
    if not panels:
        return False
    plt = pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
    for ax, ((algorithm, task), found) in zip(axes[0], panels.items()):
        for colour, (arm, records) in enumerate(found.items()):
            steps = np.array([r["env_steps"] for r in records], dtype=float)
            iou = np.array([r["iou"] for r in records], dtype=float).reshape(len(steps), -1)  # (chunks, seeds)
            ax.plot(steps, iou.mean(axis=1), color=f"C{colour}", label=f"{arm} ({iou.shape[1]} seeds)")
            ax.fill_between(steps, iou.min(axis=1), iou.max(axis=1), color=f"C{colour}", alpha=0.2, linewidth=0)
        ax.set_title(f"{algorithm}, {task}", fontsize=10)
        ax.set_xlabel("env steps per seed")
        ax.set_ylabel("sampled training IoU")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize="small")
    fig.suptitle(f"snac table, preset {preset!r}: learning curves of the arms", fontsize=11)
    fig.tight_layout()
    save_png(fig, path, dpi=100)
    return True
