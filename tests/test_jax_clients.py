"""JAX RL clients written against gymnax (PureJaxRL's `make_train(config)(key)` shape, rejax's
params-as-arguments) run on SNAC tasks with nothing but the `make` line changed.

The PPO below is this project's own minimal code in that shape: the spaces are read inside the
jitted `train`, the env goes through gymnax's FlattenObservationWrapper, LogWrapper and (outermost,
since LogWrapper expects gymnax 1.0's six-value step) LegacyStepAPIWrapper, and reset/step are
vmapped over a few worlds. The standalone PPO a user copies is examples/ppo_standalone.py (SNAC's
own six-value step, no wrappers); the last test runs it on a tiny budget.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import flax.linen as nn
import gymnax.wrappers
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax.training.train_state import TrainState

import snac_jax

NUM_ENVS = 4
NUM_STEPS = 8
NUM_UPDATES = 2
EPOCHS = 2
MINIBATCHES = 2
GAMMA, LAMBDA, CLIP, ENTROPY, VALUE_COEF = 0.99, 0.95, 0.2, 0.01, 0.5


class Policy(nn.Module):
    """A tiny actor-critic MLP (default Dense initialisers)."""

    num_actions: int

    @nn.compact
    def __call__(self, obs):
        logits = nn.Dense(self.num_actions)(nn.tanh(nn.Dense(16)(obs)))
        value = nn.Dense(1)(nn.tanh(nn.Dense(16)(obs)))
        return logits, value[..., 0]


class Step(NamedTuple):
    obs: jax.Array
    action: jax.Array
    log_prob: jax.Array
    value: jax.Array
    reward: jax.Array
    done: jax.Array
    info: dict


def wrap(env):
    env = gymnax.wrappers.FlattenObservationWrapper(env)
    env = gymnax.wrappers.LogWrapper(env)
    return gymnax.wrappers.LegacyStepAPIWrapper(env)


def make_train(env, env_params):
    """A PureJaxRL-shaped PPO: `train(key)` builds everything inside the trace."""

    def train(key):
        num_actions = env.action_space(env_params).n
        obs_shape = env.observation_space(env_params).shape
        network = Policy(num_actions)
        key, init_key, reset_key = jax.random.split(key, 3)
        state = TrainState.create(
            apply_fn=network.apply,
            params=network.init(init_key, jnp.zeros(obs_shape)),
            tx=optax.chain(optax.clip_by_global_norm(0.5), optax.adam(3e-4)),
        )
        obs, env_state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(reset_key, NUM_ENVS), env_params)

        def env_step(carry, _):
            state, env_state, obs, key = carry
            key, action_key, step_key = jax.random.split(key, 3)
            logits, value = network.apply(state.params, obs)
            action = jax.random.categorical(action_key, logits)
            log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), action[:, None], axis=1)[:, 0]
            next_obs, env_state, reward, done, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(step_key, NUM_ENVS), env_state, action, env_params
            )
            return (state, env_state, next_obs, key), Step(obs, action, log_prob, value, reward, done, info)

        def advantages(steps, last_value):
            def backwards(carry, step):
                gae, next_value = carry
                delta = step.reward + GAMMA * next_value * (1 - step.done) - step.value
                gae = delta + GAMMA * LAMBDA * (1 - step.done) * gae
                return (gae, step.value), gae

            _, adv = jax.lax.scan(backwards, (jnp.zeros_like(last_value), last_value), steps, reverse=True)
            return adv, adv + steps.value

        def loss_fn(params, batch, adv, target):
            logits, value = network.apply(params, batch.obs)
            log_probs = jax.nn.log_softmax(logits)
            log_prob = jnp.take_along_axis(log_probs, batch.action[:, None], axis=1)[:, 0]
            ratio = jnp.exp(log_prob - batch.log_prob)
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            actor = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - CLIP, 1 + CLIP) * adv).mean()
            critic = jnp.square(value - target).mean()
            entropy = -(jnp.exp(log_probs) * log_probs).sum(-1).mean()
            return actor + VALUE_COEF * critic - ENTROPY * entropy

        def update(carry, _):
            carry, steps = jax.lax.scan(env_step, carry, None, NUM_STEPS)
            state, env_state, obs, key = carry
            _, last_value = network.apply(state.params, obs)
            adv, target = advantages(steps, last_value)
            flat = jax.tree.map(lambda x: x.reshape((NUM_STEPS * NUM_ENVS,) + x.shape[2:]), (steps, adv, target))

            def epoch(carry, _):
                state, key = carry
                key, perm_key = jax.random.split(key)
                order = jax.random.permutation(perm_key, NUM_STEPS * NUM_ENVS)
                shuffled = jax.tree.map(lambda x: x[order].reshape((MINIBATCHES, -1) + x.shape[1:]), flat)

                def minibatch(state, batch):
                    loss, grads = jax.value_and_grad(loss_fn)(state.params, *batch)
                    return state.apply_gradients(grads=grads), loss

                state, losses = jax.lax.scan(minibatch, state, shuffled)
                return (state, key), losses

            (state, key), losses = jax.lax.scan(epoch, (state, key), None, EPOCHS)
            return (state, env_state, obs, key), (losses, steps.info, steps.obs)

        _, (losses, info, observations) = jax.lax.scan(update, (state, env_state, obs, key), None, NUM_UPDATES)
        return {"loss": losses, "info": info, "obs": observations}

    return train


@pytest.mark.slow
@pytest.mark.parametrize(
    ("task", "overrides"),
    [
        ("1d-static-sin", {"max_steps": 6}),
        pytest.param("2d-dynamic-sparse", {"design_bank_size": 4, "max_steps": 6, "gps": True}, marks=pytest.mark.slow),
        pytest.param("3d-static-dense", {"max_steps": 6, "landmarks": 2}, marks=pytest.mark.slow),
    ],
)
def test_purejaxrl_shaped_ppo_runs(task, overrides):
    env, env_params = snac_jax.make(task, **overrides)  # the only SNAC-specific line
    env = wrap(env)
    out = jax.jit(make_train(env, env_params))(jax.random.key(0))
    loss = np.asarray(out["loss"])
    assert loss.shape == (NUM_UPDATES, EPOCHS, MINIBATCHES) and np.all(np.isfinite(loss))
    info = jax.tree.map(np.asarray, out["info"])
    lengths = info["returned_episode_lengths"][info["returned_episode"]]
    assert lengths.size and np.all((1 <= lengths) & (lengths <= 6))  # LogWrapper saw episodes end (3D: or stuck)
    assert np.all(np.isfinite(info["returned_episode_returns"]))
    space = env.observation_space(env_params)
    obs = np.asarray(out["obs"])
    assert np.all(obs >= np.asarray(space.low)) and np.all(obs <= np.asarray(space.high))


@pytest.mark.slow
def test_params_passed_as_traced_arguments_and_vmapped_seeds():
    """rejax-style: the env params are an argument of the jitted function (traced), and the
    train function is vmapped over seeds (PureJaxRL's `jit(vmap(train))`)."""
    env, env_params = snac_jax.make("1d-dynamic", design_bank_size=4, max_steps=6)
    env = wrap(env)

    def train_with(params, key):
        return make_train(env, params)(key)["loss"]

    losses = jax.jit(jax.vmap(train_with, in_axes=(None, 0)))(env_params, jax.random.split(jax.random.key(1), 2))
    assert losses.shape == (2, NUM_UPDATES, EPOCHS, MINIBATCHES) and bool(jnp.all(jnp.isfinite(losses)))


def _standalone_example():
    """examples/ppo_standalone.py, loaded as a module (examples/ is not a package)."""
    import importlib.util
    import sys

    path = Path(__file__).parents[1] / "examples" / "ppo_standalone.py"
    spec = importlib.util.spec_from_file_location("ppo_standalone", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses (flax modules) look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
@pytest.mark.parametrize(
    ("task", "env_kwargs"),
    [
        ("1d-static-sin", {"max_steps": 6}),
        pytest.param("2d-dynamic-sparse", {"design_bank_size": 4, "max_steps": 6}, marks=pytest.mark.slow),
    ],
)
def test_the_standalone_example_trains_and_scores_its_greedy_policy(task, env_kwargs):
    """The example's own `make_train` on a tiny budget: episodes end, the losses stay finite, and
    the greedy policy it scores gets an IoU in [0, 1]. It imports nothing from `agents`."""
    example = _standalone_example()
    source = Path(example.__file__).read_text()
    assert "from agents" not in source and "import agents" not in source
    config = {
        **example.CONFIG,
        "TASK": task,
        "ENV_KWARGS": env_kwargs,
        "NUM_ENVS": 4,
        "NUM_STEPS": 8,
        "TOTAL_TIMESTEPS": 64,
        "NUM_MINIBATCHES": 2,
        "UPDATE_EPOCHS": 2,
        "HIDDEN": 8,
    }
    train_state, metrics = jax.jit(example.make_train(config))(jax.random.key(0))
    assert metrics["loss"].shape == (2,) and bool(jnp.all(jnp.isfinite(metrics["loss"])))
    assert int(metrics["episodes"].sum()) > 0
    iou = example.greedy_iou(config, train_state.params, episodes=4)
    assert 0.0 <= iou <= 1.0


@pytest.mark.slow
def test_the_standalone_examples_greedy_policy_beats_random_at_its_default_budget():
    """What `python examples/ppo_standalone.py` prints (seed 0, its own CONFIG): a greedy IoU above
    a uniformly random policy's on the same 100 episodes' protocol (about 90 s on two CPU cores)."""
    from snac_jax.evaluation import run_episodes
    from snac_jax.policies import build_policy

    example = _standalone_example()
    config = example.CONFIG
    train_state, _ = jax.jit(example.make_train(config))(jax.random.key(0))
    greedy = example.greedy_iou(config, train_state.params)
    env, params = snac_jax.make(config["TASK"])
    random = run_episodes(env, params, build_policy("random", env), jax.random.key(0), np.zeros(100, np.int32))
    assert greedy > float(random.iou.mean()) + 0.05, (greedy, float(random.iou.mean()))
