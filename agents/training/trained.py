"""Trained policies back from run directories: what `snac eval --checkpoint DIR` and `snac render
--checkpoint DIR` score and draw. The `snac_jax` library reaches this module only through the
`snac_jax.checkpoint_loaders` entry point (see pyproject.toml), never by importing `agents`."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from agents.training import sweep
from agents.training.checkpoint import CHECKPOINT_DIR, read_config, restore_latest
from agents.training.driver import initial_state
from agents.training.registry import build_algorithm


def load_trained(directory: str | Path):
    """`(algorithm object, runner state with a leading run axis, chunk)` of a run directory,
    from its newest checkpoint; the run axis is the seeds, or a sweep's arms x seeds (arm-major).
    A damaged newest checkpoint is an error (scoring the one before would silently score an
    older policy) that says how to repair the run."""
    config = read_config(directory)
    algorithm = build_algorithm(config)
    swept = sweep.load(Path(directory), config)
    if swept is not None:
        sweep.check_arms(Path(directory), config, swept)
    like = initial_state(algorithm, swept=swept)
    chunk, state, notes = restore_latest(directory, like)
    if chunk is None:
        raise ValueError(
            f"{directory}: no checkpoint under {CHECKPOINT_DIR}/ (the run was stopped before its first chunk ended?)"
        )
    if notes:
        raise ValueError(
            f"{notes[0]}; checkpoint {chunk} is intact: `snac train {config.algorithm} --resume {directory}` "
            "recomputes the later chunk(s) from it"
        )
    return algorithm, state, chunk


def _same_stride_noise(params, trained) -> bool:
    """Whether `params` move the robot as the run's world did: the −uncertainty switch lives in
    `EnvParams.stride_probs`, not in `EnvConfig`. The designs differ between a training bank and
    a test design by intent, and `snac render --max-steps` shortens an episode on purpose."""
    return bool(np.array_equal(np.asarray(params.stride_probs), np.asarray(trained.stride_probs)))


def checkpoint_policy(env, checkpoint: str | Path, seed_index: int = 0):
    """Policy builder for the evaluator: the greedy policy of run `checkpoint`, seed `seed_index`.

    `env` must be the task the run trained on (the evaluator passes each environment task);
    that and `seed_index` are checked before the checkpoint is read."""
    config = read_config(checkpoint)
    if env.config.task_id != config.task:
        raise ValueError(
            f"checkpoint {checkpoint} was trained on {config.task!r}, cannot evaluate it on {env.config.task_id!r}"
        )
    trained_env, trained_params = config.scored_world()
    # Other inputs fail deep inside JAX (gps); other rules and the stride noise act silently.
    if env.config != trained_env.config or not _same_stride_noise(env.default_params, trained_params):
        raise ValueError(
            f"checkpoint {checkpoint} was trained with switches {config.switches!r}; build the env with "
            f"them (`snac_jax.make({config.task!r}, **snac_jax.tasks.parse_switches({config.switches!r}))`)"
        )
    swept = sweep.load(Path(checkpoint), config)
    runs = config.seeds * (1 if swept is None else swept.num_arms)
    if not 0 <= seed_index < runs:
        what = "" if swept is None else f" (a sweep: arm a, seed s is index a * {config.seeds} + s)"
        raise ValueError(
            f"the seed index (seed_index, --seed-index) must be in 0..{runs - 1} for {checkpoint}{what}, "
            f"got {seed_index}"
        )
    algorithm, state, _ = load_trained(checkpoint)
    if swept is not None:
        algorithm = build_algorithm(swept.arm_config(config, seed_index // config.seeds))
    params = jax.tree.map(lambda x: x[seed_index], state.params)
    return algorithm.policy(params)


def describe_run_index(directory: str | Path, index: int) -> str:
    """Which policy run index `index` of `directory` is, in words: its training seed, and of a
    sweep its arm and the arm's settings (run `a * seeds + s` is arm a, seed s)."""
    config = read_config(directory)
    swept = sweep.load(Path(directory), config)
    if swept is None:
        return f"training seed index {index}"
    arm, seed = divmod(index, config.seeds)
    if arm >= swept.num_arms:
        return f"run index {index}"  # out of range: `checkpoint_policy` refuses it, naming the range
    return f"arm {arm} ({swept.label(arm)}), training seed index {seed} (run index {index})"


def checkpoint_builder(directory: str | Path):
    """For `snac eval --checkpoint DIR`: `(builder(env) -> Policy, the run's task, the paper row
    of its algorithm, the make overrides it trained with)`. The 1D static shapes are scored on the
    shape the run trained on; a run trained with switches or `max_steps` is scored with them. A
    team run's overrides are `snac_jax.multi.make`'s, `num_robots` among them, and its builder,
    given that team's env, returns the team's `MultiPolicy`. `builder.describe(seed_index)` names
    the policy an index loads (`describe_run_index`)."""
    config = read_config(directory)

    def builder(env, **options):
        return checkpoint_policy(env, directory, **options)

    builder.describe = lambda seed_index: describe_run_index(directory, seed_index)

    overrides = config.env_overrides
    if getattr(config, "robots", None) is not None:  # a team run (agents.learners.ippo): snac_jax.multi.make's count
        overrides = {**overrides, "num_robots": config.robots}
    return builder, config.task, getattr(config, "paper_method", config.algorithm), overrides
