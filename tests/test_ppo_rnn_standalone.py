"""examples/ppo_rnn_standalone.py, the recurrent standalone PPO: trained on a tiny budget (episodes
end, the losses stay finite, its greedy policy is scored), its GRU's memory zeroed at an
episode's start, and a truncated episode's reward bootstrapped from its final observation."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

PATH = Path(__file__).parents[1] / "examples" / "ppo_rnn_standalone.py"
TINY = {"NUM_ENVS": 4, "NUM_STEPS": 8, "TOTAL_TIMESTEPS": 64, "NUM_MINIBATCHES": 2, "UPDATE_EPOCHS": 2, "HIDDEN": 8}


@pytest.fixture(scope="module")
def example():
    """The example loaded as a module (examples/ is not a package)."""
    spec = importlib.util.spec_from_file_location("ppo_rnn_standalone", PATH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses (flax modules) look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
@pytest.mark.parametrize(
    ("task", "env_kwargs"),
    [
        ("1d-static-sin", {"max_steps": 6}),  # rollouts of 8 steps cross the step limit: truncations
        pytest.param("2d-dynamic-sparse", {"design_bank_size": 4, "max_steps": 6}, marks=pytest.mark.slow),
    ],
)
def test_the_recurrent_example_trains_and_scores_its_greedy_policy(example, task, env_kwargs):
    source = PATH.read_text()
    assert "from agents" not in source and "import agents" not in source
    config = {**example.CONFIG, "TASK": task, "ENV_KWARGS": env_kwargs, **TINY}
    train_state, metrics = jax.jit(example.make_train(config))(jax.random.key(0))
    assert metrics["loss"].shape == (2,) and bool(jnp.all(jnp.isfinite(metrics["loss"])))
    assert int(metrics["episodes"].sum()) > 0
    iou = example.greedy_iou(config, train_state.params, episodes=4)
    assert 0.0 <= iou <= 1.0


@pytest.mark.slow
def test_the_gru_forgets_at_an_episodes_start(example):
    """Where `start` is set the carry given is ignored; elsewhere it changes the outputs."""
    network = example.ActorCriticRNN(num_actions=5, hidden=8)
    x = jax.random.normal(jax.random.key(0), (3, 2, 6))
    start = jnp.array([[True, False], [False, False], [False, True]])
    zeros, memory = jnp.zeros((2, 8)), jax.random.normal(jax.random.key(1), (2, 8))
    params = network.init(jax.random.key(2), zeros, x, start)
    _, logits_zero, value_zero = network.apply(params, zeros, x, start)
    _, logits_memory, value_memory = network.apply(params, memory, x, start)
    np.testing.assert_array_equal(logits_memory[:, 0], logits_zero[:, 0])  # world 0 starts at step 0
    np.testing.assert_array_equal(value_memory[:, 0], value_zero[:, 0])
    assert not np.allclose(logits_memory[:, 1], logits_zero[:, 1])  # world 1 carries its memory in


def test_a_truncated_episode_is_bootstrapped_and_a_terminated_one_is_not(example):
    config = {**example.CONFIG, "GAMMA": 0.9, "REWARD_SCALE": 0.5}
    reward = jnp.array([2.0, 2.0, 2.0, 2.0])
    terminated = jnp.array([False, True, False, True])
    truncated = jnp.array([False, False, True, True])  # the last: both (the limit on the ending step)
    final_value = jnp.array([10.0, 10.0, 10.0, 10.0])
    got = example.bootstrapped_reward(reward, terminated, truncated, final_value, config)
    np.testing.assert_allclose(got, [1.0, 1.0, 1.0 + 0.9 * 10.0, 1.0])
