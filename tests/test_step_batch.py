"""`env.step_batch` (auto-reset of the ended worlds only) equals `vmap(env.step)` bit for bit,
and the rollout gives the same statistics either way and on one or several devices."""

from functools import partial

import jax
import numpy as np
import pytest

from snac_jax import make
from snac_jax.rollout import random_rollout, uniform_actions


@partial(jax.jit, static_argnames=("env", "batched", "num_envs", "num_steps"))
def _trajectory(key, env, params, batched: bool, num_envs: int, num_steps: int):
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, num_envs), params)
    step = env.step_batch if batched else jax.vmap(env.step, in_axes=(0, 0, 0, None))

    def body(states, step_key):
        key_act, key_step = jax.random.split(step_key)
        actions = uniform_actions(key_act, num_envs, env.num_actions)
        obs, states, reward, terminated, truncated, info = step(jax.random.split(key_step, num_envs), states, actions, params)
        return states, (obs, reward, terminated, truncated, info, states)

    return jax.lax.scan(body, states, jax.random.split(key, num_steps))


@pytest.mark.parametrize(
    "task,overrides",
    [("3d-static-sparse", {}), ("2d-dynamic-sparse", {"design_bank_size": 64, "max_steps": 40}),
     ("1d-dynamic", {"design_bank_size": 8, "max_steps": 30}), ("3d-dynamic-dense", {"landmarks": 4, "design_bank_size": 16})],
)
def test_step_batch_equals_vmapped_step(task, overrides):
    env, params = make(task, **overrides)
    key = jax.random.key(11)
    batched = _trajectory(key, env, params, True, 48, 120)
    plain = _trajectory(key, env, params, False, 48, 120)
    jax.tree.map(np.testing.assert_array_equal, batched, plain)
    done = np.asarray(plain[1][2] | plain[1][3])
    assert done.sum() >= 10  # many auto-resets were compared


def test_rollout_statistics_do_not_depend_on_the_reset_path():
    env, params = make("3d-static-dense")
    key = jax.random.key(2)
    a = random_rollout(key, env, params, 64, 100)
    b = random_rollout(key, env, params, 64, 100, reset_ended_only=False)
    jax.tree.map(np.testing.assert_array_equal, a, b)
    assert int(a.episodes) > 64
