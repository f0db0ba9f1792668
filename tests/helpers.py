"""Test helpers: run any env through a jitted random episode and collect what it did."""

from __future__ import annotations

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
