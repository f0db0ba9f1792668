"""Measured training rates and evaluation times (`rates.json`, written by `bench/table_rates.py`)
that `snac table` estimates a cell's wall time and its wall-capped budget from."""

from __future__ import annotations

import json
from pathlib import Path

from snac_jax.tasks import TASKS, task_spec

RATES_FILE = Path(__file__).parent / "rates.json"


def load_rates(path: str | Path = RATES_FILE) -> dict[str, dict[str, dict]]:
    path = Path(path)
    return json.loads(path.read_text()) if path.is_file() else {}


def _kin(task: str) -> list[str]:
    """Tasks whose measured rate stands in for `task`'s, nearest first: itself, the same
    dimension and kind (static / dynamic), then the same dimension."""
    spec = task_spec(task)
    same_kind = [t for t in TASKS if t != task and task_spec(t).dim == spec.dim and task_spec(t).dynamic == spec.dynamic]
    same_dim = [t for t in TASKS if t not in same_kind and t != task and task_spec(t).dim == spec.dim]
    return [task, *same_kind, *same_dim]


def measured(rates: dict, algorithm: str, task: str, field: str) -> tuple[float, str] | None:
    """`(value, the task whose entry gave it)` of `field` for `algorithm`: the nearest kin's entry."""
    entries = rates.get(algorithm, {})
    for near in _kin(task):
        if field in entries.get(near, {}):
            return float(entries[near][field]), near
    return None
