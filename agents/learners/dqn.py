"""DQN: acting epsilon-greedily into a replay buffer on device and learning from sampled windows,
in one jitted loop (`agents.common.offpolicy` holds the loop, the buffer and the sampling). DRQN
(`agents.learners.drqn`), DRQN + hindsight (`agents.learners.drqn_her`) and Rainbow (`agents.learners.rainbow`) extend the
`DQN` class here by overriding its steps.

The Q-network reads a stack of the last `frame_stack` inputs and, with DRQN, runs an LSTM whose
burn-in steps only warm its state (their output carry is cut from the gradient). Targets are
n-step returns (`agents.common.targets.n_step_targets`) bootstrapped from the target network, which is a
copy of the online network taken every `target_update_interval` gradient steps.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import optax

from agents.common.networks import QNetwork, apply_with_design_cache, stack_frames
from agents.common.offpolicy import ReplayConfig, ReplayLearner, Step, Worlds
from agents.common.targets import n_step_targets
from agents.training.config import option


@dataclasses.dataclass(frozen=True)
class DQNConfig(ReplayConfig):
    """DQN with double Q-learning, a dueling head, n-step returns and an optional stack of the
    last `frame_stack` observations."""

    algorithm: ClassVar[str] = "dqn"
    paper_method: ClassVar[str] = "dqn"

    learning_rate: float = option(3e-4, "Adam step size", low=0, low_open=True)
    anneal_lr: bool = option(False, "decay the learning rate linearly to 0 over the run's gradient steps")
    huber_delta: float = option(1.0, "Huber loss threshold", low=0, low_open=True)
    max_grad_norm: float = option(10.0, "global gradient norm clip", low=0, low_open=True)
    eps_start: float = option(1.0, "exploration rate at the start", low=0, high=1)
    eps_end: float = option(0.05, "exploration rate after the decay", low=0, high=1)
    exploration_fraction: float = option(0.3, "share of total_steps over which epsilon decays linearly", low=0, high=1)
    target_update_interval: int = option(250, "gradient steps between copies into the target network", low=1)
    hidden_size: int = option(128, "width of the encoder and the heads", low=1)
    dueling: bool = option(True, "separate value and advantage heads")
    layer_norm: bool = option(False, "LayerNorm before every hidden ReLU of the network (as PQN's)")
    double_q: bool = option(True, "the online network picks the bootstrap action")
    frame_stack: int = option(1, "observations the network reads at once (the newest and those before it)", low=1)

    @property
    def context(self) -> int:
        """The previous step's row and the frame stack's earlier frames (DRQN adds its burn-in)."""
        return super().context + self.frame_stack - 1


class DQN(ReplayLearner):
    """Static pieces of a DQN run; see the module docstring. Subclasses change the network core
    (`lstm_size`, `burn_in`), the whole network (`make_network`) and the Q-values it acts on
    (`acting_scores`)."""

    lstm_size = 0  # feed-forward
    burn_in = 0

    def __init__(self, config: DQNConfig):
        self.frame_stack = config.frame_stack
        super().__init__(config)
        self.network = self.make_network()
        self.optimizer = optax.chain(
            optax.clip_by_global_norm(config.max_grad_norm), optax.adam(self.learning_rate_schedule(), eps=1e-5)
        )
        self.epsilon = optax.linear_schedule(
            config.eps_start, config.eps_end, max(1, int(config.exploration_fraction * config.total_steps))
        )

    def learning_rate_schedule(self):
        """The step size: constant, or with `anneal_lr` decaying linearly to 0 over every gradient
        step the run would take if it learned from its first update (learning starts a little
        later, so it ends just above 0). Why: it keeps late updates small, one way to keep a
        learned policy from drifting; bench/results/rainbow.md records what it did for Rainbow."""
        cfg = self.config
        if not cfg.anneal_lr:
            return cfg.learning_rate
        return optax.linear_schedule(cfg.learning_rate, 0.0, cfg.num_updates * cfg.gradient_steps)

    def make_network(self) -> QNetwork:
        cfg = self.config
        return QNetwork(
            layout=self.layout,
            num_actions=self.env.num_actions,
            hidden_size=cfg.hidden_size,
            lstm_size=self.lstm_size,
            dueling=cfg.dueling,
            layer_norm=cfg.layer_norm,
        )

    # --- hooks of the replay loop ----------------------------------------------------------------

    def initial_carry(self, batch: int) -> jax.Array:
        return self.network.initial_carry(batch)

    def init_params(self, key: jax.Array, frames: jax.Array):
        params = self.network.init(key, self.initial_carry(1), frames, jnp.ones((1, 1), bool))
        return params, params

    def action_scores(self, params, carry, frames, resets):
        return self.network.apply(params, carry, frames, resets)

    def acting_scores(self, params, carry, frames, resets, keys: jax.Array, cache):
        """`((carry, Q-values), cache)`: the Q-values `act` is epsilon-greedy on, given the
        `acting_keys` beyond its own two and the design cache (`apply_with_design_cache`)."""
        return apply_with_design_cache(self.network, params, cache, carry, frames, resets)

    def act(self, params, worlds: Worlds, frames: jax.Array, keys: jax.Array, env_steps: jax.Array, cache):
        """Epsilon-greedy on the Q-values (`acting_scores`)."""
        n = self.config.num_envs
        key_explore, key_random = keys[0], keys[1]
        (carry, q), cache = self.acting_scores(params, worlds.carry, frames[None], worlds.reset[None], keys[2:], cache)
        explore = jax.random.uniform(key_explore, (n,)) < self.epsilon(env_steps)
        action = jnp.where(explore, jax.random.randint(key_random, (n,), 0, self.env.num_actions), jnp.argmax(q[0], -1))
        return carry, action, cache

    def update_target(self, params, target_params, gradient_step):
        return optax.periodic_update(params, target_params, gradient_step, self.config.target_update_interval)

    def acting_metrics(self, env_steps):
        return {"epsilon": self.epsilon(env_steps)}

    # --- learning ----------------------------------------------------------------------------------

    def burned_in_carry(self, params, frames: jax.Array, resets: jax.Array) -> jax.Array:
        """The LSTM state after a sampled window's burn-in steps, from a zero state and cut from
        the gradient (the burn-in only warms the state)."""
        carry = self.network.initial_carry(frames.shape[1])
        if self.burn_in:
            carry, _ = self.network.apply(params, carry, frames[: self.burn_in], resets[: self.burn_in])
            carry = jax.lax.stop_gradient(carry)
        return carry

    def sequence_q(self, params, frames: jax.Array, resets: jax.Array) -> jax.Array:
        """Q-values `(T - burn_in, S, A)` of a sampled window after its burn-in."""
        carry = self.burned_in_carry(params, frames, resets)
        _, q = self.network.apply(params, carry, frames[self.burn_in :], resets[self.burn_in :])
        return q

    def replayed_frames(self, batch: Step, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """`(frames, resets)` the network reads along a sampled window, from the row after the
        previous step's and the frame stack's context (that first row only lends its window and action)."""
        k, p = self.config.frame_stack, int(self.config.previous_step)
        inputs = self.network_inputs(obs, batch.action, batch.reset)[p:]
        return stack_frames(inputs, batch.reset[p:], k), batch.reset[p + k - 1 :]

    def loss(self, params, target_params, batch: Step, obs, rewards, mask):
        frames, resets = self.replayed_frames(batch, obs)
        q = self.sequence_q(params, frames, resets)  # (length + n, S, A), index 0 = batch index c
        return self.td_loss(q, target_params, frames, resets, batch, rewards, mask)

    def td_loss(self, q, target_params, frames, resets, batch: Step, rewards, mask) -> tuple[jax.Array, dict]:
        """The masked Huber loss of the online Q-values `q` of a window against its n-step
        double-Q targets from the target network."""
        cfg = self.config
        length, c = cfg.sequence_length, cfg.context
        q_target = jax.lax.stop_gradient(self.sequence_q(target_params, frames, resets))
        greedy_from = jax.lax.stop_gradient(q) if cfg.double_q else q_target
        next_action = jnp.argmax(greedy_from, axis=-1)
        values = jnp.take_along_axis(q_target, next_action[..., None], axis=-1)[..., 0]
        targets = n_step_targets(rewards[c:] * cfg.reward_scale, batch.done[c:], values, cfg.gamma, cfg.n_step, length)
        actions = batch.action[c : c + length].astype(jnp.int32)
        q_taken = jnp.take_along_axis(q[:length], actions[..., None], axis=-1)[..., 0]
        weights = mask[c : c + length]
        errors = optax.huber_loss(q_taken, jax.lax.stop_gradient(targets), delta=cfg.huber_delta)
        loss = (errors * weights).sum() / jnp.maximum(weights.sum(), 1.0)
        info = {"loss": loss, "q_mean": (q_taken * weights).sum() / jnp.maximum(weights.sum(), 1.0)}
        return loss, info
