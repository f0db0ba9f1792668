"""The plain NumPy engine (the benchmark's baseline, written from SPEC.md alone) agrees with the
golden traces, and with the JAX environment step for step on random episodes with auto-reset."""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.numpy_engine import NumpyEnv, line_cells, random_sine, random_triangle
from snac_jax import TASKS, designs, make
from tests.conftest import golden_traces


def _engine_for_trace(trace) -> NumpyEnv:
    variant = trace["variant"]
    if "-test" in variant:
        task, index = variant.rsplit("-test", 1)
        return NumpyEnv(task, test_design=int(index), max_steps=int(trace["max_steps"]))
    return NumpyEnv(variant, max_steps=int(trace["max_steps"]))


def test_numpy_engine_replays_every_golden_trace():
    for number, trace in enumerate(golden_traces()):
        env = _engine_for_trace(trace)
        expected = np.asarray(trace["observations"], dtype=np.float32)
        width = expected.shape[1]
        np.testing.assert_array_equal(env.reset()[:width], expected[0], err_msg=f"trace {number} reset")
        assert env.max_bricks == trace["max_bricks"]
        for t, (action, stride) in enumerate(zip(trace["actions"], trace["strides"])):
            obs, reward, terminated, truncated, info = env.step(action, stride)
            where = f"trace {number} ({trace['variant']}) step {t}"
            np.testing.assert_array_equal(obs[:width], expected[t + 1], err_msg=where)
            assert reward == trace["rewards"][t], where
            assert (terminated or truncated) == trace["dones"][t], where
            assert info["stride"] == stride
        np.testing.assert_array_equal(env.built(), np.asarray(trace["final_grid"]))
        assert env.iou() == pytest.approx(trace["final_iou"], abs=1e-12)


@partial(jax.jit, static_argnames=("env", "num_steps"))
def _jax_episodes(key, env, params, actions, num_steps):
    """One env under the given actions with gymnax auto-reset; what the oracle needs per step."""
    key_reset, key_run = jax.random.split(key)
    _, state = env.reset(key_reset, params)

    def body(state, inputs):
        step_key, action = inputs
        obs, state, reward, terminated, truncated, info = env.step(step_key, state, action, params)
        marks = state.landmarks if state.landmarks is not None else jnp.zeros((), bool)
        out = (obs, reward, terminated, truncated, info["stride"], info["final_observation"], state.design, marks)
        return state, out

    _, outputs = jax.lax.scan(body, state, (jax.random.split(key_run, num_steps), actions))
    return state, outputs


def _plan(mask, env):
    (pr, pc), (h, w) = env.config.pad, env.config.plan_shape
    return np.asarray(mask)[pr : pr + h, pc : pc + w]


CASES = [(task, {}) for task in TASKS] + [
    ("2d-static-sparse", {"obstacles": True}),
    ("3d-static-sparse", {"obstacles": False}),
    ("3d-dynamic-dense", {"reward_scheme": "binary", "gps": True}),
    ("1d-static-step", {"gps": True, "stride_probs": (0.2, 0.0, 0.8)}),
    ("2d-dynamic-dense", {"landmarks": 6}),
    ("3d-static-dense", {"landmarks": 8}),
]


@pytest.mark.slow
@pytest.mark.parametrize("task,overrides", CASES, ids=[f"{t}-{'-'.join(o) or 'default'}" for t, o in CASES])
def test_numpy_engine_follows_jax_env_step_for_step(task, overrides):
    """Random actions (half of them drops, to reach the brick limit), strides drawn by the JAX env,
    short step limits so that several episodes end and auto-reset; each JAX reset's design and
    landmarks are handed to the NumPy engine."""
    num_steps = 700
    max_steps = 150
    bank = {"design_bank_size": 32} if "dynamic" in task else {}
    env, params = make(task, max_steps=max_steps, **bank, **overrides)
    np_overrides = {k: v for k, v in overrides.items() if k != "landmarks"}
    engine = NumpyEnv(task, max_steps=max_steps, landmarks=overrides.get("landmarks", 0), **np_overrides)
    assert engine.num_actions == env.num_actions

    rng = np.random.default_rng(len(task) + len(overrides))
    drops = [a for a, (is_drop, *_) in enumerate(env.config.actions) if is_drop]
    moves = [a for a in range(env.num_actions) if a not in drops]
    actions = np.where(rng.random(num_steps) < 0.5, rng.choice(drops, num_steps), rng.choice(moves, num_steps))
    key = jax.random.key(5)
    _, initial = env.reset(jax.random.split(key)[0], params)
    _, out = _jax_episodes(key, env, params, jnp.asarray(actions, jnp.int32), num_steps)
    obs, rewards, terminated, truncated, strides, final_obs, next_design, marks = map(np.asarray, out)

    def reset_engine(design, landmarks):
        return engine.reset(design=design, landmarks=_plan(landmarks, env) if env.config.num_landmarks else None)

    reset_obs = reset_engine(np.asarray(initial.design), initial.landmarks)
    np.testing.assert_array_equal(reset_obs, np.asarray(env.get_obs(initial, params)))
    endings = {"terminated": 0, "truncated": 0}
    for t in range(num_steps):
        got, reward, term, trunc, info = engine.step(int(actions[t]), int(strides[t]))
        where = f"{task} {overrides} step {t}"
        assert info["stride"] == strides[t]
        np.testing.assert_array_equal(got, final_obs[t], err_msg=where)
        assert reward == rewards[t], where
        assert (term, trunc) == (bool(terminated[t]), bool(truncated[t])), where
        if term or trunc:
            endings["terminated" if term else "truncated"] += 1
            got = reset_engine(next_design[t], marks[t])
        np.testing.assert_array_equal(got, obs[t], err_msg=where + " (after auto-reset)")
    assert sum(endings.values()) >= 3, endings


def test_sampled_designs_follow_the_spec_rules():
    rng = np.random.default_rng(0)
    for _ in range(20):
        curve = random_sine(rng)
        assert curve.shape == (30,) and 8 <= curve.min() and curve.max() <= 32
    for (dim, density), (low, high) in designs.TRIANGLE_COUNT_RANGE.items():
        for _ in range(10):
            cells = random_triangle(rng, dim, density)
            count = int(np.count_nonzero(cells))
            assert count > low and (high is None or count < high)
            assert set(np.unique(cells)) <= {0, 6 if dim == 3 else 1}
    line = line_cells((0, 0), (3, 7))
    assert line[0] == (0, 0) and line[-1] == (3, 7) and len(line) == 8
    assert all(max(abs(a[0] - b[0]), abs(a[1] - b[1])) == 1 for a, b in zip(line, line[1:]))


def test_dynamic_engine_samples_a_new_design_per_episode():
    engine = NumpyEnv("2d-dynamic-sparse", seed=3)
    first = engine.reset()[51:].copy()
    second = engine.reset()[51:]
    assert first.shape == (400,) and not np.array_equal(first, second)


def test_bad_input_raises_value_error_naming_allowed_values():
    with pytest.raises(ValueError, match="allowed"):
        NumpyEnv("2d-static")
    with pytest.raises(ValueError, match="0..9"):
        NumpyEnv("1d-dynamic", test_design=10)
    engine = NumpyEnv("1d-static-sin")
    engine.reset()
    with pytest.raises(ValueError, match="0..2"):
        engine.step(3)
