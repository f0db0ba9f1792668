"""Test helpers: run any env through a jitted random episode and collect what it did; check a
two-seed run's command-line evaluation."""

from __future__ import annotations

import re
import subprocess
import sys
from functools import partial

import jax
import jax.numpy as jnp


@partial(jax.jit, static_argnames=("env", "num_steps"))
def random_episode(key, env, params, num_steps: int):
    """One env, uniform-random actions, `num_steps` auto-resetting steps.

    Returns the per-step (obs, reward, terminated, truncated, info, state) stacked over time.
    """
    key_reset, key_run = jax.random.split(key)
    obs, state = env.reset(key_reset, params)

    def body(state, step_key):
        key_action, key_step = jax.random.split(step_key)
        action = jax.random.randint(key_action, (), 0, env.num_actions)
        obs, next_state, reward, terminated, truncated, info = env.step(key_step, state, action, params)
        return next_state, (obs, action, reward, terminated, truncated, info, state)

    _, trajectory = jax.lax.scan(body, state, jax.random.split(key_run, num_steps))
    return obs, trajectory


def scripted_actions(env, moves_and_drops):
    """Expand [(action, repeat), ...] into a flat action list."""
    return [a for action, repeat in moves_and_drops for a in [action] * repeat]


def batch_index(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def as_numpy(tree):
    return jax.tree.map(lambda x: jnp.asarray(x), tree)


def result_rows(stdout: str, task: str) -> dict[int | None, tuple[str, ...]]:
    """The measured cells (episodes, mean, interval, min, std, length, bricks; not the paper's
    columns) of each of a result table's rows for `task`, by training seed (None for a row that
    names none, as `snac eval` prints one seed's row)."""
    rows = re.findall(rf"^\| {re.escape(task)}(?: \(seed (\d+)\))? \|(.*)\|$", stdout, flags=re.M)
    cells = {int(seed) if seed else None: tuple(c.strip() for c in row.split("|")) for seed, row in rows}
    return {seed: row[:5] + row[-2:] for seed, row in cells.items()}


def check_each_seed_evaluates_from_the_checkpoint(train_stdout: str, out, task: str, env: dict) -> None:
    """After `snac train ... --seeds 2 --out out`: the run printed a row for each seed, the two
    differ, and `snac eval --checkpoint out` scores the first seed by default and the second with
    `--seed-index 1`, each as the run did (same parameters, same evaluation key)."""
    trained = result_rows(train_stdout, task)
    assert set(trained) == {0, 1} and trained[0] != trained[1], train_stdout[-3000:]
    for index, flag in ((0, []), (1, ["--seed-index", "1"])):
        again = subprocess.run([sys.executable, "-m", "snac_jax.cli", "eval", "--checkpoint", str(out), "--episodes", "2",
                                *flag], capture_output=True, text=True, env=env, timeout=600)
        assert again.returncode == 0, again.stderr[-3000:]
        assert result_rows(again.stdout, task) == {None: trained[index]}, (index, again.stdout[-2000:])
