"""Measured training rates and evaluation times (`rates.json`, written by `bench/table_rates.py`)
that `snac table` estimates a cell's wall time and its wall-capped budget from, and a preset's
protocol's seconds per seed scaled from them (`eval_seconds`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from agents.table.files import expected_episodes
from snac_jax.evaluation import EPISODES_PER_TEST_DESIGN, STATIC_EPISODES
from snac_jax.tasks import TASKS, task_spec

if TYPE_CHECKING:
    from agents.table.presets import Preset

RATES_FILE = Path(__file__).parent / "rates.json"


def load_rates(path: str | Path = RATES_FILE) -> dict[str, dict[str, dict]]:
    path = Path(path)
    return json.loads(path.read_text()) if path.is_file() else {}


def _kin(task: str) -> list[str]:
    """Tasks whose measured rate stands in for `task`'s, nearest first: itself, the same
    dimension and kind (static / dynamic), then the same dimension."""
    spec = task_spec(task)
    same_kind = [
        t for t in TASKS if t != task and task_spec(t).dim == spec.dim and task_spec(t).dynamic == spec.dynamic
    ]
    same_dim = [t for t in TASKS if t not in same_kind and t != task and task_spec(t).dim == spec.dim]
    return [task, *same_kind, *same_dim]


def measured(rates: dict, algorithm: str, task: str, field: str) -> tuple[float, str] | None:
    """`(value, the task whose entry gave it)` of `field` for `algorithm`: the nearest kin's entry."""
    entries = rates.get(algorithm, {})
    for near in _kin(task):
        if field in entries.get(near, {}):
            return float(entries[near][field]), near
    return None


def eval_seconds(rates: dict, algorithm: str, task: str, preset: Preset) -> tuple[float, str] | None:
    """Seconds of the preset's protocol for one seed, and where the figure comes from: measured
    (the full protocol) for the algorithm, else for any algorithm (the protocol's cost is mostly
    the environment's), on the task or its kin, scaled by the episode counts."""
    for source in [algorithm, *sorted(set(rates) - {algorithm})]:
        found = measured(rates, source, task, "eval_s")
        if found is not None:
            seconds, measured_on = found
            full = {"static_episodes": STATIC_EPISODES, "episodes_per_test_design": EPISODES_PER_TEST_DESIGN}
            scale = expected_episodes(task, preset.protocol) / expected_episodes(measured_on, full)
            return seconds * scale, measured_on if source == algorithm else f"{source}'s {measured_on}"
    return None
