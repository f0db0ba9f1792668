"""Bad input raises ValueError naming what is allowed, before anything is traced (or, for what
only tracing sees, while tracing: shapes are static, so the checks cost nothing per step)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from snac_jax import TASKS, make, test_design_names


@pytest.mark.parametrize(
    "task,overrides,message",
    [
        ("2d-static", {}, "allowed task ids: 1d-static-sin"),
        ("4d-static-dense", {}, "3d-dynamic-sparse"),
        ("2d-static-dense", {"gpss": True}, "allowed overrides: gps"),
        ("2d-static-dense", {"stride_probs": (0.5, 0.5, 0.5)}, "summing to 1"),
        ("2d-static-dense", {"stride_probs": (1.2, -0.2, 0)}, "non-negative"),
        ("2d-static-dense", {"stride_probs": (0.5, 0.5)}, "three"),
        ("2d-static-dense", {"stride_probs": "uniform"}, "three"),
        ("2d-dynamic-dense", {"test_design": 10}, r"0\.\.9"),
        ("2d-dynamic-dense", {"test_design": -1}, r"0\.\.9"),
        ("2d-static-dense", {"test_design": 0}, "dynamic tasks only"),
        ("2d-dynamic-dense", {"test_design": 1, "design_seed": 2}, "cannot be combined"),
        ("1d-static-sin", {"landmarks": 8}, "2D or 3D"),
        ("1d-dynamic", {"obstacles": True}, "2D or 3D"),
        ("2d-static-dense", {"obstacles": "yes"}, "True or False"),
        ("2d-static-dense", {"gps": 1}, "True or False"),
        ("2d-static-dense", {"landmarks": -3}, "int >= 0"),
        ("2d-static-dense", {"landmarks": 300}, "at most 252"),
        ("3d-static-dense", {"reward_scheme": "sparse"}, "one of \\('height', 'binary'\\)"),
        ("2d-static-dense", {"max_steps": 0}, r"int in 1\.\.2147483647"),
        ("2d-dynamic-sparse", {"design_bank_size": 0}, "int >= 1"),
        ("2d-static-dense", {"max_steps": 2**31}, r"int in 1\.\.2147483647"),
        ("2d-dynamic-dense", {"design_seed": 2**64}, r"int in 0\.\.4294967295"),
        ("2d-dynamic-dense", {"design_seed": 2**32}, r"int in 0\.\.4294967295"),  # key(2**32) == key(0)
        (
            "2d-dynamic-dense",
            {"design_bank_size": 10**10},
            "a bank of 10,000,000,000 designs needs about .* GiB, more than",
        ),
    ],
)
def test_make_rejects_bad_input(task, overrides, message):
    with pytest.raises(ValueError, match=message):
        make(task, **overrides)


def test_static_tasks_have_no_test_designs():
    with pytest.raises(ValueError, match="dynamic tasks: 1d-dynamic"):
        test_design_names("2d-static-dense")


@pytest.mark.slow
def test_every_task_builds_with_defaults():
    for task in TASKS:
        env, params = make(task, design_bank_size=4) if "dynamic" in task else make(task)
        assert env.name == task


def _reset(env, params):
    return env.reset(jax.random.key(0), params)[1]


def test_an_environment_refuses_another_tasks_params_and_state():
    env, params = make("2d-static-dense")
    env_1d, params_1d = make("1d-static-sin")
    state = _reset(env, params)
    with pytest.raises(ValueError, match=r"params.designs has shape \(1, 1, 30\), .* needs \(1, 20, 20\)"):
        env.reset(jax.random.key(0), params_1d)
    with pytest.raises(ValueError, match="params of another task"):
        env.step(jax.random.key(0), state, 0, params_1d)
    with pytest.raises(ValueError, match="params of another task"):
        jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(jax.random.key(0), 2),
            jax.tree.map(lambda x: jnp.stack([x, x]), state),
            jnp.zeros(2, int),
            params_1d,
        )
    with pytest.raises(ValueError, match=r"state.grid has shape \(1, 34\)"):
        env.step(jax.random.key(0), _reset(env_1d, params_1d), 0, params)
    with pytest.raises(ValueError, match=r"stride_probs has shape \(2,\)"):
        env.reset(jax.random.key(0), params.replace(stride_probs=jnp.ones(2) / 2))


def test_known_indices_strides_and_actions_are_checked_at_the_boundary():
    env, params = make("2d-dynamic-dense", design_bank_size=4)
    state = _reset(env, params)
    with pytest.raises(ValueError, match=r"design_index must be in 0\.\.3, got 4"):
        env.reset_to_design(jax.random.key(0), params, 4)
    with pytest.raises(ValueError, match=r"design_index must be in 0\.\.3, got -1"):
        env.reset_to_design(jax.random.key(0), params, jnp.asarray(-1))
    with pytest.raises(ValueError, match=r"stride must be in 1\.\.3, got 7"):
        env.step_with_stride(state, 0, 7, params)
    with pytest.raises(ValueError, match=r"stride must be in 1\.\.3, got 0"):
        env.step_with_stride(state, 0, 0, params)
    with pytest.raises(ValueError, match=r"action must be in 0\.\.4, got 5"):
        env.step_with_stride(state, 5, 1, params)
    env.step_with_stride(state, 4, 3, params)  # the largest valid ones pass


def test_traced_values_are_not_checked_and_are_clamped():
    """Inside jit an index is not known: it is clamped into range (no per-step check)."""
    env, params = make("1d-static-sin")
    state = _reset(env, params)
    step = jax.jit(env.step_with_stride)
    for clamped, valid in ((99, 2), (-1, 2), (-100, 0)):
        np.testing.assert_array_equal(step(state, clamped, 1, params)[1].grid, step(state, valid, 1, params)[1].grid)


def test_replay_refuses_actions_and_strides_the_env_would_clamp():
    from snac_jax.replay import replay

    env, params = make("1d-static-sin", max_steps=5)
    with pytest.raises(ValueError, match=r"actions must be in 0\.\.2, got 7"):
        replay(env, params, [0, 7], [1, 1])
    with pytest.raises(ValueError, match=r"strides must be in 1\.\.3, got 4"):
        replay(env, params, [0, 1], [1, 4])
    with pytest.raises(ValueError, match="one stride per action and at least one action"):
        replay(env, params, [], [])
    with pytest.raises(ValueError, match="one stride per action"):
        replay(env, params, [0, 1], [1])


def test_non_integer_indices_strides_and_actions_are_refused_naming_the_argument():
    """A float, a bool or an array where one int belongs is refused by name: JAX would index with
    a bool as a mask, and fail on a float deep inside the step."""
    env, params = make("2d-dynamic-dense", design_bank_size=4)
    state = _reset(env, params)
    for bad, shown in (
        (0.5, "0.5"),
        (1.0, "1.0"),
        (True, "True"),
        (np.float32(2), "2.0"),
        (np.array([0, 1]), r"an int64 array of shape \(2,\)"),
    ):
        with pytest.raises(ValueError, match=rf"^design_index must be one int in 0\.\.3, got {shown}$"):
            env.reset_to_design(jax.random.key(0), params, bad)
    with pytest.raises(ValueError, match=r"^stride must be one int in 1\.\.3, got 2\.0$"):
        env.step_with_stride(state, 0, 2.0, params)
    with pytest.raises(ValueError, match=r"^action must be one int in 0\.\.4, got 1\.5$"):
        env.step_with_stride(state, 1.5, 1, params)
    with pytest.raises(ValueError, match=r"^stride must be one int in 1\.\.3, got a traced float32\[\] value"):
        jax.jit(env.step_with_stride)(state, 0, jnp.float32(2), params)  # dtypes are known while tracing
    with pytest.raises(ValueError, match=r"^action must be one int in 0\.\.4, got a traced float32\[\] value"):
        env.step(jax.random.key(0), state, jnp.float32(1), params)
    env.reset_to_design(jax.random.key(0), params, np.int64(3))  # any integer type passes
    env.step_with_stride(state, np.uint8(4), jnp.int32(3), params)
    jax.jit(env.reset_to_design)(jax.random.key(0), params, jnp.int32(9))  # a traced int is not range-checked


def test_privileged_refuses_a_batch_of_states():
    env, params = make("2d-static-dense")
    states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), 3), params)[1]
    with pytest.raises(
        ValueError,
        match=r"^env.privileged takes one world's state, got a batch of shape \(3,\): "
        r"jax.vmap\(env.privileged, in_axes=\(0, None\)\)\(states, params\)$",
    ):
        env.privileged(states, params)
    batched = jax.vmap(env.privileged, in_axes=(0, None))(states, params)
    assert batched.built.shape == (3, 20, 20) and batched.position.shape == (3, 2)
    with pytest.raises(ValueError, match=r"state.grid has shape \(1, 34\)"):
        env.privileged(_reset(*make("1d-static-sin")), params)


def _bare_action(params, state, obs, key):
    return jnp.int32(0)


def _memory_grows(params, state, obs, key):
    return jnp.int32(0), jnp.zeros(3)


def _memory_turns_float(params, state, obs, key):
    return jnp.int32(0), (jnp.zeros(2), jnp.float32(0.5))


@pytest.mark.parametrize(
    ("init", "act", "message"),
    [
        (
            lambda key, design: jnp.zeros(2),
            _bare_action,
            r"policy.act must return \(action, policy_state\), got a bare int32\[\] value",
        ),
        (
            lambda key, design: jnp.zeros(2),
            _memory_grows,
            r"policy.act must return a policy_state like the one it was given, float32\[2\], got float32\[3\]",
        ),
        (
            lambda key, design: (jnp.zeros(2), jnp.int32(0)),
            _memory_turns_float,
            r"policy.act must return a policy_state like the one it was given, \(float32\[2\], int32\[\]\), "
            r"got \(float32\[2\], float32\[\]\)",
        ),
    ],
)
def test_a_policy_breaking_the_act_contract_is_named_not_jax_internals(init, act, message):
    from snac_jax.evaluation import evaluate_task
    from snac_jax.policy import Policy
    from snac_jax.recording import record_episode

    policy = Policy(init, act, None, "broken")
    with pytest.raises(ValueError, match=message):
        evaluate_task("1d-static-sin", policy, static_episodes=2, max_steps=5)
    env, params = make("1d-static-sin", max_steps=5)
    with pytest.raises(ValueError, match=message):
        record_episode(env, params, policy, jax.random.key(0))
