"""A standalone recurrent PPO on a SNAC task in one file, PureJaxRL-shaped (its `ppo_rnn.py`):
`make_train(config)` returns a pure `train(key)` that builds a GRU actor-critic, steps every
world, computes GAE and runs the clipped updates on whole rollout sequences inside one `jit`. It
reads nothing from this repository's learners (`agents/`), only the environment library
`snac_jax`, so it is the file to copy to start a recurrent learner of your own; the feed-forward
one is `examples/ppo_standalone.py`.

    python examples/ppo_rnn_standalone.py      # 1d-static-sin, 3M env steps

Why a memory: the robot never sees where it stands (SPEC §6), so a policy that reads only the
current window must guess it; the GRU can carry what the episode has shown so far. Two details
matter on SNAC and are easy to get wrong:

- Resets: SNAC's step resets an ended episode itself, so the observation after an ending is the
  next episode's first. The GRU's state is zeroed there (`ScannedRNN`, from the `start` flag each
  step carries), in the rollout and when the loss replays the sequence, so no memory leaks from
  one episode into the next.
- Truncations: an episode cut at the step limit did not end in the task's terms, so its last
  reward is bootstrapped from the value of `info["final_observation"]` (the observation before
  the auto-reset), scored with the GRU state that saw the episode; a termination bootstraps
  nothing. Treating the limit as an ending would teach the value that the world stops there.

Measured (this file's CONFIG, key 0, on a two-core CPU shared with other jobs; `python
examples/ppo_rnn_standalone.py`): 3M env steps in 3.9 minutes of training; the sampled episodes
that ended in the last 10 updates averaged IoU 0.699, and the greedy policy scores 0.589 over 100
episodes. The tuned recurrent learners of `agents/` train far longer (bench/results/table.md).
"""

from __future__ import annotations

import functools
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
    "TOTAL_TIMESTEPS": 3_000_000,
    "UPDATE_EPOCHS": 4,
    "NUM_MINIBATCHES": 4,
    "LR": 1e-3,
    "GAMMA": 0.99,
    "GAE_LAMBDA": 0.95,
    "CLIP_EPS": 0.2,
    "ENT_COEF": 0.01,
    "ENT_COEF_END": 0.0,
    "VF_COEF": 0.5,
    "MAX_GRAD_NORM": 0.5,
    "REWARD_SCALE": 0.1,
    "HIDDEN": 64,
}


class ScannedRNN(nn.Module):
    """A GRU over time whose state is zeroed where `start` marks an episode's first step."""

    hidden: int

    @functools.partial(nn.scan, variable_broadcast="params", in_axes=0, out_axes=0, split_rngs={"params": False})
    @nn.compact
    def __call__(self, carry, step):
        x, start = step
        carry = jnp.where(start[:, None], jnp.zeros_like(carry), carry)
        return nn.GRUCell(self.hidden)(carry, x)


class ActorCriticRNN(nn.Module):
    """Dense embedding, GRU, then action logits and the state value. Time-major: `carry (B, H)`,
    `x (T, B, F)`, `start (T, B)`."""

    num_actions: int
    hidden: int

    @nn.compact
    def __call__(self, carry, x, start):
        dense = lambda n, scale: nn.Dense(n, kernel_init=nn.initializers.orthogonal(scale))
        embedding = nn.relu(dense(self.hidden, np.sqrt(2))(x))
        carry, embedding = ScannedRNN(self.hidden)(carry, (embedding, start))
        logits = dense(self.num_actions, 0.01)(nn.relu(dense(self.hidden, np.sqrt(2))(embedding)))
        value = dense(1, 1.0)(nn.relu(dense(self.hidden, np.sqrt(2))(embedding)))[..., 0]
        return carry, logits, value


def inputs(obs, last_action, num_actions):
    """What the network reads: the observation and the last action one-hot (its last slot "none"
    at an episode's first step). The action tells the GRU which way the window just shifted."""
    return jnp.concatenate([obs, jax.nn.one_hot(last_action, num_actions + 1)], axis=-1)


def bootstrapped_reward(reward, terminated, truncated, final_value, config):
    """The scaled reward, plus the discounted value of the final observation where the step limit
    cut the episode (truncated, not terminated): the return it would have gone on to earn."""
    cut = truncated & ~terminated
    return reward * config["REWARD_SCALE"] + config["GAMMA"] * jnp.where(cut, final_value, 0.0)


class Transition(NamedTuple):
    x: jax.Array  # the network's inputs
    start: jax.Array  # the observation is an episode's first: the GRU's state is zeroed before it
    action: jax.Array
    log_prob: jax.Array
    value: jax.Array
    reward: jax.Array  # scaled, plus gamma * V(final observation) where the step limit cut the episode
    done: jax.Array  # the episode ended here (terminated or truncated): nothing flows back across it
    iou: jax.Array  # the episode's final IoU where `done`


def make_train(config):
    env, env_params = snac_jax.make(config["TASK"], **config["ENV_KWARGS"])
    num_updates = config["TOTAL_TIMESTEPS"] // (config["NUM_ENVS"] * config["NUM_STEPS"])
    num_actions, n = env.num_actions, config["NUM_ENVS"]
    network = ActorCriticRNN(num_actions, config["HIDDEN"])
    step = jax.vmap(env.step, in_axes=(0, 0, 0, None))  # SNAC's step resets an ended episode itself

    def train(key):
        key, key_init, key_reset = jax.random.split(key, 3)
        obs, env_state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, n), env_params)
        none = jnp.full((n,), num_actions)  # "no last action" at an episode's start
        carry = jnp.zeros((n, config["HIDDEN"]))
        schedule = optax.linear_schedule(
            config["LR"], 0.0, num_updates * config["UPDATE_EPOCHS"] * config["NUM_MINIBATCHES"]
        )
        train_state = TrainState.create(
            apply_fn=network.apply,
            params=network.init(key_init, carry, inputs(obs, none, num_actions)[None], jnp.ones((1, n), bool)),
            tx=optax.chain(optax.clip_by_global_norm(config["MAX_GRAD_NORM"]), optax.adam(schedule, eps=1e-5)),
        )

        def env_step(runner, _):
            train_state, env_state, obs, last_action, start, carry, key = runner
            key, key_act, key_step = jax.random.split(key, 3)
            x = inputs(obs, last_action, num_actions)
            carry, logits, value = network.apply(train_state.params, carry, x[None], start[None])
            pi = distrax.Categorical(logits=logits[0])
            action = pi.sample(seed=key_act)
            next_obs, env_state, reward, terminated, truncated, info = step(
                jax.random.split(key_step, n), env_state, action, env_params
            )
            # The value of where a cut episode stood, read with the memory that saw it.
            final_x = inputs(info["final_observation"], action, num_actions)
            _, _, final_value = network.apply(train_state.params, carry, final_x[None], jnp.zeros((1, n), bool))
            reward = bootstrapped_reward(reward, terminated, truncated, final_value[0], config)
            done = terminated | truncated
            transition = Transition(x, start, action, pi.log_prob(action), value[0], reward, done, info["final_iou"])
            runner = (train_state, env_state, next_obs, jnp.where(done, num_actions, action), done, carry, key)
            return runner, transition

        def gae(batch, last_value):
            def backwards(carry, t):
                advantage, next_value = carry
                delta = t.reward + config["GAMMA"] * next_value * (1 - t.done) - t.value
                advantage = delta + config["GAMMA"] * config["GAE_LAMBDA"] * (1 - t.done) * advantage
                return (advantage, t.value), advantage

            _, advantages = jax.lax.scan(backwards, (jnp.zeros_like(last_value), last_value), batch, reverse=True)
            return advantages, advantages + batch.value

        def loss_fn(params, carry0, batch, advantages, targets, ent_coef):
            _, logits, value = network.apply(params, carry0, batch.x, batch.start)  # the sequence replayed
            pi = distrax.Categorical(logits=logits)
            ratio = jnp.exp(pi.log_prob(batch.action) - batch.log_prob)
            advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
            clip = config["CLIP_EPS"]
            actor = -jnp.minimum(ratio * advantages, jnp.clip(ratio, 1 - clip, 1 + clip) * advantages).mean()
            value_clipped = batch.value + jnp.clip(value - batch.value, -clip, clip)
            critic = 0.5 * jnp.maximum((value - targets) ** 2, (value_clipped - targets) ** 2).mean()
            return actor + config["VF_COEF"] * critic - ent_coef * pi.entropy().mean()

        def update(runner, progress):
            # The entropy bonus anneals to ENT_COEF_END, so that the greedy policy scored at the end
            # takes the actions the sampled one settled on.
            ent_coef = config["ENT_COEF"] + progress * (config["ENT_COEF_END"] - config["ENT_COEF"])
            carry0 = runner[5]  # each world's GRU state at the rollout's start: the loss replays from it
            runner, batch = jax.lax.scan(env_step, runner, None, config["NUM_STEPS"])
            train_state, _, obs, last_action, start, carry, key = runner
            _, _, last_value = network.apply(
                train_state.params, carry, inputs(obs, last_action, num_actions)[None], start[None]
            )
            advantages, targets = gae(batch, last_value[0])

            def epoch(carry, _):
                train_state, key = carry
                key, key_perm = jax.random.split(key)
                order = jax.random.permutation(key_perm, n)

                def split(x, axis):  # shuffle the worlds, cut them into minibatches along a new axis 0
                    x = jnp.take(x, order, axis=axis)
                    x = x.reshape(x.shape[:axis] + (config["NUM_MINIBATCHES"], -1) + x.shape[axis + 1 :])
                    return jnp.moveaxis(x, axis, 0)

                minibatches = (split(carry0, 0), *jax.tree.map(lambda x: split(x, 1), (batch, advantages, targets)))

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
            return (train_state, *runner[1:6], key), metrics

        progress = jnp.linspace(0.0, 1.0, num_updates)
        runner = (train_state, env_state, obs, none, jnp.ones((n,), bool), carry, key)
        runner, metrics = jax.lax.scan(update, runner, progress)
        return runner[0], metrics

    return train


def greedy_iou(config, params, episodes: int = 100, seed: int = 0) -> float:
    """The mean final IoU of the greedy (argmax) policy over `episodes` episodes, its GRU state
    carried from step to step as the policy's memory."""
    env, env_params = snac_jax.make(config["TASK"], **config["ENV_KWARGS"])
    network = ActorCriticRNN(env.num_actions, config["HIDDEN"])

    def init(key, design):  # an empty memory, "no last action", and the episode's first step ahead
        return jnp.zeros(config["HIDDEN"]), jnp.int32(env.num_actions), jnp.bool_(True)

    def act(params, policy_state, obs, key):
        carry, last_action, start = policy_state
        x = inputs(obs, last_action, env.num_actions)
        carry, logits, _ = network.apply(params, carry[None], x[None, None], start[None, None])
        action = jnp.argmax(logits[0, 0]).astype(jnp.int32)
        return action, (carry[0], action, jnp.bool_(False))

    policy = Policy(init=init, act=act, params=params, name="ppo-rnn-standalone")
    outcomes = run_episodes(env, env_params, policy, jax.random.key(seed), np.zeros(episodes, np.int32))
    return float(outcomes.iou.mean())


if __name__ == "__main__":
    start = time.perf_counter()
    train_state, metrics = jax.jit(make_train(CONFIG))(jax.random.key(0))
    jax.block_until_ready(metrics)
    minutes = (time.perf_counter() - start) / 60
    last = np.asarray(metrics["iou_sum"])[-10:].sum() / max(1, np.asarray(metrics["episodes"])[-10:].sum())
    print(
        f"trained {CONFIG['TOTAL_TIMESTEPS']:,} steps on {CONFIG['TASK']} in {minutes:.1f} min; "
        f"mean IoU of the sampled episodes that ended in the last 10 updates: {last:.3f}"
    )
    print(f"greedy IoU over 100 episodes: {greedy_iou(CONFIG, train_state.params):.3f}")
