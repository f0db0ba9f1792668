"""jit/vmap behaviour, determinism, compile-once, auto-reset and the gymnax contract."""

import jax
import numpy as np
import pytest

import snac_jax
import snac_jax.observation
from snac_jax import TASKS, make
from snac_jax.env import SNACEnv
from tests.helpers import random_episode

BANK = 64
"""The dynamic tasks' bank size in every test here: each task's bank generator compiles once for
the file, not once per size."""


@pytest.mark.parametrize("task", TASKS)
def test_same_key_same_episode_and_other_key_differs(task):
    env, params = make(task, design_bank_size=BANK) if "dynamic" in task else make(task)
    a = random_episode(jax.random.key(7), env, params, 200)
    b = random_episode(jax.random.key(7), env, params, 200)
    c = random_episode(jax.random.key(8), env, params, 200)
    jax.tree.map(np.testing.assert_array_equal, a, b)
    assert not np.array_equal(a[1][0], c[1][0])


@pytest.mark.parametrize(
    "task",
    [
        pytest.param("1d-dynamic", marks=pytest.mark.slow),
        "2d-dynamic-sparse",
        pytest.param("3d-static-dense", marks=pytest.mark.slow),
    ],
)
def test_vmap_over_1024_envs_matches_single_env_runs(task):
    env, params = make(task, design_bank_size=BANK) if "dynamic" in task else make(task)
    keys = jax.random.split(jax.random.key(1), 1024)
    batched = jax.vmap(random_episode, in_axes=(0, None, None, None))(keys, env, params, 40)
    batched = jax.device_get(batched)  # indexed in NumPy below: not one dispatch per leaf and world
    for i in range(1024):
        single = random_episode(keys[i], env, params, 40)
        jax.tree.map(lambda x, y: np.testing.assert_array_equal(x[i], y), batched, single)


def test_step_and_reset_compile_once_per_configuration(monkeypatch):
    traces = {"step_env": 0, "reset_env": 0}
    for name in traces:
        original = getattr(SNACEnv, name)

        def counted(self, *args, _original=original, _name=name, **kwargs):
            traces[_name] += 1
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(SNACEnv, name, counted)
    # A configuration no other test uses, so the jit caches start cold for it.
    env, params = make("2d-static-sparse", gps=True, landmarks=5, max_steps=77)
    for seed in range(5):
        key = jax.random.key(seed)
        obs, state = env.reset(key, params)
        for action in range(env.num_actions):
            obs, state, *_ = env.step(key, state, action, params)
    # New parameter values (not shapes) and a second instance of the same configuration.
    env2, params2 = make("2d-static-sparse", gps=True, landmarks=5, max_steps=50, stride_probs=(1, 0, 0))
    obs, state = env2.reset(jax.random.key(1), params2)
    env2.step(jax.random.key(2), state, 3, params2)
    assert traces["step_env"] == 1
    # reset_env is traced by `reset` and once more inside `step` (auto-reset).
    assert 1 <= traces["reset_env"] <= 2
    assert env == env2 and hash(env) == hash(env2)


def test_auto_reset_returns_reset_state_and_final_observation():
    env, params = make("3d-static-sparse")  # random 3D episodes end fast (stuck)
    _, (obs, action, reward, terminated, truncated, info, prev_state) = random_episode(
        jax.random.key(3), env, params, 300
    )
    done = np.asarray(terminated | truncated)
    assert done.sum() >= 2
    t = int(np.flatnonzero(done)[0])
    reset_obs, _ = env.reset(jax.random.key(0), params)
    np.testing.assert_array_equal(obs[t], reset_obs)  # static reset is the same for any key
    assert not np.array_equal(info["final_observation"][t], obs[t])
    assert int(prev_state.time[t + 1]) == 0 and int(prev_state.bricks_used[t + 1]) == 0
    # final_observation is the observation of the state the episode ended in.
    ended = jax.tree.map(lambda x: x[t], jax.device_get(prev_state))
    step_with_stride = jax.jit(env.step_with_stride)  # one program, not one per operation
    final_obs, final_state, *_ = step_with_stride(ended, action[t], info["stride"][t], params)
    np.testing.assert_array_equal(info["final_observation"][t], final_obs)
    assert float(info["final_iou"][t]) == pytest.approx(float(final_state.overlap / final_state.union))


def test_step_keeping_final_state_is_step_plus_the_state_before_the_auto_reset():
    env, params = make("3d-static-sparse")
    key = jax.random.key(5)
    _, (_, action, _, terminated, truncated, _, prev_state) = random_episode(key, env, params, 300)
    t = int(np.flatnonzero(np.asarray(terminated | truncated))[0])
    ended = jax.tree.map(lambda x: x[t], jax.device_get(prev_state))
    step_key = jax.random.key(11)
    *outputs, final_state = env.step_keeping_final_state(step_key, ended, action[t], params)
    jax.tree.map(np.testing.assert_array_equal, tuple(outputs), env.step(step_key, ended, action[t], params))
    assert int(outputs[1].time) == 0  # the returned state is the reset one...
    _, stepped, *_ = jax.jit(env.step_env)(step_key, ended, action[t], params)  # one program, not one per op
    jax.tree.map(np.testing.assert_array_equal, final_state, stepped)  # ...the seventh output the ended one
    assert int(final_state.time) > 0


def test_truncation_at_step_limit_and_termination_flags():
    env, params = make("2d-static-dense", max_steps=25)
    _, (obs, action, reward, terminated, truncated, info, prev) = random_episode(jax.random.key(0), env, params, 100)
    truncated = np.asarray(truncated)
    assert np.flatnonzero(truncated).tolist() == [24, 49, 74, 99]
    assert not np.any(np.asarray(terminated))  # 25 steps cannot spend 148 bricks


@pytest.mark.parametrize("task", TASKS)
def test_spaces_match_observations(task):
    env, params = make(task, design_bank_size=BANK) if "dynamic" in task else make(task)
    obs, state = env.reset(jax.random.key(0), params)
    space = env.observation_space(params)
    assert obs.shape == space.shape == (env.observation_layout.size,)
    assert obs.dtype == np.float32
    assert env.action_space(params).n == env.num_actions == {1: 3, 2: 5, 3: 8}[env.config.dim]
    assert np.all(obs >= space.low) and np.all(obs <= space.high)


def test_1d_reset_observation():
    env, params = make("1d-static-sin")
    obs, _ = env.reset(jax.random.key(0), params)
    np.testing.assert_array_equal(obs, [-1, -1, 0, 0, 0, 0, 0])


@pytest.mark.parametrize(
    "task,overrides",
    [
        ("1d-static-sin", {"gps": True}),
        ("1d-dynamic", {}),
        ("2d-dynamic-sparse", {"gps": True}),
        ("3d-static-dense", {}),
    ],
)
def test_observation_layout_reads_back_each_part(task, overrides):
    """The layout is the one definition of the flat observation: each slice holds its part."""
    env, params = snac_jax.make(task, **overrides)
    _, state = env.reset(jax.random.key(3), params)
    for action in (1, 0, env.num_actions - 1):
        _, state, *_ = env.step(jax.random.key(action), state, action, params)
    # Jitted: one program for both, not one per operation.
    obs, window = jax.jit(
        lambda state, params: (env.get_obs(state, params), snac_jax.observation.window(env.config, state))
    )(state, params)
    obs = np.asarray(obs)
    layout = env.observation_layout
    assert obs.shape == (layout.size,)
    np.testing.assert_array_equal(layout.window_cells(obs), np.asarray(window))
    assert obs[layout.bricks_used] == int(state.bricks_used) and obs[layout.time] == int(state.time)
    if env.config.dynamic:
        np.testing.assert_array_equal(layout.design_cells(obs), np.asarray(state.design))
    else:
        assert layout.design is None
    if env.config.gps:
        expected = state.position[1:] if env.config.dim == 1 else state.position
        np.testing.assert_array_equal(obs[layout.position], np.asarray(expected))
    else:
        assert layout.position is None
