"""Trained policies back from run directories: what `snac eval --checkpoint DIR` and `snac render
--checkpoint DIR` score and draw. The `snac_jax` library reaches this module only through the
`snac_jax.checkpoint_loaders` entry point (see pyproject.toml), never by importing `agents`."""

from __future__ import annotations

from pathlib import Path

import jax

from agents.checkpoint import read_config, restore_state
from agents.driver import initial_state
from agents.registry import build_algorithm


def load_trained(directory: str | Path):
    """`(algorithm object, runner state with a leading seed axis, chunk)` of a run directory."""
    config = read_config(directory)
    algorithm = build_algorithm(config)
    like = initial_state(algorithm)
    chunk, state = restore_state(directory, like)
    return algorithm, state, chunk


def checkpoint_policy(env, checkpoint: str | Path, seed_index: int = 0):
    """Policy builder for the evaluator: the greedy policy of run `checkpoint`, seed `seed_index`.

    `env` must be the task the run trained on (the evaluator passes each environment task)."""
    algorithm, state, _ = load_trained(checkpoint)
    if env.config.task_id != algorithm.config.task:
        raise ValueError(
            f"checkpoint {checkpoint} was trained on {algorithm.config.task!r}, cannot evaluate it on {env.config.task_id!r}"
        )
    seeds = algorithm.config.seeds
    if not 0 <= seed_index < seeds:
        raise ValueError(f"seed_index must be in 0..{seeds - 1} for {checkpoint}, got {seed_index}")
    params = jax.tree.map(lambda x: x[seed_index], state.params)
    return algorithm.policy(params)


def checkpoint_builder(directory: str | Path):
    """For `snac eval --checkpoint DIR`: `(builder(env) -> Policy, the run's task, the paper row
    of its algorithm)`. The 1D static shapes are scored on the shape the run trained on."""
    config = read_config(directory)

    def builder(env, **options):
        return checkpoint_policy(env, directory, **options)

    return builder, config.task, getattr(config, "paper_method", config.algorithm)
