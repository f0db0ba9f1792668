"""Aggregate scores over seeds and tasks as Agarwal et al. (2021, "Deep RL at the edge of the
statistical precipice") recommend, with the estimators of their `rliable` library written out
in numpy/scipy (`rliable` itself does not import beside this project's pandas):

- the interquartile mean (IQM): the mean of the middle half of all runs of all tasks, robust to
  a few outlying runs yet using half of the data, unlike the median;
- the stratified bootstrap: each task's runs (seeds) are resampled with replacement,
  independently per task, and the statistic recomputed; the 2.5th and 97.5th percentiles of the
  resampled statistics are the 95% interval. With one task it is the ordinary bootstrap over
  seeds, which is how one cell of the table gets its interval.

Scores are arrays of shape (runs, tasks); every task has the same number of runs.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import stats

DEFAULT_REPS = 10_000
BOOTSTRAP_SEED = 0
"""The rng seed of every interval the table reports, so that a page is rebuilt to the byte."""
CONFIDENCE = 0.95


def iqm(scores) -> float:
    """Interquartile mean of all entries: a quarter cut from each end, the rest averaged."""
    return float(stats.trim_mean(np.asarray(scores, dtype=np.float64), proportiontocut=0.25, axis=None))


def mean_of_runs(resampled: np.ndarray) -> np.ndarray:
    """Per bootstrap replicate (reps, runs, tasks) -> (reps,): the mean over runs and tasks."""
    return resampled.mean(axis=(1, 2))


def iqm_of_runs(resampled: np.ndarray) -> np.ndarray:
    """Per bootstrap replicate (reps, runs, tasks) -> (reps,): the IQM over runs and tasks."""
    return stats.trim_mean(resampled.reshape(len(resampled), -1), proportiontocut=0.25, axis=1)


def _as_runs_by_tasks(scores) -> np.ndarray:
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim == 1:
        scores = scores[:, None]
    if scores.ndim != 2 or scores.size == 0:
        raise ValueError(f"scores must be a non-empty (runs, tasks) array, got shape {scores.shape}")
    if not np.all(np.isfinite(scores)):
        raise ValueError("scores must be finite")
    return scores


def stratified_bootstrap_ci(
    scores,
    statistic: Callable[[np.ndarray], np.ndarray] = mean_of_runs,
    *,
    reps: int = DEFAULT_REPS,
    seed: int = BOOTSTRAP_SEED,
) -> tuple[float, float]:
    """The percentile interval of `statistic` under the stratified bootstrap (runs resampled
    within each task). `scores`: (runs, tasks), or (runs,) for a single task. The same `seed`
    gives the same interval."""
    scores = _as_runs_by_tasks(scores)
    if reps < 1:
        raise ValueError(f"reps must be >= 1, got {reps}")
    runs, tasks = scores.shape
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, runs, size=(reps, runs, tasks))
    resampled = scores[rows, np.arange(tasks)[None, None, :]]
    values = statistic(resampled)
    alpha = (1 - CONFIDENCE) / 2
    low, high = np.percentile(values, [100 * alpha, 100 * (1 - alpha)])
    return float(low), float(high)


def bootstrap_record(reps: int) -> dict:
    """How the table's intervals were made, as table.json records it."""
    return {"reps": reps, "confidence": CONFIDENCE, "interval": "percentile", "seed": BOOTSTRAP_SEED}


def cell_summary(seed_scores, *, reps: int = DEFAULT_REPS, seed: int = BOOTSTRAP_SEED) -> dict:
    """One cell of the table: the mean over seeds, its 95% bootstrap interval across seeds and
    the per-seed values."""
    values = _as_runs_by_tasks(seed_scores)[:, 0]
    return {
        "mean": float(values.mean()),
        "ci95": list(stratified_bootstrap_ci(values, mean_of_runs, reps=reps, seed=seed)),
        "seeds": [float(v) for v in values],
    }


def iqm_summary(scores, *, reps: int = DEFAULT_REPS, seed: int = BOOTSTRAP_SEED) -> dict:
    """One learner over tasks: the IQM of its (runs, tasks) scores and its 95% stratified
    bootstrap interval."""
    scores = _as_runs_by_tasks(scores)
    return {
        "iqm": iqm(scores),
        "ci95": list(stratified_bootstrap_ci(scores, iqm_of_runs, reps=reps, seed=seed)),
        "tasks": scores.shape[1],
        "runs": scores.shape[0],
    }


def difference_summary(scores, baseline, *, reps: int = DEFAULT_REPS, seed: int = BOOTSTRAP_SEED) -> dict:
    """An ablation's effect: the mean over seeds of `scores` minus that of `baseline`, with the
    95% percentile interval of the difference when each side's seeds are resampled on their own.
    No pairing is assumed: the arms share training seeds, but in different worlds they diverge
    from the first step."""
    scores, baseline = _as_runs_by_tasks(scores)[:, 0], _as_runs_by_tasks(baseline)[:, 0]
    if reps < 1:
        raise ValueError(f"reps must be >= 1, got {reps}")
    rng = np.random.default_rng(seed)  # the arm's seeds resampled first, then the base's
    arm, base = (v[rng.integers(0, len(v), size=(reps, len(v)))].mean(axis=1) for v in (scores, baseline))
    low, high = np.percentile(arm - base, [2.5, 97.5])
    return {"delta": float(scores.mean() - baseline.mean()), "ci95": [float(low), float(high)]}
