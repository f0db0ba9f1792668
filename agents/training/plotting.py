"""`DIR/curve.png`: mean final IoU and mean episode return against env steps, one line per seed,
with the paper's best reinforcement-learning result for the task as a dashed line."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from snac_jax.paper import load_paper_results, paper_column

RL_METHODS = ("dqn", "drqn", "drqn_her", "sac", "ppo", "rainbow")
"""The paper's learned methods (not the human or handcrafted rows)."""


def best_rl_result(task: str, paper: dict | None = None) -> tuple[str, float] | None:
    """`(method, mean IoU)` of the paper's best learned method on `task`, or None if none learned it."""
    paper = load_paper_results() if paper is None else paper
    column = paper_column(task)
    scores = [
        (method, paper["methods"][method][column]["avg"])
        for method in RL_METHODS
        if paper["methods"].get(method, {}).get(column, {}).get("avg") is not None
    ]
    return max(scores, key=lambda s: s[1]) if scores else None


def pyplot():
    """matplotlib's pyplot on the Agg backend: every figure here is written to a file, never shown."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path: str | Path, dpi: int) -> None:
    """Write `fig` to `path` atomically as a PNG, then close it."""
    from snac_jax.atomic import atomic_write

    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=dpi))
    pyplot().close(fig)


def plot_curve(records: list[dict], task: str, title: str, path: str | Path) -> None:
    """Write the learning curve of `records` (metrics.jsonl lines) to `path` atomically."""
    plt = pyplot()
    steps = np.array([r["env_steps"] for r in records], dtype=float)
    fig, (ax_iou, ax_return) = plt.subplots(1, 2, figsize=(11, 4))
    for name, ax, label in (("iou", ax_iou, "mean final IoU"), ("return", ax_return, "mean episode return")):
        values = np.array([r[name] for r in records], dtype=float)  # (chunks, seeds)
        for seed in range(values.shape[1] if values.ndim == 2 else 0):
            ax.plot(steps, values[:, seed], marker=".", label=f"seed {seed}")
        ax.set_xlabel("env steps per seed")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    best = best_rl_result(task)
    if best is not None:
        method, score = best
        ax_iou.axhline(score, linestyle="--", color="k", label=f"paper best RL ({method}, {score:.3f})")
    ax_iou.set_ylim(0, 1)
    ax_iou.legend(loc="lower right", fontsize="small")
    fig.suptitle(title)
    fig.tight_layout()
    save_png(fig, path, dpi=100)
