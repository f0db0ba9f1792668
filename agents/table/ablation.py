"""The ablation section of `snac table --report`: an ablation preset's arms (`budgets.toml`,
`variants`) against its base arm, beside the paper's ablation table.

The paper reports its DRQN ablation as the base IoU and, for each switch, the change from it
(`paper_results.json`, "ablation_drqn"). Ours is the same shape: each arm's mean over seeds with
its 95% bootstrap interval across seeds, and for every arm but the base, its difference from the
base with the interval of that difference (`statistics.difference_summary`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agents.table import statistics
from agents.table.files import adopted_base, budget_record, budget_text, interval, read_raw, record_path, seed_means
from agents.table.plan import TRAIN_SEED
from agents.table.presets import BASE_ARM as BASE
from agents.table.presets import Preset, arm_changes
from snac_jax.atomic import atomic_write
from snac_jax.evaluation import REPORT_EVAL_SEED
from snac_jax.paper import load_paper_results

PAPER_TABLE = "ablation_drqn"
PAPER_LEARNER = "drqn"  # the paper's ablation table is DRQN's


def with_adopted_base(raw: dict, results_dir: Path, preset: Preset, pending: dict[Path, str]) -> dict:
    """`raw` (`files.load_raw`, the copies of `preset`) with the base arm of each (learner, task)
    that has other arms but no base copy of its own read from the copy of the preset it `adopts`
    (`pending`: copies about to be written), where that cell is every arm's base
    (`files.adopted_base`); else the base has no cell. A base copy of its own that names the run
    it adopted is marked `own_copy` (the run as it was adopted, which its arms were measured against)."""
    if preset.adopts is None or not preset.variants:
        return raw
    base = next(v for v in preset.variants if v.name == BASE)
    for algorithm, cells in raw.items():
        for task in sorted({files["cell"]["task"] for files in cells.values()} & set(base.tasks)):
            path = record_path(results_dir, preset.adopts, algorithm, task)
            if (own := cells.get(f"{task}.{BASE}")) is not None:
                own["own_copy"] = "adopted_from" in own["cell"]
            if own is not None or not (path in pending or path.is_file()):
                continue
            record = read_raw(path, pending.get(path))
            arms = [files for files in cells.values() if files["cell"]["task"] == task]
            if all(adopted_base(record, files) for files in arms):
                adopted = {"variant": BASE, "paper_variant": base.paper, "switches": "", "settings": {}}
                adopted["adopted_from"] = f"{preset.adopts}/{algorithm}/{task}"
                cells[f"{task}.{BASE}"] = {**record, "cell": {**record["cell"], **adopted}}
    return raw


def curves_name(preset: str) -> str:
    """The file name of an ablation preset's learning-curve figure, beside table.md."""
    return f"table-{preset}-curves.png"


def _arm_order(arms: list[str]):
    """Sort key of arm names: the preset's order, then arms it does not name, by name."""
    return lambda arm: (arms.index(arm) if arm in arms else len(arms), arm)


def build(
    raw: dict,
    *,
    arms: list[str],
    paper: dict | None = None,
    preset: str = "",
    reps: int = statistics.DEFAULT_REPS,
    bootstrap_seed: int = 0,
    curves: bool = False,
) -> dict[str, Any]:
    """table.json's section of an ablation preset from its copied cells (`raw.load_raw`); `arms`:
    the preset's arm names in the order the table lists them (arms it does not name follow, by
    name); `curves`: whether the arms' learning-curve figure was drawn (`curves`). The paper's
    values stand beside the learner it ablated (DRQN) only."""
    paper = (load_paper_results() if paper is None else paper).get(PAPER_TABLE, {})
    order = _arm_order(arms)
    learners: dict[str, dict] = {}
    for algorithm, cells in raw.items():
        ablated = algorithm == PAPER_LEARNER  # not drqn-aux, which shares DRQN's paper row but is another learner
        by_task: dict[str, dict[str, dict]] = {}
        for files in cells.values():
            by_task.setdefault(files["cell"]["task"], {})[files["cell"]["variant"]] = files
        for task, found in by_task.items():
            base = found.get(BASE)
            rows = {}
            for arm in sorted(found, key=order):
                files, scores = found[arm], seed_means(found[arm])
                paper_arm = paper.get(task, {}).get(files["cell"]["paper_variant"], {}) if ablated else {}
                row = {
                    **statistics.cell_summary(scores, reps=reps, seed=bootstrap_seed),
                    "paper_variant": files["cell"]["paper_variant"],
                    "changes": arm_changes(
                        files["cell"]["switches"], files["cell"].get("settings", {}), files["cell"].get("evaluation")
                    ),
                    "budget": budget_record([files]),
                    "paper": paper_arm.get("avg"),
                    "adopted_from": files["cell"].get("adopted_from"),
                    **({"own_copy": True} if files.get("own_copy") else {}),
                    **({"evaluation": files["cell"]["evaluation"]} if files["cell"].get("evaluation") else {}),
                }
                if arm != BASE:  # the paper's value of an arm is its change from the base
                    # A change is read only against a base trained as long: an arm kept at a
                    # smaller budget than a retrained base would show the budget, not the arm.
                    comparable = base is not None and base["config"]["total_steps"] == files["config"]["total_steps"]
                    row["delta"] = (
                        statistics.difference_summary(scores, seed_means(base), reps=reps, seed=bootstrap_seed)
                        if comparable
                        else None
                    )
                rows[arm] = row
            learners.setdefault(algorithm, {})[task] = rows
    return {
        "preset": preset,
        "kind": "ablation",
        "train_seed": TRAIN_SEED,
        "eval_seed": REPORT_EVAL_SEED,
        "bootstrap": {"reps": reps, "confidence": 0.95, "interval": "percentile", "seed": bootstrap_seed},
        "ablation": learners,
        "curves": curves,
    }


def _scored_otherwise(table: dict) -> bool:
    """Whether an arm of the section acts with settings of its own when scored (`Variant.evaluation`)."""
    return any(
        row.get("evaluation")
        for tasks in table["ablation"].values()
        for rows in tasks.values()
        for row in rows.values()
    )


def section(table: dict, description: str) -> list[str]:
    """table.md's section of an ablation preset."""
    lines = [
        f"## Preset `{table['preset']}`" + (f": {description}" if description else ""),
        "",
        "Each arm trains and is scored with its switches (SPEC §9) and trains with its learner settings"
        + (
            '; an arm whose settings say "at evaluation" trains as the base arm (taking over its run) and its '
            "greedy policy acts with them when scored"
            if _scored_otherwise(table)
            else ""
        )
        + ". The paper's value of the base arm is its IoU, of every other arm its change from the base (the paper's ablation table, average IoU). "
        "Δ: ours minus our base, with the 95% bootstrap interval of the difference (each arm's seeds "
        "resampled on their own). With three to five seeds per arm a percentile bootstrap interval is narrow: "
        "for two arms of three normal draws and no true difference it holds 0 only about four times in "
        "five, so read a Δ as an effect only where it is large against the seeds' spread. No Δ (—) where "
        "the base has no cell yet or trained another number of env steps than the arm.",
        "",
    ]
    if not table["ablation"]:
        return lines + [f"No finished cells yet: `snac table --preset {table['preset']} --dry-run` shows the plan.", ""]
    lines += [
        "| learner | task | arm (paper's name) | switches, settings | ours: IoU [95% CI] | ours: Δ vs base [95% CI] | paper: IoU or Δ | env steps/seed |",
        "|---|---|---|---|---:|---:|---:|---:|",
    ]
    for learner, tasks in table["ablation"].items():
        for task, rows in tasks.items():
            for arm, row in rows.items():
                ours = interval(row["mean"], row["ci95"])
                delta = "—" if row.get("delta") is None else interval(row["delta"]["delta"], row["delta"]["ci95"], True)
                paper = (
                    "—" if row["paper"] is None else f"{row['paper']:+.3f}" if arm != BASE else f"{row['paper']:.3f}"
                )
                paper_name = f" ({row['paper_variant']})" if row["paper_variant"] else ""
                lines.append(
                    f"| {learner} | {task} | {arm}{paper_name} | `{row['changes'] or '—'}` | {ours} | "
                    f"{delta} | {paper} | {budget_text(row['budget'])} |"
                )
    adopted = [
        f"{learner} on {task} ({arm}): `{row['adopted_from']}`"
        + (
            f" (read from this preset's own copy, `{task}.{arm}.json`, the run as it was adopted)"
            if row.get("own_copy")
            else ""
        )
        for learner, tasks in table["ablation"].items()
        for task, rows in tasks.items()
        for arm, row in rows.items()
        if row.get("adopted_from")
    ]
    if adopted:
        lines += [
            "",
            "Arms that adopted another preset's finished run with the same config.json (`adopts` in "
            "budgets.toml) instead of training it again: " + "; ".join(adopted) + ".",
        ]
    if table.get("curves"):
        lines += [
            "",
            f"Learning curves of the arms: `{curves_name(table['preset'])}` (sampled training IoU, "
            "the mean over seeds and a band from the lowest to the highest seed).",
        ]
    return lines + [""]


def curves(raw: dict, *, arms: list[str], path: str | Path, preset: str = "") -> bool:
    """The arms' learning curves, one panel per (learner, task): each arm's sampled training IoU
    (metrics.jsonl) against env steps, the mean over seeds with a band from the lowest to the
    highest seed. The table scores the greedy policy once at the end; the curves show whether
    an arm's gap was there all along or opened late. Returns False (and writes nothing) where no
    copied cell kept its curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = _arm_order(arms)
    panels: dict[tuple[str, str], dict[str, list[dict]]] = {}
    for algorithm, cells in raw.items():
        for files in cells.values():
            if files.get("metrics"):
                panels.setdefault((algorithm, files["cell"]["task"]), {})[files["cell"]["variant"]] = files["metrics"]
    if not panels:
        return False
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
    for ax, ((algorithm, task), found) in zip(axes[0], sorted(panels.items())):
        for colour, arm in enumerate(sorted(found, key=order)):
            steps = np.array([r["env_steps"] for r in found[arm]], dtype=float)
            iou = np.array([r["iou"] for r in found[arm]], dtype=float).reshape(len(steps), -1)  # (chunks, seeds)
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
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    plt.close(fig)
    return True
