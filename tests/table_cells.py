"""A finished table cell's copied files, made by hand, for the report and README tests."""

from __future__ import annotations

from snac_jax.evaluation import REPORT_EVAL_SEED


def cell_files(algorithm: str, task: str, means: list[float], steps: int, capped: bool = False,
           walls: tuple[float, ...] = ()) -> dict:
    """One copied cell; `walls`: its curve's cumulative wall_s per chunk (none: no curve kept)."""
    return {
        "config": {"algorithm": algorithm, "task": task, "seeds": len(means), "total_steps": steps},
        "eval": {f"{task} (seed {i})": {"mean": m, "seed": REPORT_EVAL_SEED} for i, m in enumerate(means)},
        "cell": {"budget": {"env_steps": steps, "requested": 2 * steps if capped else steps, "capped": capped,
                            "source": "test"}},
        "metrics": [{"chunk": i, "wall_s": w} for i, w in enumerate(walls)],
    }
