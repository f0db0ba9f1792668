"""The raw results of `snac table`: each finished cell's small JSON files (`config.json`,
`eval.json`, `cell.json`, and its learning curve `metrics.jsonl`; never checkpoints), copied from
the runs directory to `bench/results/table/<preset>/<algorithm>/<cell>/` and read back from there,
so that every table, curve and training wall time can be rebuilt from the repository. Cells copied
before the curves were kept have no `metrics.jsonl`; their wall times are on the learners' pages."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from agents import checkpoint
from agents.table.plan import CELL_FILE, EVAL_FILE, eval_is_valid, expected_episodes

RAW_FILES = (checkpoint.CONFIG_FILE, EVAL_FILE, CELL_FILE)
OPTIONAL_RAW_FILES = (checkpoint.METRICS_FILE,)


def _finished(directory: Path) -> bool:
    try:
        config = json.loads((directory / checkpoint.CONFIG_FILE).read_text())
        cell = json.loads((directory / CELL_FILE).read_text())
    except (OSError, ValueError):
        return False
    episodes = expected_episodes(cell["task"], cell["protocol"])
    return eval_is_valid(directory / EVAL_FILE, config["seeds"], episodes, seed=cell["eval_seed"])


def collect(runs_dir: str | Path, results_dir: str | Path, preset: str) -> list[Path]:
    """Copy every finished cell's JSON files under `results_dir/table/<preset>/`; returns the
    cells copied."""
    source, target = Path(runs_dir) / preset, Path(results_dir) / "table" / preset
    copied = []
    for directory in sorted(p.parent for p in source.glob(f"*/*/{EVAL_FILE}")):
        if not _finished(directory):
            continue
        destination = target / directory.relative_to(source)
        destination.mkdir(parents=True, exist_ok=True)
        for name in RAW_FILES + tuple(n for n in OPTIONAL_RAW_FILES if (directory / n).is_file()):
            shutil.copyfile(directory / name, destination / name)
        copied.append(destination)
    return copied


def load_raw(results_dir: str | Path, preset: str) -> dict[str, dict[str, dict]]:
    """algorithm -> cell (its directory's name: the task, and an ablation's arm) -> {"config", "eval",
    "cell", "metrics"} of the copied cells ("metrics": the curve's records, empty where not copied)."""
    raw: dict[str, dict[str, dict]] = {}
    for directory in sorted(p.parent for p in (Path(results_dir) / "table" / preset).glob(f"*/*/{EVAL_FILE}")):
        if _finished(directory):
            files = {name.split(".")[0]: json.loads((directory / name).read_text()) for name in RAW_FILES}
            files["metrics"] = checkpoint.read_metrics_lines(directory / checkpoint.METRICS_FILE)
            raw.setdefault(directory.parent.name, {})[directory.name] = files
    return raw


def seed_means(files: dict) -> list[float]:
    """Per-seed protocol means of one cell, in seed order (eval.json keeps it)."""
    return [float(r["mean"]) for r in files["eval"].values()]


def training_wall_s(cells: list[dict]) -> float | None:
    """Training wall time of one or more cells (a column's shapes run one after another), all
    seeds together, from their curves (the driver's cumulative `wall_s`, resumes included); None
    where a cell's curve was not copied."""
    if any(not c.get("metrics") for c in cells):
        return None
    return round(sum(c["metrics"][-1]["wall_s"] for c in cells), 1)


def budget_record(cells: list[dict]) -> dict[str, Any]:
    """The training budget of one or more cells (a column's shapes): env steps per seed per task,
    what was requested before the wall-time cap, whether any was capped, and why, and the
    training wall time it took."""
    budgets = [c["cell"]["budget"] for c in cells]
    return {
        "env_steps_per_seed": {c["config"]["task"]: c["config"]["total_steps"] for c in cells},
        "requested_per_seed": {c["config"]["task"]: b["requested"] for c, b in zip(cells, budgets)},
        "capped": any(b["capped"] for b in budgets),
        "source": "; ".join(dict.fromkeys(b["source"] for b in budgets)),
        "training_wall_s": training_wall_s(cells),
    }


def _steps(n: int) -> str:
    return f"{n / 1e6:.3g}M" if n >= 1e6 else f"{n / 1e3:.3g}k"


def budget_text(budget: dict) -> str:
    """A budget record as the tables print it: env steps per seed, `*` where capped."""
    steps = sorted(set(budget["env_steps_per_seed"].values()))
    text = _steps(steps[0]) if len(steps) == 1 else f"{_steps(steps[0])}–{_steps(steps[-1])}"
    return text + ("*" if budget["capped"] else "")
