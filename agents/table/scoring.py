"""An ablation arm that changes only how its trained policy acts when scored (`Variant.evaluation`,
e.g. `safe_drops` on a policy trained without it): the config its greedy policy is scored with,
and the check that a finished cell was scored with the arm's settings. Such an arm trains as the
base arm does, so it takes over the base's run (`plan.find_twin`) and scores that policy again."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from agents.config import TrainConfig
from agents.registry import make_config
from agents.table.files import CELL_FILE


def scoring_config(config: TrainConfig, evaluation: dict[str, Any]) -> TrainConfig:
    """The config whose greedy policy a cell scores: its training config with the arm's
    evaluation-only settings, validated as any config is (an option the learner refuses, such
    as `safe_drops` without the obstacle rule, is its one-line error)."""
    if not evaluation:
        return config
    trained = {k: v for k, v in config.to_json().items() if k not in ("algorithm", "task")}
    return make_config(config.algorithm, config.task, **{**trained, **evaluation})


def check_scored_as(directory: Path, evaluation: dict[str, Any]) -> None:
    """A finished cell must have been scored acting with its arm's evaluation-only settings
    (its cell.json's `evaluation`), as its run must have trained with the cell's settings."""
    path = directory / CELL_FILE
    scored = json.loads(path.read_text()).get("evaluation", {}) if path.is_file() else {}
    if scored != evaluation:
        raise ValueError(f"{directory} was scored acting with {scored or 'its training settings'}, the arm now asks "
                         f"{evaluation or 'its training settings'}; move its eval.json away to score it again")
