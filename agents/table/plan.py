"""The plan of `snac table`: the grid's cells (`agents.table.presets`), what each trains and
where it stands, before anything starts.

A cell trains as one `agents.training.driver.train` call with its seeds vmapped, in
`<runs-dir>/<preset>/<algorithm>/<task>[.<arm>]/`, then is scored with the reporting protocol. Its
directory says where it stands: `done` (a finished eval.json, with or without checkpoints),
`partial` (checkpoints: resumed), or `new` (empty, or only what its own start left before a first
checkpoint). A run there with other settings is refused, never trained over (another budget included).

An ablation's arm with `evaluation` settings trains nothing: it scores its base arm's run again.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from agents.table.files import (
    CELL_FILE,
    EVAL_FILE,
    eval_is_valid,
    expected_episodes,
    steps_text,
)
from agents.table.presets import BASE_ARM, Preset, Variant, expand_tasks
from agents.training import checkpoint, schemas
from agents.training.config import TrainConfig
from agents.training.registry import make_config, tuned_source
from snac_jax.evaluation import REPORT_EVAL_SEED
from snac_jax.paper import paper_column
from snac_jax.tasks import task_spec

TRAIN_SEED = 1
"""Base training seed of the table's runs (seed i trains from fold_in(key(1), i)); the runs that
chose the tuned settings trained from base seed 0, so no table run repeats one of them."""
RESTARTABLE = {checkpoint.CONFIG_FILE, checkpoint.METRICS_FILE, checkpoint.CHECKPOINT_DIR}
"""What a cell's start leaves before its first checkpoint, besides its lock."""


def scoring_config(config: TrainConfig, evaluation: dict[str, Any]) -> TrainConfig:
    """The config whose greedy policy a cell scores: its training config with the arm's
    evaluation-only settings, which may only be the learner's `acting_options`."""
    if not evaluation:
        return config
    other = sorted(set(evaluation) - set(config.acting_options))
    if other:
        raise ValueError(
            f"{config.algorithm} cannot act with {other} at evaluation: an option there may change only how "
            f"the trained policy acts, not its network, its world or its training; {config.algorithm}'s: "
            f"{', '.join(config.acting_options) or 'none'}"
        )
    trained = {k: v for k, v in config.to_json().items() if k not in ("algorithm", "task")}
    return make_config(config.algorithm, config.task, **{**trained, **evaluation})


def requested_budget(preset: Preset, config: TrainConfig) -> tuple[int, str]:
    """Env steps per seed the preset asks for `config`'s algorithm and task, and why."""
    budget = preset.budgets.get(config.algorithm, {})
    steps, why = budget.get("env_steps"), f"{preset.name}: {budget.get('source')}"
    if isinstance(steps, dict):  # one budget per environment task
        if config.task not in steps:
            raise ValueError(
                f"the {preset.name} preset gives {config.algorithm} a budget on {', '.join(steps)} only, not on {config.task}"
            )
        return steps[config.task], why
    if steps is not None:
        return steps, why
    if "episodes" in budget:
        limit = config.max_steps or task_spec(config.task).max_steps
        return budget["episodes"] * limit, f"{why}, x the step limit ({task_spec(config.task).dim}D: {limit})"
    if "source" in budget:
        return config.total_steps, why
    if "total_steps" in preset.overrides(config.algorithm):
        return config.total_steps, f"{preset.name}: the preset's total_steps"
    if (source := tuned_source(config.algorithm, config.task, "total_steps")) is not None:
        return config.total_steps, f"{preset.name}: tuned total_steps (agents/tuned/{source.name})"
    return config.total_steps, f"{preset.name}: {type(config).__name__}'s default total_steps (no tuned entry)"


@dataclasses.dataclass
class Cell:
    algorithm: str
    task: str
    directory: Path
    config: TrainConfig  # its total_steps: the budget, env steps per seed
    budget_source: str  # why that budget
    preset: Preset
    variant: Variant | None = None  # an ablation's arm: the cell's directory is <task>.<arm>
    status: str = "new"  # new | partial | done
    done_steps: int = 0  # per seed, from the run's metrics
    estimate_s: float | None = None
    estimate_from: str = ""
    metrics: list[dict] = dataclasses.field(default_factory=list)
    base_run: Path | None = None  # an evaluation arm: the base arm's run it scores

    @property
    def evaluation(self) -> dict[str, Any]:
        return {} if self.variant is None else self.variant.evaluation

    @property
    def total_steps(self) -> int:
        """Env steps per seed the run will have trained (whole updates)."""
        return self.config.num_updates * self.config.steps_per_update

    def record(self) -> dict[str, Any]:
        """cell.json: what the report needs beside config.json and eval.json."""
        arm = {}
        if self.variant is not None:
            arm = {"variant": self.variant.name, "paper_variant": self.variant.paper}
            arm |= {"switches": self.variant.switches, "settings": self.variant.settings}
            if self.evaluation:  # the run it scored again, `<preset>/<algorithm>/<cell>`
                arm |= {"evaluation": self.evaluation, "adopted_from": "/".join(self.base_run.parts[-3:])}
        steps = self.config.total_steps
        return {
            "preset": self.preset.name,
            "algorithm": self.algorithm,
            "column": paper_column(self.task),
            "task": self.task,
            # `requested` above `env_steps`: a record of the former wall-time cap (the report's `*`)
            "budget": {"env_steps": steps, "requested": steps, "source": self.budget_source},
            "eval_seed": REPORT_EVAL_SEED,
            "protocol": self.preset.protocol,
            **arm,
        }


def settings_differ(cell: Cell, config: TrainConfig) -> list[str]:
    """The settings in which a run made with `config` differs from the cell's."""
    stored, wanted = config.to_json(), cell.config.to_json()
    return sorted(k for k in set(stored) | set(wanted) if stored.get(k) != wanted.get(k))


def _trained_like(cell: Cell, directory: Path) -> bool:
    """Whether `directory` holds a config.json with the cell's settings."""
    try:
        return not settings_differ(cell, checkpoint.read_config(directory))
    except (OSError, ValueError):
        return False


def cell_state(cell: Cell) -> None:
    """Fill in where the cell stands from its directory (see the module's docstring)."""
    directory, episodes = cell.directory, expected_episodes(cell.task, cell.preset.protocol)
    if directory.is_symlink() or (directory.exists() and not directory.is_dir()):
        raise ValueError(f"{directory} is not a directory (a link or a file), where a cell of the table goes")
    last, ours = checkpoint.latest_chunk(directory), _trained_like(cell, directory)
    if last is not None and not ours:
        stored, wanted = checkpoint.read_config(directory), cell.config.to_json()
        changes = ", ".join(
            f"{k}: {stored.to_json().get(k)!r} there, {wanted.get(k)!r} now" for k in settings_differ(cell, stored)
        )
        raise ValueError(
            f"{directory} holds a run made with other settings ({changes}); "
            "choose another --runs-dir or remove that directory"
        )
    if ours and eval_is_valid(directory / EVAL_FILE, cell.config.seeds, episodes, REPORT_EVAL_SEED):
        path = directory / CELL_FILE
        scored = schemas.load(path, schemas.CELL_JSON).get("evaluation", {}) if path.is_file() else {}
        if scored != cell.evaluation:
            raise ValueError(
                f"{directory} was scored acting with {scored or 'its training settings'}, the arm now asks "
                f"{cell.evaluation or 'its training settings'}; move that directory away to score the run again"
            )
        cell.status, cell.done_steps = "done", cell.total_steps
    elif last is not None:
        records = checkpoint.read_metrics_lines(directory / checkpoint.METRICS_FILE)
        cell.metrics = [r for r in records if r["chunk"] <= last]
        cell.status, cell.done_steps = "partial", (cell.metrics[-1]["env_steps"] if cell.metrics else 0)
    else:
        cell.status, cell.done_steps = "new", 0
        _check_new(cell, ours)


def _check_new(cell: Cell, ours: bool) -> None:
    """A new cell's directory holds nothing (a free lock aside), or what its own start left before
    its first checkpoint (trained again from the start), or, for an evaluation arm, its own
    scoring cut short; anything else is refused: the table deletes nothing it did not make."""
    directory = cell.directory
    if not directory.is_dir():
        return
    checkpoint.check_lock_file(directory)
    entries = sorted(p.name for p in directory.iterdir() if p.name != checkpoint.LOCK_FILE)
    if not entries or (ours and cell.evaluation and not (directory / checkpoint.CHECKPOINT_DIR).exists()):
        return
    if ours and set(entries) <= RESTARTABLE:
        if checkpoint.read_metrics_lines(directory / checkpoint.METRICS_FILE):
            raise ValueError(
                f"{directory} holds a start of this cell whose {checkpoint.METRICS_FILE} records chunks that "
                "no checkpoint kept; the table deletes nothing it did not make: remove that directory to "
                "train the cell from the start"
            )
        return
    shown = ", ".join(entries[:6]) + (", ..." if len(entries) > 6 else "")
    raise ValueError(
        f"{directory} holds files that no start of this cell left there ({shown}) and no checkpoint; "
        "the table deletes nothing it did not make: move that directory away, or choose another --runs-dir"
    )


def estimate(cell: Cell) -> None:
    """Seconds of training left, and where the figure comes from: a started run's own rate (its
    metrics.jsonl); None for a cell not started, as nothing else measures its rate."""
    if cell.status == "done":
        cell.estimate_s, cell.estimate_from = 0.0, "finished"
    elif cell.evaluation:
        cell.estimate_s, cell.estimate_from = None, f"scores {cell.base_run} again: unknown"
    elif not cell.metrics or cell.metrics[-1]["wall_s"] <= 0:
        cell.estimate_s, cell.estimate_from = None, "unknown: not started"
    else:
        last, seeds = cell.metrics[-1], cell.config.seeds
        rate = last["env_steps"] * seeds / last["wall_s"]
        cell.estimate_s = (cell.total_steps - cell.done_steps) * seeds / rate
        cell.estimate_from = (
            f"this run's metrics.jsonl: {rate:,.0f} steps/s over {len(cell.metrics)} chunks, training only"
        )


def make_plan(preset: Preset, algorithms, tasks, seeds: int | None, runs_dir, arms=None) -> list[Cell]:
    """Every cell of the grid (algorithms x tasks, x an ablation's arms, or the `arms` named), with
    its config, budget, status and estimate."""
    runs_dir, variants = Path(runs_dir), preset.variants
    if arms is not None:
        names = [v.name for v in preset.variants]
        unknown = [a for a in arms if a not in names]
        if not names or unknown or not arms:
            wrong = f"has no arm(s) {unknown or list(arms)}" if arms else "needs at least one arm named"
            its = ", ".join(names) if names else "none (it is not an ablation)"
            raise ValueError(f"preset {preset.name!r} {wrong}; its arms: {its}")
        variants = tuple(v for v in preset.variants if v.name in arms)
    cells = []
    for algorithm in dict.fromkeys(algorithms):
        for task in expand_tasks(tasks):
            for variant in [v for v in variants if task in v.tasks] if variants else [None]:
                arm = {} if variant is None else {**variant.settings, "switches": variant.switches}
                overrides = {
                    **preset.overrides(algorithm),
                    "seeds": seeds or preset.seeds,
                    "seed": TRAIN_SEED,
                    "switches": "",
                    **arm,
                }
                steps, source = requested_budget(preset, make_config(algorithm, task, **overrides))
                config = make_config(algorithm, task, **{**overrides, "total_steps": steps})
                name = task if variant is None else f"{task}.{variant.name}"
                cells.append(
                    Cell(algorithm, task, runs_dir / preset.name / algorithm / name, config, source, preset, variant)
                )
    if variants and not cells:
        chosen = "arm" if arms is None else "arm named in --arms"
        listing = "; ".join(f"{v.name}: {', '.join(v.tasks)}" for v in variants)
        raise ValueError(f"no {chosen} of preset {preset.name!r} runs on {', '.join(tasks)}; their tasks: {listing}")
    training = set()  # (algorithm, task) whose base arm this plan trains
    for cell in cells:
        if cell.evaluation:
            scoring_config(cell.config, cell.evaluation)  # an option the learner refuses fails before training
        cell_state(cell)
        if cell.variant is not None and cell.variant.name == BASE_ARM and cell.status in ("new", "partial"):
            training.add((cell.algorithm, cell.task))
        if cell.evaluation and cell.status != "done":
            cell.base_run = runs_dir / preset.name / cell.algorithm / f"{cell.task}.{BASE_ARM}"
            started = checkpoint.latest_chunk(cell.base_run) is not None and _trained_like(cell, cell.base_run)
            if (cell.algorithm, cell.task) not in training and not started:
                raise ValueError(
                    f"arm {cell.variant.name!r} of preset {preset.name!r} scores the base arm's run again: "
                    f"no run of it with checkpoints and this arm's config is at {cell.base_run}; train it first "
                    f"(snac table --preset {preset.name} --tasks {cell.task}) or leave the arm out (--arms)"
                )
        estimate(cell)
    return cells


def duration(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    hours, rest = divmod(int(round(seconds)), 3600)
    return f"{hours} h {rest // 60:02d} min" if hours else f"{rest // 60} min {rest % 60:02d} s"


def format_plan(cells: list[Cell], runs_dir: str | Path) -> str:
    """The plan as printed before anything starts: one line per cell, the budgets' sources and
    the total estimate (a lower bound, or unknown, where cells have none)."""
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
        done = f"{c.done_steps / max(c.total_steps, 1):.0%} done"
        status = done if c.status == "partial" else c.status
        lines.append(
            f"{c.algorithm:<10} {c.directory.name:<{width}} {steps_text(c.config.total_steps):>24} {c.config.seeds:>5} "
            f"{status:<9} {duration(c.estimate_s):>13}  {c.estimate_from}"
        )
    lines += ["", "budgets:", *(f"  {s}" for s in dict.fromkeys(f"{c.algorithm}: {c.budget_source}" for c in cells))]
    known = sum(c.estimate_s for c in cells if c.estimate_s is not None)
    unknown = sum(c.estimate_s is None for c in cells)
    total, note = duration(known), ""
    if unknown:  # a sum of no estimates is no estimate; with some, a lower bound
        total = f"at least {total}" if known > 0 else "unknown"
        note = f"; {unknown} {'cell' if unknown == 1 else 'cells'} of unknown time" + (
            " not counted" if known > 0 else ""
        )
    counted = ", ".join(f"{sum(c.status == s for c in cells)} {s}" for s in ("new", "partial", "done")) + note
    return "\n".join([*lines, "", f"total estimate: {total} ({counted})"])
