"""Soft Actor-Critic for discrete actions (Christodoulou 2019, "Soft Actor-Critic for Discrete
Action Settings"), on the on-device replay loop of `agents.common.offpolicy`.

A categorical actor and two critics (each a Q-value per action) with Polyak-averaged target
copies; the temperature alpha is learned (as log alpha) so that the policy's entropy tends to a
target, a fraction of log|A| (the uniform policy's entropy). With a discrete action set every
expectation over actions is a sum weighted by the policy's probabilities, so no loss samples an
action (`soft_values`, `actor_loss`, `temperature_loss`, pure functions the tests call directly):

- critic: y = n-step return bootstrapped from V(s') = sum_a pi(a|s') [min_i Q_targ,i(s', a) -
  alpha log pi(a|s')], and each critic regresses Q_i(s, a) on y;
- actor: sum_a pi(a|s) [alpha log pi(a|s) - min_i Q_i(s, a)];
- temperature: log alpha (H(pi(.|s)) - target entropy).

`done` (terminated or truncated) cuts the n-step return and its bootstrap, as for the Q-learners:
the step counter is in the observation, so the step limit is part of the observed state.

Exploration samples from the actor, after `learning_starts` env steps of uniformly random actions
(the paper's "start steps"). The greedy policy the evaluator scores is the argmax of the actor's
logits. The networks are feed-forward and read the observation with the previous step
(`ObsLayout.with_previous_step`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from agents.common.inputs import ObsLayout
from agents.common.networks import ObservationEncoder, apply_with_design_cache, scaled_init
from agents.common.offpolicy import ReplayConfig, ReplayLearner, Step, Worlds
from agents.common.targets import n_step_targets
from agents.training.config import option

PARTS = ("actor", "critic", "log_alpha")  # what `params` holds; each part has its own Adam


@dataclasses.dataclass(frozen=True)
class SACConfig(ReplayConfig):
    """SAC-Discrete with twin critics, Polyak-averaged targets and a learned temperature. The
    defaults are the paper's appendix settings where it gives them (learning rate, tau, start
    steps, minibatch size, the 1D network) and Christodoulou's otherwise (one-step targets, target
    entropy 0.98 log|A|)."""

    algorithm: ClassVar[str] = "sac"
    paper_method: ClassVar[str] = "sac"

    num_envs: int = option(64, "parallel worlds per seed (split over devices)", low=1)
    gradient_steps: int = option(8, "gradient steps per learning phase", low=1)
    batch_size: int = option(64, "sampled sequences per gradient step", low=1)
    n_step: int = option(1, "steps of reward before the bootstrap", low=1)
    learning_starts: int = option(
        400, "env steps per seed of uniformly random actions before the actor acts and the first gradient step", low=0
    )
    learning_rate: float = option(
        3e-4, "Adam step size of the actor, the critics and the temperature", low=0, low_open=True
    )
    max_grad_norm: float = option(
        10.0, "gradient norm clip, for each of the actor, the critics and the temperature", low=0, low_open=True
    )
    tau: float = option(
        5e-3,
        "Polyak factor: the target critics move this share toward the critics per gradient step",
        low=0,
        high=1,
        low_open=True,
    )
    target_entropy_fraction: float = option(
        0.98, "the temperature is tuned toward a policy entropy of this times log(number of actions)", low=0, high=1
    )
    initial_alpha: float = option(1.0, "temperature at the start", low=0, low_open=True)
    hidden_sizes: str = option("64,64", "hidden layer widths of the actor and of each critic, comma-separated")

    @property
    def layers(self) -> tuple[int, ...]:
        return tuple(int(width) for width in self.hidden_sizes.split(","))

    def check(self) -> None:
        super().check()
        try:
            ok = all(width > 0 for width in self.layers)
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(
                f"hidden_sizes must be comma-separated ints >= 1 such as '64,128,64', got {self.hidden_sizes!r}"
            )


# --- the losses, pure functions -------------------------------------------------------------------


def _weighted_mean(x: jax.Array, weights: jax.Array) -> jax.Array:
    return (x * weights).sum() / jnp.maximum(weights.sum(), 1.0)


def soft_values(q: jax.Array, log_probs: jax.Array, alpha: jax.Array) -> jax.Array:
    """V(s) = sum_a pi(a|s) [min_i Q_i(s, a) - alpha log pi(a|s)], from the twin critics'
    `q (2, ..., A)` and the policy's `log_probs (..., A)`; shape `(...)`."""
    return (jnp.exp(log_probs) * (q.min(axis=0) - alpha * log_probs)).sum(axis=-1)


def critic_loss(q: jax.Array, actions: jax.Array, targets: jax.Array, weights: jax.Array) -> jax.Array:
    """The squared errors of both critics, summed over the two and averaged over the weighted
    steps: `q (2, ..., A)`, `actions`, `targets` and `weights` of shape `(...)`. The targets are
    held fixed."""
    q_taken = jnp.take_along_axis(q, actions[None, ..., None], axis=-1)[..., 0]
    errors = ((q_taken - jax.lax.stop_gradient(targets)) ** 2).sum(axis=0)
    return _weighted_mean(errors, weights)


def actor_loss(log_probs: jax.Array, q: jax.Array, alpha: jax.Array, weights: jax.Array) -> jax.Array:
    """sum_a pi(a|s) [alpha log pi(a|s) - min_i Q_i(s, a)], averaged over the weighted states:
    `log_probs (..., A)`, `q (2, ..., A)`. Only the policy learns from it (Q and alpha held fixed)."""
    q_min = jax.lax.stop_gradient(q.min(axis=0))
    alpha = jax.lax.stop_gradient(alpha)
    return _weighted_mean((jnp.exp(log_probs) * (alpha * log_probs - q_min)).sum(axis=-1), weights)


def entropy(log_probs: jax.Array) -> jax.Array:
    return -(jnp.exp(log_probs) * log_probs).sum(axis=-1)


def temperature_loss(
    log_alpha: jax.Array, log_probs: jax.Array, target_entropy: float, weights: jax.Array
) -> jax.Array:
    """log alpha (H(pi(.|s)) - target entropy), averaged over the weighted states. Descending it
    lowers alpha while the policy is more random than the target and raises it while it is less;
    only alpha learns from it."""
    gap = jax.lax.stop_gradient(entropy(log_probs)) - target_entropy
    return log_alpha * _weighted_mean(gap, weights)


# --- networks --------------------------------------------------------------------------------------


class ActionHead(nn.Module):
    """One output per action from the encoded observation `(..., O)` through `layers`: the
    actor's logits, or one critic's Q-values."""

    layout: ObsLayout
    num_actions: int
    layers: tuple[int, ...]
    gain: float

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        x = ObservationEncoder(layout=self.layout, hidden_size=self.layers[0], layers=self.layers)(obs)
        return nn.Dense(self.num_actions, kernel_init=scaled_init(self.gain))(x)


class TwinCritic(nn.Module):
    """Two independently initialised `ActionHead`s: `(..., O)` -> Q-values `(2, ..., A)`."""

    layout: ObsLayout
    num_actions: int
    layers: tuple[int, ...]

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        critics = nn.vmap(
            ActionHead, variable_axes={"params": 0}, split_rngs={"params": True}, in_axes=None, out_axes=0, axis_size=2
        )
        return critics(layout=self.layout, num_actions=self.num_actions, layers=self.layers, gain=1.0)(obs)


# --- the algorithm ---------------------------------------------------------------------------------


class SAC(ReplayLearner):
    """Static pieces of a SAC run; see the module docstring. `params` holds the three parts of
    `PARTS`; `target_params` the target critics."""

    def __init__(self, config: SACConfig):
        super().__init__(config)
        num_actions = self.env.num_actions
        # The actor's small output gain makes the first policy nearly uniform.
        self.actor = ActionHead(layout=self.layout, num_actions=num_actions, layers=config.layers, gain=0.01)
        self.critic = TwinCritic(layout=self.layout, num_actions=num_actions, layers=config.layers)
        self.target_entropy = config.target_entropy_fraction * math.log(num_actions)
        part = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.learning_rate))
        self.optimizer = optax.multi_transform({name: part for name in PARTS}, {name: name for name in PARTS})

    # --- hooks of the replay loop ------------------------------------------------------------------

    def init_params(self, key: jax.Array, frames: jax.Array):
        key_actor, key_critic = jax.random.split(key)
        obs = frames[..., 0, :]
        params = {
            "actor": self.actor.init(key_actor, obs),
            "critic": self.critic.init(key_critic, obs),
            "log_alpha": jnp.log(jnp.asarray(self.config.initial_alpha, jnp.float32)),
        }
        return params, params["critic"]

    def action_scores(self, params, carry, frames, resets):
        return carry, self.actor.apply(params["actor"], frames[..., 0, :])

    def act(self, params, worlds: Worlds, frames: jax.Array, keys: jax.Array, env_steps: jax.Array, cache):
        """A sample of the policy, or a uniformly random action before `learning_starts`."""
        key_random, key_policy = keys
        logits, cache = apply_with_design_cache(self.actor, params["actor"], cache, frames[None, :, 0, :])
        sampled = jax.random.categorical(key_policy, logits[0])
        uniform = jax.random.randint(key_random, sampled.shape, 0, self.env.num_actions)
        return worlds.carry, jnp.where(env_steps < self.config.learning_starts, uniform, sampled), cache

    def update_target(self, params, target_params, gradient_step):
        return optax.incremental_update(params["critic"], target_params, self.config.tau)

    # --- learning ----------------------------------------------------------------------------------

    def loss(self, params, target_params, batch: Step, obs, rewards, mask):
        """The three losses summed: each holds everything but its own part fixed, so the
        gradient of the sum is the three parts' gradients side by side."""
        cfg = self.config
        length, c = cfg.sequence_length, cfg.context
        inputs = self.network_inputs(obs, batch.action, batch.reset)[c:]  # (length + n, S, O), 0 = row c
        log_probs = jax.nn.log_softmax(self.actor.apply(params["actor"], inputs))
        q = self.critic.apply(params["critic"], inputs[:length])  # (2, length, S, A)
        q_next = self.critic.apply(target_params, inputs)
        alpha = jnp.exp(params["log_alpha"])
        values = soft_values(q_next, jax.lax.stop_gradient(log_probs), jax.lax.stop_gradient(alpha))
        targets = n_step_targets(rewards[c:] * cfg.reward_scale, batch.done[c:], values, cfg.gamma, cfg.n_step, length)
        actions = batch.action[c : c + length].astype(jnp.int32)
        weights = mask[c : c + length]
        learned = log_probs[:length]
        losses = {
            "critic_loss": critic_loss(q, actions, targets, weights),
            "actor_loss": actor_loss(learned, q, alpha, weights),
            "alpha_loss": temperature_loss(params["log_alpha"], learned, self.target_entropy, weights),
        }
        total = sum(losses.values())
        q_taken = jnp.take_along_axis(q.min(axis=0), actions[..., None], axis=-1)[..., 0]
        return total, {
            "loss": total,
            **losses,
            "alpha": alpha,
            "entropy": _weighted_mean(entropy(learned), weights),
            "q_mean": _weighted_mean(q_taken, weights),
        }
