"""Network pieces shared by every learner: observation layout and scaling, the design encoder,
a GRU or LSTM scanned over time with resets at episode boundaries, and the actor-critic heads.

Every network takes time-major inputs `(T, B, obs_size)` with `resets (T, B)` (True where the
observation starts a new episode) and a carry `(B, carry_size)`, and returns the new carry.
Feed-forward networks ignore the carry (a `(B, 1)` placeholder), so one training loop serves both.

Observation scaling lives here, not in the environment: raw counters reach 1300 and heights 57.

Initialisers are variance-scaling ones, never orthogonal: orthogonal init inside a jit vmapped
over seeds deadlocked on 2 CPU cores.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.env import SNACEnv
from snac_jax.state import EnvParams


def scaled_init(gain: float) -> nn.initializers.Initializer:
    """Fan-in scaled normal with the variance an orthogonal init of this gain would give."""
    return nn.initializers.variance_scaling(gain**2, "fan_in", "truncated_normal")


@dataclasses.dataclass(frozen=True)
class ObsLayout:
    """Where each part of the flat observation (SPEC §6) sits, and how to scale it to ~[-1, 1]."""

    window_shape: tuple[int, int]
    plan_shape: tuple[int, int]
    dynamic: bool
    gps: bool
    height_scale: float  # the tallest design cell (1 in 2D)
    brick_scale: float  # the largest brick budget
    step_scale: float  # the step limit
    # > 0: the learner appends the previous step to the environment's observation: the window
    # before the last action, and that action one-hot in `num_actions + 1` entries
    # (`with_previous_step`).
    num_actions: int = 0

    @classmethod
    def from_env(cls, env: SNACEnv, params: EnvParams, previous_step: bool = False) -> "ObsLayout":
        config = env.config
        return cls(
            window_shape=config.window_shape,
            plan_shape=config.plan_shape,
            dynamic=config.dynamic,
            gps=config.gps,
            height_scale=float(max(1, int(np.max(np.asarray(params.designs))))),
            brick_scale=float(max(1, int(np.max(np.asarray(params.design_max_bricks))))),
            step_scale=float(int(params.max_steps_in_episode)),
            num_actions=env.num_actions if previous_step else 0,
        )

    @property
    def window_size(self) -> int:
        return self.window_shape[0] * self.window_shape[1]

    @property
    def design_size(self) -> int:
        return self.plan_shape[0] * self.plan_shape[1]

    @property
    def env_obs_size(self) -> int:
        """The environment's observation (SPEC §6)."""
        gps_size = (1 if self.plan_shape[0] == 1 else 2) if self.gps else 0
        return self.window_size + 2 + (self.design_size if self.dynamic else 0) + gps_size

    @property
    def previous_step_size(self) -> int:
        return self.window_size + self.num_actions + 1 if self.num_actions else 0

    @property
    def obs_size(self) -> int:
        """What the network reads: the environment's observation (+ the previous step)."""
        return self.env_obs_size + self.previous_step_size

    def with_previous_step(
        self, obs: jax.Array, previous_obs: jax.Array, last_action: jax.Array, reset: jax.Array
    ) -> jax.Array:
        """Append to `obs (..., env_obs_size)` the window of `previous_obs` and the one-hot of
        `last_action`; where `reset` (an episode's first observation) there is no previous step:
        the window repeats the current one and the action is "none" (index `num_actions`).

        Why: the robot localises by how its window shifted after a move (SPEC §11). A recurrent
        policy that samples its actions cannot tell from its own state which one was drawn, and
        comparing two windows is far easier side by side than through a recurrent state. PPO on
        1d-static-sin, same settings and budget: greedy IoU 0.816 without, 0.855 with the last
        action, 0.907 with both (bench/results/ppo.md).
        """
        if not self.num_actions:
            return obs
        w = self.window_size
        previous_window = jnp.where(reset[..., None], obs[..., :w], previous_obs[..., :w])
        last_action = jnp.where(reset, self.num_actions, last_action)
        action = jax.nn.one_hot(last_action, self.num_actions + 1, dtype=obs.dtype)
        return jnp.concatenate([obs, previous_window.astype(obs.dtype), action], axis=-1)

    def episode_start_memory(self) -> dict[str, jax.Array]:
        """What a `Policy` keeps between steps to build its inputs, at an episode's start (the
        `reset` flag also zeroes a recurrent carry)."""
        return {
            "reset": jnp.ones((), bool),
            "previous_obs": jnp.zeros((self.env_obs_size,), jnp.float32),
            "last_action": jnp.zeros((), jnp.int32),
        }

    def acting_inputs(self, obs: jax.Array, memory: dict[str, jax.Array]) -> jax.Array:
        """The network's input for one observation, given the memory of the steps before it."""
        return self.with_previous_step(obs, memory["previous_obs"], memory["last_action"], memory["reset"])

    def remember(self, obs: jax.Array, action: jax.Array) -> dict[str, jax.Array]:
        """The memory after acting `action` on `obs`: what the next step reads as its previous one."""
        return {"reset": jnp.zeros((), bool), "previous_obs": obs.astype(jnp.float32), "last_action": action.astype(jnp.int32)}

    @property
    def num_height_classes(self) -> int:
        """Landmark (-2), padding (-1), heights 0..tallest, and one class for anything taller."""
        return int(self.height_scale) + 4

    def height_classes(self, cells: jax.Array) -> jax.Array:
        """One-hot `(..., n, num_height_classes)` of raw cell values.

        Why: the policy must stop dropping exactly when a column reaches its design height
        (+10 at equality, -1 above). A scaled height puts 19 and 20 bricks 0.03 apart; a one-hot
        makes "is it exactly 20?" one weight, and a trained PPO policy without it missed its
        columns by ~4 bricks even at the start cell, whose position it knows.
        """
        index = jnp.clip(cells.astype(jnp.int32) + 2, 0, self.num_height_classes - 1)
        return jax.nn.one_hot(index, self.num_height_classes, dtype=jnp.float32)

    def split(self, obs: jax.Array) -> dict[str, jax.Array]:
        """Scaled parts of `obs (..., obs_size)`: window (..., wr, wc), its cells one-hot
        (..., wr * wc, classes), counters (..., 2),
        with the switches design (..., *plan_shape) and position (..., 1 or 2), and with
        `num_actions` the previous window (scaled and one-hot) and the last action."""
        lead = obs.shape[:-1]
        w = self.window_size
        parts = {
            "window": obs[..., :w].reshape(lead + self.window_shape) / self.height_scale,
            "window_classes": self.height_classes(obs[..., :w]),
            "counters": obs[..., w : w + 2] / jnp.array([self.brick_scale, self.step_scale]),
        }
        offset = w + 2
        if self.dynamic:
            parts["design"] = obs[..., offset : offset + self.design_size].reshape(lead + self.plan_shape) / self.height_scale
            offset += self.design_size
        if self.gps:
            gps_size = self.env_obs_size - offset
            parts["position"] = obs[..., offset : offset + gps_size] / max(self.plan_shape)
        if self.num_actions:
            previous_window = obs[..., self.env_obs_size : self.env_obs_size + w]
            parts["previous_window"] = previous_window.reshape(lead + self.window_shape) / self.height_scale
            parts["previous_window_classes"] = self.height_classes(previous_window)
            parts["last_action"] = obs[..., self.env_obs_size + w :]
        return parts


class DesignEncoder(nn.Module):
    """Features of a dynamic task's design: a dense layer over a row of column heights, a small
    strided conv over a 2D/3D plan.

    Why dense in 1D: the encoder runs on every step the learner trains on, and a 1D conv over
    the 30 columns made PPO's 1d-dynamic training 1.7x slower on the CPU (35.6k vs 60.2k
    env-steps/s, bench/results/ppo.md); greedy IoU 0.805 with the conv (and GRU 64), 0.795
    with the dense layer (and GRU 32): one seed each, on different machines."""

    features: int

    @nn.compact
    def __call__(self, design: jax.Array) -> jax.Array:
        lead, plan = design.shape[:-2], design.shape[-2:]
        if plan[0] == 1:  # 1D: the row of column heights through a dense layer
            x = design.reshape((-1, plan[1]))
            x = nn.relu(nn.Dense(self.features, kernel_init=scaled_init(np.sqrt(2)))(x))
        else:
            x = design.reshape((-1,) + plan + (1,))
            x = nn.relu(nn.Conv(16, (3, 3), strides=(2, 2), kernel_init=scaled_init(np.sqrt(2)))(x))
            x = nn.relu(nn.Conv(16, (3, 3), strides=(2, 2), kernel_init=scaled_init(np.sqrt(2)))(x))
            x = x.reshape((x.shape[0], -1))
        x = nn.relu(nn.Dense(self.features, kernel_init=scaled_init(np.sqrt(2)))(x))
        return x.reshape(lead + (self.features,))


class ObservationEncoder(nn.Module):
    """Scaled and one-hot window + counters (+ design features, + position) -> an MLP embedding."""

    layout: ObsLayout
    hidden_size: int

    @nn.compact
    def __call__(self, obs: jax.Array) -> jax.Array:
        parts = self.layout.split(obs)
        lead = obs.shape[:-1]
        features = [
            parts["window"].reshape(lead + (-1,)),
            parts["window_classes"].reshape(lead + (-1,)),
            parts["counters"],
        ]
        if "position" in parts:
            features.append(parts["position"])
        if self.layout.num_actions:
            features += [
                parts["previous_window"].reshape(lead + (-1,)),
                parts["previous_window_classes"].reshape(lead + (-1,)),
                parts["last_action"],
            ]
        if "design" in parts:
            features.append(DesignEncoder(self.hidden_size)(parts["design"]))
        x = jnp.concatenate(features, axis=-1)
        for _ in range(2):
            x = nn.relu(nn.Dense(self.hidden_size, kernel_init=scaled_init(np.sqrt(2)))(x))
        return x


class ScannedRNN(nn.Module):
    """A GRU or LSTM over time (`nn.scan`) whose carry is zeroed where `resets` marks a new
    episode. Call with `carry (B, carry_size)` and `(inputs (T, B, F), resets (T, B))`.

    The carry is always one array, so recurrent learners keep it in a runner state and a replay
    sample the same way: the GRU's hidden state, or the LSTM's cell and hidden states side by
    side (`carry_size` = 2 * features).
    """

    features: int
    cell: str = "gru"  # "gru" or "lstm"

    @functools.partial(
        nn.scan, variable_broadcast="params", in_axes=0, out_axes=0, split_rngs={"params": False}
    )
    @nn.compact
    def __call__(self, carry: jax.Array, step: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        inputs, resets = step
        carry = jnp.where(resets[:, None], jnp.zeros_like(carry), carry)
        inits = dict(kernel_init=scaled_init(1.0), recurrent_kernel_init=scaled_init(1.0))
        if self.cell == "lstm":
            (c, h), out = nn.OptimizedLSTMCell(self.features, **inits)(jnp.split(carry, 2, axis=-1), inputs)
            return jnp.concatenate([c, h], axis=-1), out
        return nn.GRUCell(self.features, **inits)(carry, inputs)


def mlp_head(x: jax.Array, hidden_size: int, out: int, gain: float) -> jax.Array:
    x = nn.relu(nn.Dense(hidden_size, kernel_init=scaled_init(np.sqrt(2)))(x))
    return nn.Dense(out, kernel_init=scaled_init(gain))(x)


class ActorCritic(nn.Module):
    """Policy logits and value from the observation, with an optional GRU core."""

    layout: ObsLayout
    num_actions: int
    hidden_size: int = 64
    rnn_size: int = 0  # 0: feed-forward

    @property
    def carry_size(self) -> int:
        return self.rnn_size if self.rnn_size else 1

    def initial_carry(self, batch: int) -> jax.Array:
        return jnp.zeros((batch, self.carry_size), jnp.float32)

    @nn.compact
    def __call__(
        self, carry: jax.Array, obs: jax.Array, resets: jax.Array
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """`carry (B, C)`, `obs (T, B, O)`, `resets (T, B)` -> `(carry, logits (T, B, A), value (T, B))`."""
        x = ObservationEncoder(self.layout, self.hidden_size)(obs)
        if self.rnn_size:
            carry, x = ScannedRNN(self.rnn_size, "gru")(carry, (x, resets))
        logits = mlp_head(x, self.hidden_size, self.num_actions, 0.01)
        value = mlp_head(x, self.hidden_size, 1, 1.0)[..., 0]
        return carry, logits, value


def param_count(params) -> int:
    return int(sum(np.prod(p.shape) for p in jax.tree.leaves(params)))


__all__: Sequence[str] = ("ObsLayout", "DesignEncoder", "ObservationEncoder", "ScannedRNN", "ActorCritic", "scaled_init")
