"""`env.step_batch` equals `vmap(env.step)` bit for bit under either auto-reset strategy (the
ended worlds reset one by one, or every world's fresh state selected), the backend picks its
strategy, and the rollout gives the same statistics whichever strategy steps it."""

from functools import partial

import jax
import numpy as np
import pytest

from snac_jax import batched_step, make
from snac_jax.rollout import random_rollout, uniform_actions

STRATEGIES = ("loop", "select")


@partial(jax.jit, static_argnames=("env", "num_envs", "num_steps"))
def _trajectories(key, env, params, num_envs: int, num_steps: int):
    """`{strategy: trajectory}` for each auto-reset strategy, and `"vmap"`: by `vmap(env.step)`, from
    the same key, as one program: XLA compiles the parts they share once (about half the compile
    time of three programs)."""
    runs = {reset: _trajectory(key, env, params, reset, num_envs, num_steps) for reset in STRATEGIES}
    return {**runs, "vmap": _trajectory(key, env, params, None, num_envs, num_steps)}


def _trajectory(key, env, params, reset: str | None, num_envs: int, num_steps: int):
    """`num_steps` steps of `num_envs` worlds by `env.step_batch(..., reset=reset)`, or by
    `vmap(env.step)` where `reset` is None."""
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, num_envs), params)
    if reset is None:
        step = jax.vmap(env.step, in_axes=(0, 0, 0, None))
    else:
        step = partial(env.step_batch, reset=reset)

    def body(states, step_key):
        key_act, key_step = jax.random.split(step_key)
        actions = uniform_actions(key_act, num_envs, env.num_actions)
        obs, states, reward, terminated, truncated, info = step(
            jax.random.split(key_step, num_envs), states, actions, params
        )
        return states, (obs, reward, terminated, truncated, info, states)

    return jax.lax.scan(body, states, jax.random.split(key, num_steps))


@pytest.mark.parametrize(
    "task,overrides",
    [
        ("3d-static-sparse", {}),
        ("2d-dynamic-sparse", {"design_bank_size": 64, "max_steps": 40}),
        ("1d-dynamic", {"design_bank_size": 8, "max_steps": 30}),
        ("1d-static-sin", {"max_steps": 25}),
        ("2d-static-dense", {"max_steps": 35}),
        ("3d-dynamic-dense", {"landmarks": 4, "design_bank_size": 16}),
    ],
)
def test_step_batch_equals_vmapped_step(task, overrides):
    env, params = make(task, **overrides)
    trajectories = _trajectories(jax.random.key(11), env, params, 48, 120)
    plain = trajectories["vmap"]
    for reset in STRATEGIES:
        jax.tree.map(partial(np.testing.assert_array_equal, err_msg=f"reset={reset}"), trajectories[reset], plain)
    done = np.asarray(plain[1][2] | plain[1][3])
    assert done.sum() >= 10  # many auto-resets were compared


def test_auto_is_loop_on_a_cpu_and_select_on_an_accelerator():
    assert batched_step.resolve_reset("auto", "cpu") == "loop"
    assert batched_step.resolve_reset("auto", "gpu") == "select"
    assert batched_step.resolve_reset("auto", "tpu") == "select"
    assert batched_step.resolve_reset("select", "cpu") == "select"
    assert batched_step.resolve_reset("loop", "gpu") == "loop"
    assert batched_step.resolve_reset("auto") == ("loop" if jax.default_backend() == "cpu" else "select")


@pytest.mark.parametrize("bad", ["Loop", "", "vmap", None, 1])
def test_an_unknown_reset_strategy_is_refused_in_one_line_before_tracing(bad):
    env, params = make("1d-static-sin")
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), 2), params)
    with pytest.raises(ValueError, match=r"^reset must be one of auto, loop, select, got") as caught:
        env.step_batch(jax.random.split(jax.random.key(1), 2), states, np.zeros(2, np.int32), params, reset=bad)
    assert "\n" not in str(caught.value)
    with pytest.raises(ValueError, match="reset must be one of"):
        random_rollout(jax.random.key(0), env, params, 4, 3, reset=bad)


def test_step_batch_compiles_once_per_strategy():
    env, params = make("2d-static-dense", max_steps=12)
    keys = jax.random.split(jax.random.key(0), 8)
    _, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    actions = np.zeros(8, np.int32)
    env._step_batch.clear_cache()
    for reset in ("loop", "select", "loop", "select", "auto"):
        for _ in range(2):
            env.step_batch(keys, states, actions, params, reset=reset)
    assert env._step_batch._cache_size() == 2  # "auto" is one of the two


@partial(jax.jit, static_argnames=("env",))
def _rollouts(key, env, params):
    """`{strategy: random_rollout(...)}` for each auto-reset strategy, as one program (see `_trajectories`)."""
    return {reset: random_rollout(key, env, params, 64, 100, reset=reset) for reset in STRATEGIES}


@pytest.mark.parametrize("reset", STRATEGIES)
def test_rollout_statistics_do_not_depend_on_the_reset_strategy(reset):
    env, params = make("3d-static-dense")
    rollouts = _rollouts(jax.random.key(2), env, params)
    a, b = rollouts[reset], rollouts["select" if reset == "loop" else "loop"]
    jax.tree.map(np.testing.assert_array_equal, a, b)
    assert int(a.episodes) > 64
