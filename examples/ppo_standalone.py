"""A standalone PPO on a SNAC task in one file, PureJaxRL-shaped: `make_train(config)` returns a
pure `train(key)` that builds the network, steps every world, computes GAE and runs the clipped
updates inside one `jit`. It reads nothing from this repository's learners (`agents/`), only the
environment library `snac_jax`, so it is the file to copy to start a learner of your own.

    python examples/ppo_standalone.py          # 1d-static-sin, seed 0: one to two minutes on two CPU cores
    python examples/ppo_standalone.py --seed 1

It prints the greedy policy's mean IoU on 100 episodes, scored by `snac_jax.evaluation`: 0.666,
0.602, 0.651, 0.454 and 0.545 for seeds 0 to 4 (`--seed N`, on a CPU), where a uniformly random
policy scores 0.388 (`snac eval --policy random --task 1d-static-sin --episodes 100`). The policy is feed-forward: it
reads the observation, the one before it and the last action (the window's shift shows how far
the last move went), but keeps no memory beyond, so expect it well below the recurrent learners
of `agents/` (the robot never sees where it stands, SPEC §6), and its greedy score varies from
seed to seed more than theirs.
"""

from __future__ import annotations

import argparse
import time
from typing import NamedTuple

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training.train_state import TrainState

import snac_jax
from snac_jax.evaluation import run_episodes
from snac_jax.policy import Policy

CONFIG = {
    "TASK": "1d-static-sin",
    "ENV_KWARGS": {},
    "NUM_ENVS": 64,
    "NUM_STEPS": 64,
    "TOTAL_TIMESTEPS": 5_000_000,
    "UPDATE_EPOCHS": 4,
    "NUM_MINIBATCHES": 4,
    "LR": 1e-3,
    "GAMMA": 0.99,
    "GAE_LAMBDA": 0.95,
    "CLIP_EPS": 0.2,
    "ENT_COEF": 0.01,
    # Below zero: late in training the bonus becomes a penalty on entropy, so the sampled policy
    # turns nearly deterministic and its argmax (what `greedy_iou` scores) is the policy that was
    # trained. Without it a memoryless policy leans on sampling to leave a spot it keeps returning
    # to, and its argmax repeats one action there.
    "ENT_COEF_END": -0.05,
    "VF_COEF": 0.5,
    "MAX_GRAD_NORM": 0.5,
    "REWARD_SCALE": 0.1,
    "HIDDEN": 64,
}


class ActorCritic(nn.Module):
    """Two tanh MLPs: action logits and the state value."""

    num_actions: int
    hidden: int

    @nn.compact
    def __call__(self, obs):
        def mlp(x, out, scale):
            for _ in range(2):
                x = nn.tanh(nn.Dense(self.hidden, kernel_init=nn.initializers.orthogonal(np.sqrt(2)))(x))
            return nn.Dense(out, kernel_init=nn.initializers.orthogonal(scale))(x)

        return mlp(obs, self.num_actions, 0.01), mlp(obs, 1, 1.0)[..., 0]


def make_inputs(env, env_params):
    """`inputs(obs, previous_obs, last_action)`: what the network reads. The observation and the
    previous one, each entry divided by its largest magnitude in the task's observation space (the
    step and brick counters run to hundreds: unscaled, they saturate the tanh units), and the last
    action one-hot (its last slot "none" at an episode's first step, where the previous
    observation is `obs`)."""
    space = env.observation_space(env_params)
    scale = jnp.maximum(jnp.maximum(space.high, -space.low), 1.0)

    def inputs(obs, previous_obs, last_action):
        one_hot = jax.nn.one_hot(last_action, env.num_actions + 1)
        return jnp.concatenate([obs / scale, previous_obs / scale, one_hot], axis=-1)

    return inputs


class Transition(NamedTuple):
    obs: jax.Array  # the network's inputs
    action: jax.Array
    log_prob: jax.Array
    value: jax.Array
    reward: jax.Array
    done: jax.Array
    iou: jax.Array  # the episode's final IoU where `done`


def make_train(config):
    env, env_params = snac_jax.make(config["TASK"], **config["ENV_KWARGS"])
    num_updates = config["TOTAL_TIMESTEPS"] // (config["NUM_ENVS"] * config["NUM_STEPS"])
    network, num_actions = ActorCritic(env.num_actions, config["HIDDEN"]), env.num_actions
    step = jax.vmap(env.step, in_axes=(0, 0, 0, None))  # SNAC's step resets an ended episode itself
    inputs = make_inputs(env, env_params)

    def train(key):
        key, key_init, key_reset = jax.random.split(key, 3)
        obs, env_state = jax.vmap(env.reset, in_axes=(0, None))(
            jax.random.split(key_reset, config["NUM_ENVS"]), env_params
        )
        none = jnp.full(obs.shape[:1], num_actions)  # "no last action" at an episode's start
        schedule = optax.linear_schedule(
            config["LR"], 0.0, num_updates * config["UPDATE_EPOCHS"] * config["NUM_MINIBATCHES"]
        )
        train_state = TrainState.create(
            apply_fn=network.apply,
            params=network.init(key_init, inputs(obs, obs, none)[0]),
            tx=optax.chain(optax.clip_by_global_norm(config["MAX_GRAD_NORM"]), optax.adam(schedule, eps=1e-5)),
        )

        def env_step(runner, _):
            train_state, env_state, (obs, previous_obs, last_action), key = runner
            key, key_act, key_step = jax.random.split(key, 3)
            net_obs = inputs(obs, previous_obs, last_action)
            logits, value = network.apply(train_state.params, net_obs)
            pi = distrax.Categorical(logits=logits)
            action = pi.sample(seed=key_act)
            next_obs, env_state, reward, terminated, truncated, info = step(
                jax.random.split(key_step, config["NUM_ENVS"]), env_state, action, env_params
            )
            done = terminated | truncated  # a truncation is treated as an ending here, for brevity
            transition = Transition(
                net_obs, action, pi.log_prob(action), value, reward * config["REWARD_SCALE"], done, info["final_iou"]
            )
            seen = (next_obs, jnp.where(done[:, None], next_obs, obs), jnp.where(done, num_actions, action))
            return (train_state, env_state, seen, key), transition

        def gae(batch, last_value):
            def backwards(carry, t):
                advantage, next_value = carry
                delta = t.reward + config["GAMMA"] * next_value * (1 - t.done) - t.value
                advantage = delta + config["GAMMA"] * config["GAE_LAMBDA"] * (1 - t.done) * advantage
                return (advantage, t.value), advantage

            _, advantages = jax.lax.scan(backwards, (jnp.zeros_like(last_value), last_value), batch, reverse=True)
            return advantages, advantages + batch.value

        def loss_fn(params, batch, advantages, targets, ent_coef):
            logits, value = network.apply(params, batch.obs)
            pi = distrax.Categorical(logits=logits)
            ratio = jnp.exp(pi.log_prob(batch.action) - batch.log_prob)
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
            clip = config["CLIP_EPS"]
            actor = -jnp.minimum(ratio * advantages, jnp.clip(ratio, 1 - clip, 1 + clip) * advantages).mean()
            value_clipped = batch.value + jnp.clip(value - batch.value, -clip, clip)
            critic = 0.5 * jnp.maximum((value - targets) ** 2, (value_clipped - targets) ** 2).mean()
            return actor + config["VF_COEF"] * critic - ent_coef * pi.entropy().mean()

        def update(runner, progress):
            # The entropy coefficient anneals linearly from ENT_COEF to ENT_COEF_END (see CONFIG).
            ent_coef = config["ENT_COEF"] + progress * (config["ENT_COEF_END"] - config["ENT_COEF"])
            runner, batch = jax.lax.scan(env_step, runner, None, config["NUM_STEPS"])
            train_state, env_state, seen, key = runner
            advantages, targets = gae(batch, network.apply(train_state.params, inputs(*seen))[1])

            def epoch(carry, _):
                train_state, key = carry
                key, key_perm = jax.random.split(key)
                flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), (batch, advantages, targets))
                order = jax.random.permutation(key_perm, config["NUM_ENVS"] * config["NUM_STEPS"])
                minibatches = jax.tree.map(
                    lambda x: x[order].reshape((config["NUM_MINIBATCHES"], -1) + x.shape[1:]), flat
                )

                def minibatch(train_state, minibatch):
                    loss, grads = jax.value_and_grad(loss_fn)(train_state.params, *minibatch, ent_coef)
                    return train_state.apply_gradients(grads=grads), loss

                train_state, losses = jax.lax.scan(minibatch, train_state, minibatches)
                return (train_state, key), losses

            (train_state, key), losses = jax.lax.scan(epoch, (train_state, key), None, config["UPDATE_EPOCHS"])
            metrics = {
                "loss": losses.mean(),
                "episodes": batch.done.sum(),
                "iou_sum": jnp.where(batch.done, batch.iou, 0.0).sum(),
            }
            return (train_state, env_state, seen, key), metrics

        progress = jnp.linspace(0.0, 1.0, num_updates)
        runner, metrics = jax.lax.scan(update, (train_state, env_state, (obs, obs, none), key), progress)
        return runner[0], metrics

    return train


def greedy_iou(config, params, episodes: int = 100, seed: int = 0) -> float:
    """The mean final IoU of the greedy (argmax) policy over `episodes` episodes."""
    env, env_params = snac_jax.make(config["TASK"], **config["ENV_KWARGS"])
    network = ActorCritic(env.num_actions, config["HIDDEN"])
    inputs = make_inputs(env, env_params)

    def init(key, design):  # the previous observation (unused at the start) and "no last action"
        return jnp.zeros(env.observation_space(env_params).shape), jnp.int32(env.num_actions)

    def act(params, policy_state, obs, key):
        previous_obs, last_action = policy_state
        previous_obs = jnp.where(last_action == env.num_actions, obs, previous_obs)
        logits, _ = network.apply(params, inputs(obs, previous_obs, last_action))
        action = jnp.argmax(logits).astype(jnp.int32)
        return action, (obs, action)

    policy = Policy(init=init, act=act, params=params)
    outcomes = run_episodes(env, env_params, policy, jax.random.key(seed), np.zeros(episodes, np.int32))
    return float(outcomes.iou.mean())


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0, help="the training key's seed (default 0)")
    seed = parser.parse_args().seed
    start = time.perf_counter()
    train_state, metrics = jax.jit(make_train(CONFIG))(jax.random.key(seed))
    last = np.asarray(metrics["iou_sum"])[-10:].sum() / max(1, np.asarray(metrics["episodes"])[-10:].sum())
    print(
        f"trained {CONFIG['TOTAL_TIMESTEPS']:,} steps on {CONFIG['TASK']} (seed {seed}) in "
        f"{time.perf_counter() - start:.0f} s; "
        f"mean IoU of the sampled episodes that ended in the last 10 updates: {last:.3f}"
    )
    print(f"greedy IoU over 100 episodes: {greedy_iou(CONFIG, train_state.params):.3f}")
