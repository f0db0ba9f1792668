"""The plan of `snac table`: which cells a grid has, what each trains, where it stands and how
long it should take, before anything starts.

A cell is one (algorithm, environment task) run in `<runs-dir>/<preset>/<algorithm>/<task>/`: one
`agents.training.driver.train` call with the preset's seeds vmapped, then the reporting protocol. The
paper's `1d-static` column is three cells, one per shape. Budgets are env steps, from the presets of
`budgets.toml` (`agents.table.presets`); a cell that has started estimates its remaining training
time from its own `metrics.jsonl`, and any other is "unknown": there is nothing else to measure by.

A cell's directory holding its run at a smaller budget than the preset's (trained when the table
capped budgets to a wall time) is kept as that run, finished or resumed at its own budget, and the
plan says it is below the preset's: the table never trains over a run. To train the preset's
budget, move that directory away or choose another runs directory.

A preset that `adopts` another takes over its finished cell with a new cell's settings, budget
included (`find_twin`): its run, else its raw copy in the record, since runs directories stay
where they were trained.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from agents.table.files import (
    EVAL_FILE,
    RECORD_FIELD,
    check_finished_without_checkpoints,
    eval_is_valid,
    expected_episodes,
    new_cell_leftovers,
    own_files,
    read_record,
    record_copy,
    record_path,
)
from agents.table.presets import Preset, Variant, expand_tasks
from agents.table.scoring import check_scored_as, missing_run, scoring_config
from agents.training import checkpoint
from agents.training.config import TrainConfig
from agents.training.registry import ALGORITHMS, config_class, make_config, tuned_source
from snac_jax.evaluation import REPORT_EVAL_SEED
from snac_jax.tasks import task_spec

TRAIN_SEED = 1
"""Base training seed of the table's runs (seed i trains from fold_in(key(1), i)); the runs that
chose the tuned settings trained from base seed 0, so no table run repeats one of them."""


# --- budgets -------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Budget:
    """A cell's env steps per seed, the preset's budget, and why the preset asks that."""

    env_steps: int  # per seed, what the cell's config asks: the preset's, or its run's where smaller
    requested: int  # per seed, the preset's
    source: str

    @property
    def below(self) -> bool:
        """Whether the cell's run trains less than the preset asks (a run kept at its own budget)."""
        return self.env_steps < self.requested

    def describe(self) -> str:
        text = _steps(self.env_steps)
        return f"{text} (below {_steps(self.requested)})" if self.below else text


def _steps(n: int) -> str:
    return f"{n / 1e6:.3g}M" if n >= 1e6 else f"{n / 1e3:.3g}k" if n >= 1e3 else str(n)


def requested_budget(preset: Preset, config: TrainConfig) -> tuple[int, str]:
    """Env steps per seed the preset asks for `config`'s algorithm and task, and why."""
    budget = preset.budgets.get(config.algorithm, {})
    if isinstance(budget.get("env_steps"), dict):  # one budget per environment task
        if config.task not in budget["env_steps"]:
            raise ValueError(
                f"the {preset.name} preset gives {config.algorithm} a budget on "
                f"{', '.join(budget['env_steps'])} only, not on {config.task}"
            )
        return int(budget["env_steps"][config.task]), f"{preset.name}: {budget['source']}"
    if "env_steps" in budget:
        return int(budget["env_steps"]), f"{preset.name}: {budget['source']}"
    if "episodes" in budget:
        limit = config.max_steps or task_spec(config.task).max_steps
        steps = int(budget["episodes"]) * limit
        return steps, f"{preset.name}: {budget['source']}, x the step limit ({task_spec(config.task).dim}D: {limit})"
    if "source" in budget:
        why = budget["source"]
    elif "total_steps" in preset.overrides(config.algorithm):
        why = "the preset's total_steps"
    elif (source := tuned_source(config.algorithm, config.task, "total_steps")) is not None:
        why = f"tuned total_steps (agents/tuned/{source.name})"
    else:
        why = f"{type(config).__name__}'s default total_steps (no tuned entry)"
    return config.total_steps, f"{preset.name}: {why}"


def cell_config(
    preset: Preset, algorithm: str, task: str, seeds: int, variant: Variant | None = None
) -> tuple[TrainConfig, Budget]:
    """The config a cell trains and its budget: the preset's."""
    arm = {} if variant is None else {**variant.settings, "switches": variant.switches}
    overrides = {**preset.overrides(algorithm), "seeds": seeds, "seed": TRAIN_SEED, "switches": "", **arm}
    steps, source = requested_budget(preset, make_config(algorithm, task, **overrides))
    config = make_config(algorithm, task, **{**overrides, "total_steps": steps})
    scoring_config(config, {} if variant is None else variant.evaluation)  # a refused option fails before training
    return config, Budget(env_steps=steps, requested=steps, source=source)


# --- cells -------------------------------------------------------------------------------------


@dataclasses.dataclass
class Cell:
    """One (algorithm, environment task) run of the grid and where it stands."""

    algorithm: str
    column: str
    task: str
    directory: Path
    config: TrainConfig
    budget: Budget
    preset: Preset
    status: str = "new"  # new | partial | done
    done_steps: int = 0  # per seed, from the run's metrics
    estimate_s: float | None = None
    estimate_from: str = ""
    metrics: list[dict] = dataclasses.field(default_factory=list)  # a started run's metrics.jsonl
    variant: Variant | None = None  # an ablation preset's arm; its cell's directory is <task>.<arm>
    adopts_from: Path | None = None  # a new cell's twin: another preset's finished run with its settings
    adopts_record: bool = False  # adopts_from is that run's raw copy in the record, not a run directory

    @property
    def evaluation(self) -> dict[str, Any]:
        """The arm's evaluation-only settings (empty: the cell acts as it trained)."""
        return {} if self.variant is None else self.variant.evaluation

    @property
    def total_steps(self) -> int:
        """Env steps per seed the run will have trained (whole updates)."""
        return self.config.num_updates * self.config.steps_per_update

    def record(self) -> dict[str, Any]:
        """cell.json: what the table needs beside config.json and eval.json."""
        arm = (
            {}
            if self.variant is None
            else {
                "variant": self.variant.name,
                "paper_variant": self.variant.paper,
                "switches": self.variant.switches,
                "settings": self.variant.settings,
                **({"evaluation": self.evaluation} if self.evaluation else {}),
            }
        )
        adopted = (
            {} if self.adopts_from is None else {"adopted_from": f"{self.preset.adopts}/{self.algorithm}/{self.task}"}
        )
        if self.adopts_record:
            adopted[RECORD_FIELD] = str(self.adopts_from)
        return {
            "preset": self.preset.name,
            "algorithm": self.algorithm,
            "column": self.column,
            "task": self.task,
            "budget": dataclasses.asdict(self.budget),
            "eval_seed": REPORT_EVAL_SEED,
            "protocol": self.preset.protocol,
            **arm,
            **adopted,
        }


def _settings_differ(cell: Cell, config: TrainConfig) -> list[str]:
    """The settings in which the cell's own run, made with `config`, differs from the cell's. A
    smaller budget alone is no difference: the run trained when the table capped budgets to a
    wall time, and it stays the cell's, at its own budget (`_take_run_budget`), so that no run
    is stranded or trained over."""
    stored, wanted = config.to_json(), cell.config.to_json()
    differ = sorted(k for k in set(stored) | set(wanted) if stored.get(k) != wanted.get(k))
    return [] if differ == ["total_steps"] and config.total_steps <= cell.budget.requested else differ


def _take_run_budget(cell: Cell, config: TrainConfig) -> None:
    """Give the cell the budget of its own run (one `_settings_differ` found equal to the cell's
    but for a smaller budget)."""
    if config.total_steps != cell.config.total_steps:
        cell.config = config
        cell.budget = dataclasses.replace(cell.budget, env_steps=config.total_steps)


def _continues(cell: Cell, config: TrainConfig) -> bool:
    """Whether a run made with `config` is the cell's (`_settings_differ`); if so the cell takes
    its budget."""
    if _settings_differ(cell, config):
        return False
    _take_run_budget(cell, config)
    return True


def _check_same_config(cell: Cell) -> None:
    """A started run must have the cell's settings, except a smaller budget (`_settings_differ`),
    which the cell then takes over."""
    config = checkpoint.read_config(cell.directory)
    differ = _settings_differ(cell, config)
    if differ:
        stored, wanted = config.to_json(), cell.config.to_json()
        changes = ", ".join(f"{k}: {stored.get(k)!r} there, {wanted.get(k)!r} now" for k in differ)
        raise ValueError(
            f"{cell.directory} holds a run made with other settings ({changes}); "
            "choose another --runs-dir or remove that directory"
        )
    _take_run_budget(cell, config)


def own_copy(cell: Cell) -> dict | None:
    """The cell.json of this cell's copy of a raw copy in its directory (`files.record_copy`), or None."""
    return record_copy(
        cell.directory, (cell.preset.name, cell.algorithm, cell.task, cell.variant and cell.variant.name)
    )


def _finished_elsewhere(cell: Cell) -> bool:
    """Whether the cell's directory holds its own files but no checkpoints (trained on another
    machine, copied back without them: `files.own_files`) with the cell's settings. They must be a
    finished run (`files.check_finished_without_checkpoints`), or the cell is refused."""
    owner = (cell.preset.name, cell.algorithm, cell.task, cell.variant and cell.variant.name)
    if own_files(cell.directory, owner) is None or not (cell.directory / checkpoint.CONFIG_FILE).is_file():
        return False
    try:
        if not _continues(cell, checkpoint.read_config(cell.directory)):
            return False  # another run's files where this cell goes: refused as such (`new_cell_leftovers`)
    except ValueError:
        return False
    check_finished_without_checkpoints(cell.directory, cell.config, expected_episodes(cell.task, cell.preset.protocol))
    return True


def cell_state(cell: Cell) -> None:
    """Fill in the cell's status and the env steps per seed its run has done. A new cell's
    directory must hold nothing the table did not make (`files.new_cell_leftovers`). A cell copied
    from a raw copy (no checkpoints) is done once its eval.json, which the copy writes last, is
    there; before that it is new, and running it completes the copy. A cell's own finished files
    back without checkpoints are done (`_finished_elsewhere`). A done cell scored acting otherwise
    than its arm now asks is refused (`scoring.check_scored_as`)."""
    if (copied := own_copy(cell)) is not None:
        if (cell.directory / checkpoint.CONFIG_FILE).is_file():
            _check_same_config(cell)
        cell.status, cell.done_steps = "new", 0
        if (cell.directory / EVAL_FILE).is_file():
            episodes = expected_episodes(cell.task, cell.preset.protocol)
            if not eval_is_valid(cell.directory / EVAL_FILE, cell.config.seeds, episodes):
                raise ValueError(
                    f"{cell.directory / EVAL_FILE} is not a finished result of this cell, and the cell, "
                    f"copied from {copied[RECORD_FIELD]}, has no checkpoints to evaluate again: move "
                    "that directory away"
                )
            cell.status, cell.done_steps = "done", cell.total_steps
            check_scored_as(cell.directory, cell.evaluation)
        return
    if checkpoint.latest_chunk(cell.directory) is None:
        cell.status, cell.done_steps = "new", 0
        if _finished_elsewhere(cell):
            cell.status, cell.done_steps = "done", cell.total_steps
            check_scored_as(cell.directory, cell.evaluation)
            return
        new_cell_leftovers(cell.directory, lambda config: _continues(cell, config))
        return
    _check_same_config(cell)
    if eval_is_valid(cell.directory / EVAL_FILE, cell.config.seeds, expected_episodes(cell.task, cell.preset.protocol)):
        cell.status, cell.done_steps = "done", cell.total_steps
        check_scored_as(cell.directory, cell.evaluation)
        return
    records = checkpoint.read_metrics_lines(cell.directory / checkpoint.METRICS_FILE)
    last_chunk = checkpoint.latest_chunk(cell.directory)
    cell.metrics = [r for r in records if r["chunk"] <= last_chunk]
    cell.status, cell.done_steps = "partial", (cell.metrics[-1]["env_steps"] if cell.metrics else 0)


def find_twin(cell: Cell, runs_dir: str | Path, results_dir: str | Path | None = None) -> Path | None:
    """The finished run of the preset `cell.preset.adopts` with the cell's settings and protocol
    (in `<runs_dir>/<that preset>/<algorithm>/<task>/`), else, with `results_dir`, that run's raw
    copy there (`record_twin`; then `cell.adopts_record`), which the cell takes over instead of
    training the same thing again; None where there is none. An arm scored acting otherwise
    (`Cell.evaluation`) takes a run only: a raw copy has no params to score again."""
    if cell.preset.adopts is None:
        return None
    twin = _run_twin(cell, runs_dir)
    if twin is None and results_dir is not None and not cell.evaluation:  # a raw copy has no policy to score again
        path = record_path(results_dir, cell.preset.adopts, cell.algorithm, cell.task)
        cell.adopts_record = record_twin(cell, path) is not None
        twin = path if cell.adopts_record else None
    return twin


def _same_settings(cell: Cell, config: TrainConfig) -> bool:
    """Whether another preset's run made with `config` is the cell's twin: every setting the
    same, budget included (a twin at a smaller budget would set the arms of an ablation against
    a base that trained less than they do)."""
    return config.to_json() == cell.config.to_json()


def record_twin(cell: Cell, path: Path) -> tuple[TrainConfig, dict] | None:
    """The config and raw copy at `path` where it is the cell's twin (`files.read_record`: a
    damaged one is a `ValueError` naming it)."""
    return read_record(
        path, lambda config: _same_settings(cell, config), expected_episodes(cell.task, cell.preset.protocol)
    )


def _run_twin(cell: Cell, runs_dir: str | Path) -> Path | None:
    source = Path(runs_dir) / cell.preset.adopts / cell.algorithm / cell.task
    if checkpoint.latest_chunk(source) is None:
        return None
    try:
        config = checkpoint.read_config(source)
    except (OSError, ValueError):  # another preset's run this code no longer reads: train instead
        return None
    episodes = expected_episodes(cell.task, cell.preset.protocol)
    if not eval_is_valid(source / EVAL_FILE, config.seeds, episodes) or not _same_settings(cell, config):
        return None
    return source


def estimate(cell: Cell) -> None:
    """Seconds of training left for the cell, and where the figure comes from: a started run's
    own rate (its metrics.jsonl); None for a cell that has not started, as nothing else measures
    its rate. Evaluation is not counted."""
    if cell.status == "done":
        cell.estimate_s, cell.estimate_from = 0.0, "finished"
        return
    if cell.adopts_from is not None:
        twin = f"the record {cell.adopts_from}" if cell.adopts_record else cell.adopts_from
        cell.estimate_s, cell.estimate_from = 0.0, f"adopts {twin}, finished with the same settings"
        if cell.evaluation:  # the adopted policy is scored again, acting with the arm's settings
            cell.estimate_s, cell.estimate_from = None, cell.estimate_from + ", scored again: unknown"
        return
    records = cell.metrics
    if not records or records[-1]["wall_s"] <= 0:
        cell.estimate_s, cell.estimate_from = None, "unknown: not started"
        return
    seeds = cell.config.seeds
    rate = records[-1]["env_steps"] * seeds / records[-1]["wall_s"]
    cell.estimate_s = (cell.total_steps - cell.done_steps) * seeds / rate
    cell.estimate_from = f"this run's metrics.jsonl: {rate:,.0f} steps/s over {len(records)} chunks, training only"


def make_plan(
    preset: Preset,
    algorithms,
    tasks,
    seeds: int | None,
    runs_dir: str | Path,
    arms=None,
    results_dir: str | Path | None = None,
) -> list[Cell]:
    """Every cell of the grid (algorithms x tasks, x an ablation's arms, or the `arms` named), with
    its config, budget, status and estimate. `results_dir`: where the record's raw copies are,
    for twins no run of `runs_dir` holds (`find_twin`; None: runs only)."""
    algorithms = list(dict.fromkeys(algorithms))  # a cell named twice is one cell, planned and run once
    variants = preset.variants
    if arms is not None:
        names = [v.name for v in preset.variants]
        unknown = [a for a in arms if a not in names]
        if not names or unknown or not arms:
            wrong = f"has no arm(s) {unknown or list(arms)}" if arms else "needs at least one arm named"
            raise ValueError(
                f"preset {preset.name!r} {wrong}; its arms: "
                f"{', '.join(names) if names else 'none (it is not an ablation)'}"
            )
        variants = tuple(v for v in preset.variants if v.name in arms)
    for algorithm in algorithms:
        if algorithm not in ALGORITHMS:
            raise ValueError(f"unknown algorithm {algorithm!r}; allowed: {', '.join(ALGORITHMS)}")
        config_class(algorithm)

    def cell(algorithm, column, task, variant) -> Cell:
        config, budget = cell_config(preset, algorithm, task, preset.seeds if seeds is None else seeds, variant)
        name = task if variant is None else f"{task}.{variant.name}"
        return Cell(
            algorithm=algorithm,
            column=column,
            task=task,
            config=config,
            budget=budget,
            preset=preset,
            directory=Path(runs_dir) / preset.name / algorithm / name,
            variant=variant,
        )

    cells = [
        cell(algorithm, column, task, variant)
        for algorithm in algorithms
        for column, task in expand_tasks(tasks)
        for variant in ([v for v in variants if task in v.tasks] if variants else [None])
    ]
    if variants and not cells:
        chosen = "arm" if arms is None else "arm named in --arms"
        listing = "; ".join(f"{v.name}: {', '.join(v.tasks)}" for v in variants)
        raise ValueError(f"no {chosen} of preset {preset.name!r} runs on {', '.join(tasks)}; their tasks: {listing}")
    for cell in cells:
        cell_state(cell)
        if cell.status == "new":
            cell.adopts_from = find_twin(cell, runs_dir, results_dir)
            if not cell.adopts_record and (copied := own_copy(cell)) is not None:
                raise ValueError(
                    f"{cell.directory} holds a copy of {copied[RECORD_FIELD]} cut short, which this plan "
                    "does not adopt (another --results-dir, or the record changed): move that directory away"
                )
            if cell.evaluation and cell.adopts_from is None:
                raise ValueError(missing_run(cell, runs_dir))
        estimate(cell)
    return cells
