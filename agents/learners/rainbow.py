"""Rainbow (Hessel et al. 2018) as the paper's appendix configures it: the DQN of `agents.learners.dqn` with
a distributional (C51) dueling head of 101 atoms on [-5, 35], factorised noisy layers (sigma0 = 0.1)
that explore instead of epsilon-greedy, 3-step returns, double-Q bootstrap actions, and prioritised
replay (priority exponent 0.5; importance-sampling exponent 0.4, annealed to 1 over training) in a
buffer of 10^4 steps; learning rate 5e-5 in 1D and 2D, 1e-4 in 3D (agents/tuned/rainbow.toml).

The replay loop (`agents.common.offpolicy`), epsilon-greedy acting, the replayed windows (previous-step
inputs, episode boundaries, the n steps to bootstrap from) and the greedy policy are DQN's. Rainbow
changes the network (`make_network`: noisy layers, `atoms` logits per action), the replay
(`make_buffer`: flashbax's prioritised trajectory buffer), how Q-values are read (`q_values`: each
action's expected return, under fresh noise for each world when acting, `acting_scores`; from the
noise-free mean network for the greedy policy, `action_scores`) and the learning step
(`gradient_step`: prioritised sampling, importance weights, new priorities; the optimiser step and
target copy are the replay loop's `apply_gradients`).

The loss of a sampled window is the KL divergence from the projected n-step target distribution
(`agents.common.targets.categorical_projection`) to the predicted one, weighted by the window's
importance-sampling weight; that KL is the window's new priority, as in Rainbow. With
`cross_entropy_priority` the priority is the cross-entropy instead (the KL plus the target's
entropy, which has no gradient), as Dopamine and the paper's own code prioritise: a window whose
target is spread out then keeps a higher priority after it is learnt.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import flashbax as fbx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.scipy.special import xlogy

from agents.common.networks import QNetwork, apply_with_design_cache
from agents.common.offpolicy import RunnerState, Step
from agents.common.targets import categorical_projection, n_step_returns
from agents.learners.dqn import DQN, DQNConfig
from agents.training.config import option

# Added to every priority: a window whose KL is 0 would otherwise never be drawn again.
PRIORITY_FLOOR = 1e-6


@dataclasses.dataclass(frozen=True)
class RainbowConfig(DQNConfig):
    """Defaults are the paper's Rainbow settings. Those it does not give are DQN's, with the tuned
    DQN's flow of data (64 worlds, 2 gradient steps per 8 steps of every world: each step is
    sampled about once) rather than its class defaults (256 worlds, 1 gradient step)."""

    algorithm: ClassVar[str] = "rainbow"
    paper_method: ClassVar[str] = "rainbow"

    v_min: float = option(-5.0, "lowest return of the value distribution's support")
    v_max: float = option(35.0, "highest return of the value distribution's support")
    atoms: int = option(101, "atoms of the support, evenly spaced from v_min to v_max", low=2)
    noisy: bool = option(True, "factorised noisy layers explore (without: plain layers, epsilon-greedy from eps_start)")
    sigma0: float = option(0.1, "noisy layers' initial noise scale: sigma = sigma0 / sqrt(fan_in)", low=0)
    priority_exponent: float = option(
        0.5, "replay draws a window with probability ~ priority ** this (0: uniform)", low=0, high=1
    )
    importance_exponent: float = option(
        0.4, "importance-sampling exponent at the start, annealed linearly to 1 over total_steps", low=0, high=1
    )
    cross_entropy_priority: bool = option(
        False,
        "a window's new priority is its cross-entropy to the target (Dopamine, the paper's code) rather than its KL",
    )
    buffer_size: int = option(10_000, "replay capacity in env steps, over all worlds of a seed", low=1)
    num_envs: int = option(64, "parallel worlds per seed (split over devices)", low=1)
    gradient_steps: int = option(2, "gradient steps per learning phase", low=1)
    learning_rate: float = option(5e-5, "Adam step size", low=0, low_open=True)
    eps_start: float = option(0.0, "epsilon-greedy on top of the noisy layers, at the start (0: none)", low=0, high=1)
    eps_end: float = option(0.0, "epsilon-greedy on top of the noisy layers, after the decay", low=0, high=1)
    huber_delta: float = option(1.0, "not used: Rainbow's loss is a KL divergence", low=0, low_open=True, cli=False)

    def check(self) -> None:
        super().check()
        if self.v_min >= self.v_max:
            raise ValueError(f"v_min ({self.v_min}) must be below v_max ({self.v_max})")


def importance_weights(probabilities: jax.Array, beta: jax.Array) -> jax.Array:
    """Prioritised replay's importance-sampling weights of a sampled batch (Schaul et al. 2016):
    w_i = (N P(i))^-beta / max_j w_j. The buffer's size N cancels, leaving (min_j P(j) / P(i))^beta.
    A window drawn at probability 0 (float rounding in the sum tree can land on an item that is no
    longer valid) gets weight 0."""
    valid = probabilities > 0
    smallest = jnp.min(jnp.where(valid, probabilities, jnp.inf))
    return jnp.where(valid, (smallest / jnp.where(valid, probabilities, 1.0)) ** beta, 0.0)


def cross_entropy_and_kl(target: jax.Array, logits: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The cross-entropy and the KL divergence from distributions `target` (..., atoms) to the
    softmax of `logits`; they differ by the target's entropy (taken as 0 log 0 = 0)."""
    cross_entropy = -(target * jax.nn.log_softmax(logits)).sum(axis=-1)
    return cross_entropy, cross_entropy + xlogy(target, target).sum(axis=-1)


class Rainbow(DQN):
    acting_keys = 3  # DQN's two for epsilon-greedy, and one for the noisy layers' noise

    def __init__(self, config: RainbowConfig):
        super().__init__(config)
        self.support = jnp.asarray(np.linspace(config.v_min, config.v_max, config.atoms, dtype=np.float32))
        self.beta = optax.linear_schedule(config.importance_exponent, 1.0, config.total_steps)

    def make_network(self) -> QNetwork:
        cfg = self.config
        return super().make_network().clone(atoms=cfg.atoms, noisy=cfg.noisy, sigma0=cfg.sigma0)

    def make_buffer(self):
        cfg = self.config
        return fbx.make_prioritised_trajectory_buffer(
            add_batch_size=cfg.num_envs,
            sample_batch_size=cfg.batch_size,
            sample_sequence_length=cfg.sample_length,
            period=1,
            min_length_time_axis=cfg.sample_length,
            max_length_time_axis=self.per_world,
            priority_exponent=cfg.priority_exponent,
            # flashbax picks how it writes a batch of priorities by device (a scan on CPU).
            device=jax.default_backend() if jax.default_backend() in ("gpu", "tpu") else "cpu",
        )

    # --- the network -------------------------------------------------------------------------------

    def logits(
        self,
        params,
        carry: jax.Array,
        frames: jax.Array,
        resets: jax.Array,
        key: jax.Array | None = None,
        per_world: bool = False,
    ):
        """`(carry, logits (T, B, A, atoms))`; with `key` the noisy layers draw fresh noise from it
        (one draw for the batch, or with `per_world` one per step and world), without it they are
        their mean."""
        return self.network.apply(params, carry, frames, resets, **self._noise(key, per_world))

    def _noise(self, key: jax.Array | None, per_world: bool) -> dict:
        """The network's keyword arguments for a noise draw from `key` (none: the mean network)."""
        if key is None or not self.config.noisy:
            return {}
        return {"noise": True, "noise_per_world": per_world, "rngs": {"noise": key}}

    def expected(self, logits: jax.Array) -> jax.Array:
        """Each action's expected return under its predicted distribution."""
        return (jax.nn.softmax(logits) * self.support).sum(axis=-1)

    def q_values(
        self,
        params,
        carry: jax.Array,
        frames: jax.Array,
        resets: jax.Array,
        key: jax.Array | None = None,
        per_world: bool = False,
    ):
        """`(carry, Q-values (T, B, A))`; `key` draws a noisy network's noise, None: its mean (greedy)."""
        carry, logits = self.logits(params, carry, frames, resets, key, per_world)
        return carry, self.expected(logits)

    def action_scores(self, params, carry, frames, resets):
        return self.q_values(params, carry, frames, resets)

    def acting_scores(self, params, carry, frames, resets, keys: jax.Array, cache):
        """Q-values under noise drawn for each world apart. Why: one draw for all worlds perturbs
        every world the same way, and at sigma0 = 0.1 that rarely changes the mean network's
        choice, so all worlds took the same action (bench/results/rainbow.md)."""
        noise = self._noise(keys[0], per_world=True)
        (carry, logits), cache = apply_with_design_cache(self.network, params, cache, carry, frames, resets, **noise)
        return (carry, self.expected(logits)), cache

    # --- learning ----------------------------------------------------------------------------------

    def window_logits(
        self, params, target_params, frames: jax.Array, resets: jax.Array, key_online: jax.Array, key_target: jax.Array
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Logits `(length, S, A, atoms)` along a replayed window of `length + n` rows (row 0 = the
        batch's row `context`): the online network's at the learning rows `[0, length)`, and, under
        `stop_gradient`, the online and the target network's at the rows n steps later `[n, n + length)`.

        Why not all rows: the network is feed-forward (DQN's, without the LSTM), so each row is read
        alone and only these need computing. The rows in between feed nothing to the loss, yet
        computing them, and their zero gradients, was most of a gradient step's cost. Each network
        draws one noise for the whole batch, so splitting the rows over calls with the same key
        computes the same function."""
        cfg = self.config
        length, n = cfg.sequence_length, cfg.n_step
        carry = self.network.initial_carry(frames.shape[1])
        _, learning = self.logits(params, carry, frames[:length], resets[:length], key_online)
        _, bootstrap_online = self.logits(params, carry, frames[n:], resets[n:], key_online)
        _, bootstrap_target = self.logits(target_params, carry, frames[n:], resets[n:], key_target)
        return learning, jax.lax.stop_gradient(bootstrap_online), jax.lax.stop_gradient(bootstrap_target)

    def loss(
        self, params, target_params, batch: Step, weights: jax.Array, key_online: jax.Array, key_target: jax.Array
    ):
        """`(loss, (metrics, per-window priority))` of a time-major batch `(L, S)` with importance
        weights `(S,)`. The online and the target network draw independent noise. The priority is
        the window's mean KL, or its mean cross-entropy with `cross_entropy_priority`."""
        cfg = self.config
        length, c, n = cfg.sequence_length, cfg.context, cfg.n_step
        frames, resets = self.replayed_frames(batch, batch.obs.astype(jnp.float32))
        learning, bootstrap_online, bootstrap_target = self.window_logits(
            params, target_params, frames, resets, key_online, key_target
        )
        greedy_from = bootstrap_online if cfg.double_q else bootstrap_target
        next_action = jnp.argmax(self.expected(greedy_from), axis=-1)  # (length, S)
        next_probs = jax.nn.softmax(
            jnp.take_along_axis(bootstrap_target, next_action[..., None, None], axis=-2)[..., 0, :]
        )
        returns, discounts = n_step_returns(batch.reward[c:] * cfg.reward_scale, batch.done[c:], cfg.gamma, n, length)
        target = jax.lax.stop_gradient(categorical_projection(self.support, next_probs, returns, discounts))

        actions = batch.action[c : c + length].astype(jnp.int32)
        taken = jnp.take_along_axis(learning, actions[..., None, None], axis=-2)[..., 0, :]  # (length, S, atoms)
        cross_entropy, kl = cross_entropy_and_kl(target, taken)  # (length, S)
        loss = (weights * kl.mean(axis=0)).mean()
        priority = (cross_entropy if cfg.cross_entropy_priority else kl).mean(axis=0)  # (S,)
        return loss, ({"loss": loss, "q_mean": self.expected(taken).mean()}, priority)

    def gradient_step(self, state: RunnerState) -> tuple[RunnerState, dict]:
        """Sample windows by priority, take a step on the importance-weighted loss, and give each
        sampled window the priority `loss` computed for it (its KL, or its cross-entropy)."""
        key, key_sample, key_online, key_target = jax.random.split(state.key, 4)
        sample = self.buffer.sample(state.buffer, key_sample)
        batch = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), sample.experience)
        weights = importance_weights(sample.probabilities, self.beta(state.env_steps))
        (_, (info, priority)), grads = jax.value_and_grad(self.loss, has_aux=True)(
            state.params, state.target_params, batch, weights, key_online, key_target
        )
        state = self.apply_gradients(state.replace(key=key), grads)
        priorities = jnp.where(sample.probabilities > 0, jnp.maximum(priority, 0.0) + PRIORITY_FLOOR, 0.0)
        return state.replace(buffer=self.buffer.set_priorities(state.buffer, sample.indices, priorities)), info
