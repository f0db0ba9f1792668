"""The episode loop: it stops at each episode's own end (termination, truncation), the two loops
agree, vmap and jit behave, and a recorded episode replays to the same end."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from snac_jax import episodes, make, metrics
from snac_jax.policy import uniform_random_policy
from snac_jax.recording import record_episode
from snac_jax.replay import replay
from snac_jax.tasks import make_params

DROP_1D, RIGHT_1D = 2, 1


def _three_brick_task(max_steps=600):
    """1D, a design of three bricks: the budget is 3, so the third drop terminates the episode."""
    env, params = make("1d-static-sin", max_steps=max_steps, stride_probs=(1, 0, 0))
    design = np.zeros(params.designs.shape, np.int16)
    design[0, 0, 10:13] = 1
    fresh = make_params(design, 1)
    return env, params.replace(
        designs=fresh.designs, design_max_bricks=fresh.design_max_bricks, design_volume=fresh.design_volume
    )


def _given(episode, action_stride):
    action, stride = action_stride
    return episodes.Move(action, stride=stride), episode.agent


@partial(jax.jit, static_argnames=("env",))
def _scan_given(env, params, actions, strides):
    obs, state = env.reset(jax.random.key(0), params)
    return episodes.scan_episode(env, params, _given, episodes.start(obs, state, None), xs=(actions, strides))


def _assert_frozen_after(steps, final, end):
    """Every step from `end` on (0-based) is not taken and shows the final episode."""
    live = np.asarray(steps.live)
    assert live[:end].all() and not live[end:].any()
    assert not np.any(steps.reward[end:]) and not np.any(steps.terminated[end:]) and not np.any(steps.truncated[end:])
    for leaf, last in zip(jax.tree.leaves(steps.state), jax.tree.leaves(final.state)):
        for t in range(end - 1, leaf.shape[0]):
            np.testing.assert_array_equal(leaf[t], last)
    np.testing.assert_array_equal(steps.obs[end - 1 :], np.broadcast_to(final.obs, steps.obs[end - 1 :].shape))


def test_termination_freezes_the_episode_at_the_third_drop():
    env, params = _three_brick_task()
    actions = jnp.full(8, DROP_1D, jnp.int32)
    final, steps = _scan_given(env, params, actions, jnp.ones(8, jnp.int32))
    np.testing.assert_array_equal(steps.terminated, [False, False, True] + [False] * 5)
    assert not np.any(steps.truncated)
    assert bool(final.done) and int(final.state.time) == 3 and int(final.state.bricks_used) == 3
    assert float(final.episode_return) == pytest.approx(float(np.sum(steps.reward[:3])))
    _assert_frozen_after(steps, final, 3)


def test_truncation_freezes_the_episode_at_the_step_limit():
    env, params = _three_brick_task(max_steps=5)
    actions = jnp.full(9, RIGHT_1D, jnp.int32)
    final, steps = _scan_given(env, params, actions, jnp.ones(9, jnp.int32))
    np.testing.assert_array_equal(steps.truncated, [False] * 4 + [True] + [False] * 4)
    assert not np.any(steps.terminated)
    assert bool(final.done) and int(final.state.time) == 5
    np.testing.assert_array_equal(final.state.position, [0, 5])
    _assert_frozen_after(steps, final, 5)


# --- a policy's episodes: the two loops, vmap, determinism, compile once ------------------------------

_RANDOM = uniform_random_policy(8)
_TRACES = {"count": 0}


def _decide(episode, x):
    """Random actions, the key threaded through the agent state (`x` is None in both loops)."""
    _TRACES["count"] += 1
    key, key_act, key_step = jax.random.split(episode.agent, 3)
    action, _ = _RANDOM.act(None, None, episode.obs, key_act)
    return episodes.Move(action, key=key_step), key


def _leaves(tree):
    as_data = lambda x: jax.random.key_data(x) if jnp.issubdtype(x.dtype, jax.dtypes.prng_key) else x
    return [np.asarray(as_data(leaf)) for leaf in jax.tree.leaves(tree)]


def _first(env, params, key):
    key_reset, key_run = jax.random.split(key)
    obs, state = env.reset(key_reset, params)
    return episodes.start(obs, state, key_run)


@partial(jax.jit, static_argnames=("env",))
def _to_end(env, params, keys):
    return jax.vmap(lambda key: episodes.run_to_end(env, params, _decide, _first(env, params, key)))(keys)


@partial(jax.jit, static_argnames=("env", "num_steps"))
def _scanned(env, params, key, num_steps):
    return episodes.scan_episode(env, params, _decide, _first(env, params, key), num_steps=num_steps)


@pytest.fixture(scope="module")
def random_3d():
    env, params = make("3d-static-sparse", max_steps=40)
    assert env.num_actions == 8
    keys = jax.random.split(jax.random.key(3), 6)
    return env, params, keys, jax.device_get(_to_end(env, params, keys))


@pytest.mark.slow
def test_vmapped_episodes_end_on_their_own_and_equal_single_runs(random_3d):
    env, params, keys, finals = random_3d
    lengths = np.asarray(finals.state.time)
    assert np.all(finals.done) and np.all(lengths <= 40)
    assert len(set(lengths.tolist())) > 1  # some end before the step limit, by running out of bricks or stuck
    for i in (0, int(np.argmin(lengths))):
        one = jax.device_get(_to_end(env, params, keys[i : i + 1]))
        for leaf, batched in zip(_leaves(one), _leaves(finals)):
            np.testing.assert_array_equal(leaf[0], batched[i])


def test_scan_and_run_to_end_reach_the_same_end(random_3d):
    env, params, keys, finals = random_3d
    i = int(np.argmin(finals.state.time))
    final, steps = jax.device_get(_scanned(env, params, keys[i], 40))
    length = int(finals.state.time[i])
    assert int(np.sum(steps.live)) == length
    assert bool(steps.terminated[length - 1] | steps.truncated[length - 1])
    np.testing.assert_array_equal(final.state.grid, finals.state.grid[i])
    assert float(final.episode_return) == float(finals.episode_return[i])
    assert float(metrics.iou(final.state)) == float(metrics.iou(jax.tree.map(lambda x: x[i], finals.state)))


def test_same_key_same_episodes_and_one_trace_per_configuration(random_3d):
    env, params, keys, finals = random_3d
    traces = _TRACES["count"]
    again = jax.device_get(_to_end(env, params, keys))
    shorter = jax.device_get(_to_end(env, params.replace(max_steps_in_episode=jnp.asarray(7, jnp.int32)), keys))
    assert _TRACES["count"] == traces  # new keys or another step limit: the same program
    for a, b in zip(_leaves(again), _leaves(finals)):
        np.testing.assert_array_equal(a, b)
    assert np.all(np.asarray(shorter.state.time) <= 7)
    other = jax.device_get(_to_end(env, params, jax.random.split(jax.random.key(4), 6)))
    assert not np.array_equal(other.state.grid, finals.state.grid)


def test_a_move_takes_a_key_or_a_stride():
    env, params = _three_brick_task()
    first = episodes.start(*env.reset(jax.random.key(0), params), None)
    both = lambda episode, x: (episodes.Move(jnp.int32(0), key=jax.random.key(0), stride=jnp.int32(1)), None)
    with pytest.raises(ValueError, match="exactly one"):
        episodes.scan_episode(env, params, both, first, num_steps=2)


def test_a_recorded_episode_replays_to_the_same_end():
    env, params = make("2d-static-dense", max_steps=60)
    trajectory = record_episode(env, params, uniform_random_policy(env.num_actions), jax.random.key(5))
    out = replay(env, params, trajectory.actions, trajectory.strides)
    last = trajectory.state_at(-1)
    np.testing.assert_array_equal(out["rewards"], trajectory.rewards)
    assert bool(out["terminated"][-1]) == trajectory.terminated
    assert out["final_iou"] == trajectory.final_iou == float(metrics.iou(last))
    (pr, pc), (h, w) = env.config.pad, env.config.plan_shape
    np.testing.assert_array_equal(out["final_grid"], last.grid[pr : pr + h, pc : pc + w])
