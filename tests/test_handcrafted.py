"""The handcrafted baseline: localisation, wall fixes, legal actions, vmap and the 1D variants."""

from __future__ import annotations

import functools
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from snac_jax import make
from snac_jax.config import MOVE_DIRECTIONS
from snac_jax.policies import build_policy
from snac_jax.policies.handcrafted import handcrafted_policy


@partial(jax.jit, static_argnames=("env", "policy", "num_steps"))
def _trace(key, env, params, policy, num_steps):
    """One episode of `policy`, recording per step the true position the policy was looking
    from, its estimate after localising, its action, and whether the episode had ended."""
    key_reset, key_init, key_run = jax.random.split(key, 3)
    obs, state = env.reset_to_design(key_reset, params, 0)
    policy_state = policy.init(key_init, state.design)

    def body(carry, step_key):
        obs, state, policy_state, done = carry
        key_act, key_step = jax.random.split(step_key)
        action, policy_state = policy.act(policy.params, policy_state, obs, key_act)
        record = (state.position, policy_state.estimate, action, done)
        obs, state, _, terminated, _ = env.step_env(key_step, state, action, params)
        done = done | terminated | env.is_truncated(state, params)
        return (obs, state, policy_state, done), record

    _, records = jax.lax.scan(
        body, (obs, state, policy_state, jnp.asarray(False)), jax.random.split(key_run, num_steps)
    )
    return records


def _estimate_errors(task, variant="no-map", episodes=1, steps=None, **overrides):
    env, params = make(task, **overrides)
    policy = handcrafted_policy(env, variant)
    steps = steps or int(params.max_steps_in_episode)
    errors = 0
    for seed in range(episodes):
        position, estimate, _, ended = jax.device_get(_trace(jax.random.key(seed), env, params, policy, steps))
        live = ~ended
        assert live.sum() > 20
        errors += int(np.sum(np.any(position[live] != estimate[live], axis=-1)))
    return errors


@pytest.mark.slow
@pytest.mark.parametrize(
    "task, variant, overrides",
    [
        ("1d-static-sin", "no-map", {}),
        ("1d-static-step", "map", {}),
        ("2d-static-dense", "no-map", {}),
        ("2d-dynamic-sparse", "no-map", {"test_design": 3}),
        # With obstacles a move blocked by a brick looks like "nothing changed" and is counted
        # as one cell (the reference's odometry), so exactness needs the obstacle rule off.
        ("3d-static-sparse", "no-map", {"obstacles": False}),
    ],
)
def test_localisation_is_exact_when_every_stride_is_one(task, variant, overrides):
    assert _estimate_errors(task, variant, stride_probs=(1, 0, 0), **overrides) == 0


def test_localisation_drifts_with_random_strides():
    # The exactness above is a property of stride 1, not of a test that cannot fail.
    assert _estimate_errors("1d-static-sin", "no-map") > 0


@functools.cache
def _jitted_act(policy):
    return jax.jit(policy.act)


def _after_a_move(env, params, previous_position, action, believed_position):
    """A robot that truly moved one cell from `previous_position` by the move `action` while
    believing it stood at `believed_position`: its policy state and its new observation."""
    _, state = env.reset_to_design(jax.random.key(0), params, 0)
    at = lambda position: env.get_obs(state.replace(position=jnp.asarray(position, jnp.int32)), params)
    rows, cols = env.config.window_shape
    previous_window = at(previous_position)[: rows * cols].reshape(rows, cols)
    true_position = np.add(previous_position, MOVE_DIRECTIONS[action])
    policy = handcrafted_policy(env)
    policy_state = policy.init(jax.random.key(0), state.design).replace(
        estimate=jnp.asarray(believed_position, jnp.int32),
        last_action=jnp.asarray(action, jnp.int32),
        last_window=previous_window,
    )
    return policy, policy_state, at(true_position)


@pytest.mark.parametrize("task", ["2d-static-dense", "3d-static-dense"])
@pytest.mark.parametrize(
    "previous_position, action, believed_position, expected",
    [
        ((1, 17), 1, (6, 9), (1, 18)),  # top and right walls in view: both coordinates snap
        ((18, 0), 2, (12, 4), (19, 0)),  # bottom-left corner
        ((10, 1), 1, (7, 9), (7, 2)),  # left wall only: the column snaps, the row is kept
        ((17, 9), 1, (13, 5), (17, 6)),  # bottom wall only: the row snaps, the column moves by 1
    ],
)
def test_estimate_snaps_to_the_true_position_next_to_a_wall(
    task, previous_position, action, believed_position, expected
):
    env, params = make(task)
    policy, policy_state, obs = _after_a_move(env, params, previous_position, action, believed_position)
    _, policy_state = _jitted_act(policy)(None, policy_state, obs, jax.random.key(1))
    assert tuple(np.asarray(policy_state.estimate)) == expected


def test_a_drop_keeps_the_estimate_even_next_to_a_wall():
    env, params = make("2d-static-dense")
    policy, policy_state, obs = _after_a_move(env, params, (1, 17), 1, (6, 9))
    policy_state = policy_state.replace(last_action=jnp.asarray(4, jnp.int32))
    _, policy_state = _jitted_act(policy)(None, policy_state, obs, jax.random.key(1))
    assert tuple(np.asarray(policy_state.estimate)) == (6, 9)


@pytest.mark.slow
@pytest.mark.parametrize(
    "task, policy_name, overrides",
    [
        ("1d-dynamic", "handcrafted", {"test_design": 0}),
        ("1d-static-gauss", "handcrafted-map", {}),
        ("2d-static-sparse", "handcrafted", {"landmarks": 8}),
        ("2d-static-dense", "handcrafted", {"obstacles": True}),
        ("3d-dynamic-dense", "handcrafted", {"test_design": 5}),
        ("3d-static-dense", "handcrafted", {"obstacles": False, "gps": True}),
    ],
)
def test_actions_stay_inside_the_action_set(task, policy_name, overrides):
    env, params = make(task, **overrides)
    policy = build_policy(policy_name, env)
    _, _, actions, ended = jax.device_get(_trace(jax.random.key(3), env, params, policy, 300))
    actions = actions[~ended]
    assert actions.size > 0
    assert actions.min() >= 0 and actions.max() < env.num_actions
    # It builds: some drop action appears (1D/2D: the last action; 3D: actions 4..7).
    first_drop = 2 if env.config.dim == 1 else 4
    assert np.any(actions >= first_drop)


@pytest.mark.slow
@pytest.mark.parametrize("task", ["1d-static-sin", "2d-static-dense", "3d-static-sparse"])
def test_vmap_gives_the_same_actions_as_unbatched(task):
    env, params = make(task)
    policy = handcrafted_policy(env)
    keys = jax.random.split(jax.random.key(7), 3)
    batched = jax.vmap(lambda k: _trace(k, env, params, policy, 300))(keys)
    for i, key in enumerate(keys):
        single = _trace(key, env, params, policy, 300)
        np.testing.assert_array_equal(np.asarray(batched[2][i]), np.asarray(single[2]))
        np.testing.assert_array_equal(np.asarray(batched[1][i]), np.asarray(single[1]))


def test_the_policy_never_reads_the_true_position():
    # The same observations give the same actions with and without the GPS entries.
    env, params = make("2d-static-dense")
    env_gps, params_gps = make("2d-static-dense", gps=True)
    plain = _trace(jax.random.key(5), env, params, handcrafted_policy(env), 300)
    with_gps = _trace(jax.random.key(5), env_gps, params_gps, handcrafted_policy(env_gps), 300)
    np.testing.assert_array_equal(np.asarray(plain[2]), np.asarray(with_gps[2]))


def test_policies_are_cached_per_configuration():
    env, _ = make("2d-static-dense")
    assert handcrafted_policy(env) is handcrafted_policy(make("2d-static-dense")[0])
    assert handcrafted_policy(env) is not handcrafted_policy(make("2d-static-sparse")[0])


def test_bad_variant_is_a_value_error():
    env, _ = make("1d-static-sin")
    with pytest.raises(ValueError, match="no-map"):
        handcrafted_policy(env, "maps")
