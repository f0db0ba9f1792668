"""`SNACEnv.observation_space` / `action_space`: built under `jit` and `vmap` with traced params,
per-entry bounds that are tight where they can be, and never broken by a rollout."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from snac_jax import make
from tests.helpers import random_episode

CASES = [
    ("1d-static-sin", {"max_steps": 60}),
    ("1d-dynamic", {"gps": True, "design_bank_size": 16}),
    ("2d-static-dense", {"landmarks": True}),
    ("2d-dynamic-sparse", {"gps": True, "design_bank_size": 16, "max_steps": 200}),
    ("3d-static-sparse", {"max_steps": 400}),
    ("3d-dynamic-dense", {"gps": True, "landmarks": 4, "design_bank_size": 16}),
]
IDS = [f"{task}-{'-'.join(overrides) or 'default'}" for task, overrides in CASES]


def bounds(env, params):
    space = env.observation_space(params)
    return space.low, space.high


def expected_bounds(env, params):
    """The bounds written out entry by entry from the layout, in NumPy."""
    config, layout = env.config, env.observation_layout
    steps = int(params.max_steps_in_episode)
    bricks = min(int(np.max(np.asarray(params.design_max_bricks))), steps)
    low = np.zeros(layout.size, np.float32)
    high = np.zeros(layout.size, np.float32)
    window_low = np.full(layout.window_shape, -2.0 if config.num_landmarks else -1.0)
    window_low[config.pad] = -2.0 if config.num_landmarks else 0.0  # the robot's own cell
    low[layout.window] = window_low.reshape(-1)
    high[layout.window] = 1.0 if config.dim == 2 else bricks
    high[layout.bricks_used] = bricks
    high[layout.time] = steps
    if config.dynamic:
        high[layout.design] = np.max(np.asarray(params.designs))
    if config.gps:
        high[layout.position] = [19, 19] if config.dim > 1 else [29]
    return low, high


@pytest.mark.parametrize(("task", "overrides"), CASES, ids=IDS)
def test_bounds_under_jit_and_vmap_contain_a_random_rollout(task, overrides):
    env, params = make(task, **overrides)
    low, high = jax.jit(bounds, static_argnums=0)(env, params)
    assert low.shape == high.shape == env.observation_space(params).shape == (env.observation_layout.size,)
    expected_low, expected_high = expected_bounds(env, params)
    np.testing.assert_array_equal(low, expected_low)
    np.testing.assert_array_equal(high, expected_high)
    np.testing.assert_array_equal(bounds(env, params)[1], high)  # eager and jitted agree

    # vmap over params that differ in the step limit: each gets its own bounds.
    limits = jnp.asarray([7, 30])
    stacked = jax.tree.map(lambda leaf: jnp.stack([leaf, leaf]), params).replace(max_steps_in_episode=limits)
    low_v, high_v = jax.vmap(lambda p: bounds(env, p))(stacked)
    assert high_v.shape == (2, env.observation_layout.size)
    for i, limit in enumerate([7, 30]):
        want_low, want_high = expected_bounds(env, params.replace(max_steps_in_episode=limit))
        np.testing.assert_array_equal(np.broadcast_to(low_v, high_v.shape)[i], want_low)
        np.testing.assert_array_equal(high_v[i], want_high)

    _, (obs, _, _, _, _, info, _) = random_episode(jax.random.key(1), env, params, 2000)
    for name, batch in (("obs", np.asarray(obs)), ("final_observation", np.asarray(info["final_observation"]))):
        below = np.argwhere(batch < low)
        above = np.argwhere(batch > high)
        assert below.size == 0, f"{name} below low at (step, entry) {below[:5].tolist()}"
        assert above.size == 0, f"{name} above high at (step, entry) {above[:5].tolist()}"

    space = env.observation_space(params)
    assert bool(jax.jit(lambda o: jax.vmap(space.contains)(o))(obs).all())


def test_step_limit_and_padding_bounds_are_reached():
    env, params = make("1d-static-sin", max_steps=60)
    low, high = bounds(env, params)
    layout = env.observation_layout
    _, (obs, _, _, _, truncated, info, _) = random_episode(jax.random.key(0), env, params, 600)
    final = np.asarray(info["final_observation"])[np.asarray(truncated)]
    assert final.shape[0] > 0
    assert float(high[layout.time]) == 60
    assert np.all(final[:, layout.time] == 60)
    assert np.asarray(obs)[:, layout.window].min() == -1.0 == float(np.min(low))


def test_spaces_inside_a_jitted_function_with_params_as_arguments():
    env, params = make("2d-dynamic-dense", gps=True, design_bank_size=8)

    @jax.jit
    def sample_and_check(key, p):
        space, actions = env.observation_space(p), env.action_space(p)
        x = space.sample(key)
        return x, space.contains(x), actions.sample(key), jnp.asarray(actions.n)

    x, inside, action, n = sample_and_check(jax.random.key(0), params)
    assert x.shape == (env.observation_layout.size,) and bool(inside)
    assert 0 <= int(action) < int(n) == env.num_actions == 5

    per_world = jax.vmap(lambda p: env.observation_space(p).high)(
        jax.tree.map(lambda leaf: jnp.stack([leaf] * 3), params)
    )
    assert per_world.shape == (3, env.observation_layout.size)
