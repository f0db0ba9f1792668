"""gymnax's own wrappers run our envs unchanged (PureJaxRL-style code)."""

import gymnax.wrappers
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from snac_jax import make


def _purejaxrl_rollout(env, params, num_envs=16, num_steps=200):
    """What a PureJaxRL loop does: vmapped reset/step under jit, actions from the action space."""

    @jax.jit
    def run(key):
        key, key_reset = jax.random.split(key)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, num_envs), params)

        def body(carry, step_key):
            obs, state = carry
            key_act, key_step = jax.random.split(step_key)
            actions = jax.vmap(env.action_space(params).sample)(jax.random.split(key_act, num_envs))
            out = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key_step, num_envs), state, actions, params
            )
            return (out[0], out[1]), out

        return jax.lax.scan(body, (obs, state), jax.random.split(key, num_steps))[1]

    return run(jax.random.key(0))


@pytest.mark.slow
@pytest.mark.parametrize("task", ["1d-static-sin", "3d-dynamic-dense"])
def test_log_and_flatten_wrappers(task):
    base, params = make(task, design_bank_size=16) if "dynamic" in task else make(task, max_steps=50)
    env = gymnax.wrappers.LogWrapper(gymnax.wrappers.FlattenObservationWrapper(base))
    obs, state, reward, terminated, truncated, info = _purejaxrl_rollout(env, params)
    assert obs.shape == (200, 16, base.observation_layout.size)
    done = np.asarray(terminated | truncated)
    assert done.any()
    returned = np.asarray(info["returned_episode"])
    np.testing.assert_array_equal(returned, done)
    # Logged episode returns equal the sum of rewards within each finished episode.
    rewards = np.asarray(reward)
    logged = np.asarray(info["returned_episode_returns"])
    for env_index in range(16):
        ends = np.flatnonzero(done[:, env_index])
        start = 0
        for end in ends:
            assert logged[end, env_index] == pytest.approx(rewards[start : end + 1, env_index].sum())
            start = end + 1
    assert info["final_observation"].shape == obs.shape
    assert np.all(np.isfinite(np.asarray(info["final_iou"])))


def test_legacy_step_api_wrapper_returns_five_values_with_done():
    base, params = make("2d-static-dense", max_steps=30)
    env = gymnax.wrappers.LegacyStepAPIWrapper(base)
    obs, state = env.reset(jax.random.key(0), params)
    outputs = env.step(jax.random.key(1), state, 4, params)
    assert len(outputs) == 5
    for t in range(29):
        obs, state, reward, done, info = env.step(jax.random.key(t), state, jnp.int32(t % 5), params)
        assert not bool(done)
    obs, state, reward, done, info = env.step(jax.random.key(99), state, 0, params)
    assert bool(done) and bool(info["truncated"]) and int(state.time) == 0
