"""A finished table cell's copied files, made by hand, for the report and README tests."""

from __future__ import annotations

from snac_jax.evaluation import REPORT_EVAL_SEED


def cell_files(
    algorithm: str, task: str, means: list[float], steps: int, below: bool = False, walls: tuple[float, ...] = ()
) -> dict:
    """One copied cell; `below`: trained at half the budget requested (as under the wall-time cap
    the table once had); `walls`: its curve's cumulative wall_s per chunk (none: no curve kept)."""
    return {
        "config": {"algorithm": algorithm, "task": task, "seeds": len(means), "total_steps": steps},
        "eval": {f"{task} (seed {i})": {"mean": m, "seed": REPORT_EVAL_SEED} for i, m in enumerate(means)},
        "cell": {
            "budget": {
                "env_steps": steps,
                "requested": 2 * steps if below else steps,
                "source": "test",
            }
        },
        "metrics": [{"chunk": i, "wall_s": w} for i, w in enumerate(walls)],
    }


def write_cell(
    directory,
    *,
    algorithm: str = "ppo",
    task: str = "1d-static-sin",
    preset: str = "smoke",
    means: tuple[float, ...] = (0.5, 0.7),
    episodes: int = 2,
) -> dict:
    """A finished cell's files on disk, written by hand as `snac table` writes them (config.json,
    cell.json, eval.json scored with the reporting key, metrics.jsonl); returns their contents."""
    import json
    from pathlib import Path

    from agents.training.registry import make_config
    from snac_jax.paper import paper_column

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    config = make_config(algorithm, task, seeds=len(means), total_steps=2048, num_envs=16, rollout_steps=8).to_json()
    cell = {
        "preset": preset,
        "algorithm": algorithm,
        "column": paper_column(task),
        "task": task,
        "budget": {"env_steps": 2048, "requested": 2048, "source": "test"},
        "eval_seed": REPORT_EVAL_SEED,
        "protocol": {"static_episodes": episodes, "episodes_per_test_design": 1},
    }
    row = {
        "min": 0.1,
        "std": 0.1,
        "episodes": episodes,
        "mean_length": 40.0,
        "mean_bricks_used": 3.0,
        "mean_return": 1.0,
        "per_design": {},
        "seed": REPORT_EVAL_SEED,
        "wall_s": 1.0,
    }
    evaluation = {
        f"{task} (seed {i})": {"task": f"{task} (seed {i})", "mean": m, **row, "ci95": [m - 0.05, m + 0.05]}
        for i, m in enumerate(means)
    }
    files = {"config.json": config, "cell.json": cell, "eval.json": evaluation}
    for name, content in files.items():
        (directory / name).write_text(json.dumps(content, indent=2) + "\n")
    (directory / "metrics.jsonl").write_text(json.dumps({"chunk": 0, "env_steps": 2048, "wall_s": 3.0}) + "\n")
    return files


def raw_copy_text(directory) -> str:
    """The raw copy the report would write of the cell in `directory`, spliced from its files'
    texts as they are (damaged or not): {"cell", "config", "eval", "curve"}."""
    from pathlib import Path

    directory = Path(directory)
    parts = [
        f'"{key}": ' + (directory / name).read_text().strip()
        for key, name in (("cell", "cell.json"), ("config", "config.json"), ("eval", "eval.json"))
    ]
    metrics = directory / "metrics.jsonl"
    lines = [line for line in metrics.read_text().splitlines() if line.strip()] if metrics.is_file() else []
    return "{" + ", ".join(parts) + ', "curve": [' + ", ".join(lines) + "]}\n"


def unpack_raw(path, directory) -> None:
    """A raw copy (`bench/results/table/.../<cell>.json`) written back as a cell directory's files
    (config.json, cell.json, eval.json, metrics.jsonl), as a runs directory holds them."""
    import json
    from pathlib import Path

    record, directory = json.loads(Path(path).read_text()), Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for key, name in (("cell", "cell.json"), ("config", "config.json"), ("eval", "eval.json")):
        (directory / name).write_text(json.dumps(record[key], indent=2) + "\n")
    (directory / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in record["curve"]))


def write_record(results, cell, means=(0.5, 0.7), episodes: int = 2, seed: int = REPORT_EVAL_SEED):
    """The raw copy the report would keep of `cell` finished (4 chunks, scored over `episodes`
    episodes with evaluation key `seed`), written by hand: {"cell", "config", "eval", "curve"}."""
    from pathlib import Path

    from agents.table.files import raw_text

    row = {
        "min": 0.1,
        "std": 0.1,
        "episodes": episodes,
        "mean_length": 40.0,
        "mean_bricks_used": 3.0,
        "mean_return": 1.0,
        "per_design": {},
        "seed": seed,
        "wall_s": 1.0,
    }
    evaluation = {
        f"{cell.task} (seed {i})": {"task": f"{cell.task} (seed {i})", "mean": m, **row, "ci95": [m - 0.05, m + 0.05]}
        for i, m in enumerate(means)
    }
    curve = [
        {
            "chunk": i,
            "env_steps": 512 * (i + 1),
            "wall_s": 2.0 * (i + 1),
            "iou": [0.1 * i, 0.2 * i],
            "return": [1.0, None],
        }
        for i in range(4)
    ]
    path = Path(results) / "table" / cell.preset.name / cell.algorithm / f"{cell.task}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        raw_text(
            {
                "cell": {**cell.record(), "eval_seed": seed},
                "config": cell.config.to_json(),
                "eval": evaluation,
                "metrics": curve,
            }
        )
    )
    return path
