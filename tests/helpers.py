"""Test helpers: run any env through a jitted random episode and collect what it did; check a
two-seed run's command-line evaluation."""

from __future__ import annotations

import json
import subprocess
import sys
from functools import partial
from pathlib import Path

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


def check_each_seed_evaluates_from_the_checkpoint(train_stdout: str, out: Path, task: str, env: dict) -> None:
    """After `snac train ... --seeds 2 --out out`: the run printed a row for each seed, its
    `eval.json` holds a result for each seed, the two differ, and `snac eval --checkpoint out --json` scores the first seed by default
    and the second with `--seed-index 1`, each exactly as the run did (same parameters, same
    evaluation key): every field but the row's name and the wall time."""
    assert f"| {task} (seed 0) |" in train_stdout and f"| {task} (seed 1) |" in train_stdout, train_stdout[-3000:]
    measured = lambda result: {k: v for k, v in result.items() if k not in ("task", "wall_s")}
    trained = {key: measured(result) for key, result in json.loads((out / "eval.json").read_text()).items()}
    assert set(trained) == {f"{task} (seed 0)", f"{task} (seed 1)"}, sorted(trained)
    assert trained[f"{task} (seed 0)"] != trained[f"{task} (seed 1)"]
    for index, flag in ((0, []), (1, ["--seed-index", "1"])):
        path = out / f"eval-again-{index}.json"
        again = subprocess.run(
            [
                sys.executable,
                "-m",
                "snac_jax.cli",
                "eval",
                "--checkpoint",
                str(out),
                "--episodes",
                "2",
                "--json",
                str(path),
                *flag,
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=600,
        )
        assert again.returncode == 0, again.stderr[-3000:]
        result = json.loads(path.read_text())
        assert {key: measured(r) for key, r in result.items()} == {task: trained[f"{task} (seed {index})"]}, index
