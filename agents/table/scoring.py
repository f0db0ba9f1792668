"""An ablation arm that changes only how its trained policy acts when scored (`Variant.evaluation`,
e.g. `safe_drops` on a policy trained without it): the config its greedy policy is scored with
(only a learner's `acting_options`), the check that a finished cell was scored with the arm's
settings, and its adoption kept across a resume. Such an arm trains as the base arm does, so it
takes over the finished run the base arm adopts, checkpoints and all (`plan.find_twin`; the plan
refuses it where that run is not there), and scores those params again."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from agents.table.files import CELL_FILE, RECORD_FIELD
from agents.training import schemas
from agents.training.config import TrainConfig
from agents.training.registry import make_config


def scoring_config(config: TrainConfig, evaluation: dict[str, Any]) -> TrainConfig:
    """The config whose greedy policy a cell scores: its training config with the arm's
    evaluation-only settings, validated as any config is (an option the learner refuses, such
    as `safe_drops` without the obstacle rule, is its one-line error)."""
    if not evaluation:
        return config
    other = sorted(set(evaluation) - set(config.acting_options))
    if other:
        allowed = ", ".join(config.acting_options) or "none"
        raise ValueError(
            f"{config.algorithm} cannot act with {other} at evaluation: an option there may change only how "
            f"the trained policy acts, not its network, its world or its training; {config.algorithm}'s: "
            f"{allowed}"
        )
    trained = {k: v for k, v in config.to_json().items() if k not in ("algorithm", "task")}
    return make_config(config.algorithm, config.task, **{**trained, **evaluation})


def check_scored_as(directory: Path, evaluation: dict[str, Any]) -> None:
    """A finished cell must have been scored acting with its arm's evaluation-only settings
    (its cell.json's `evaluation`), as its run must have trained with the cell's settings."""
    path = directory / CELL_FILE
    scored = schemas.load(path, schemas.CELL_JSON).get("evaluation", {}) if path.is_file() else {}
    if scored != evaluation:
        raise ValueError(
            f"{directory} was scored acting with {scored or 'its training settings'}, the arm now asks "
            f"{evaluation or 'its training settings'}; move that directory away to score the run again"
        )


def adoption_kept(directory: Path, record: dict[str, Any]) -> dict[str, Any]:
    """A cell's record (`Cell.record`) with the adoption its own cell.json in `directory` names
    where this plan no longer knows it: a cell that took over another run and was stopped
    before it was scored is planned as a partial run, and is still that run."""
    path = directory / CELL_FILE
    if not path.is_file():
        return record
    before = schemas.load(path, schemas.CELL_JSON)
    kept = {k: before[k] for k in ("adopted_from", RECORD_FIELD) if k in before and k not in record}
    return {**record, **kept}


def missing_run(cell, runs_dir) -> str:
    """The error of an arm scored acting otherwise (`plan.Cell`) whose base run is not there to
    take over: it has no params of its own to score, and training some would not be the base's."""
    preset = cell.preset
    return (
        f"arm {cell.variant.name!r} of preset {preset.name!r} scores the policy of {preset.adopts}/{cell.algorithm}/"
        f"{cell.task} again: that run, finished with its checkpoints and this arm's training settings, is not "
        f"under {runs_dir}; train it first (snac table --preset {preset.adopts} --tasks {cell.task}) or leave the "
        "arm out (--arms)"
    )
