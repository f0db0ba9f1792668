"""Auxiliary localisation and map losses on a learner's recurrent state, the stride curriculum, and
DRQN and PQN-RNN trained with them (`drqn-aux`, `pqn-aux`).

The robot must localise from what its window shows (SPEC §11): the handcrafted policy keeps an
explicit estimate of its position, a recurrent learner only what its memory happens to hold.
These losses ask the memory to hold it. Small heads on the recurrent state predict, from the
environment's privileged state (SPEC §12, training only):

- `position`: the true plan position, one class per row and one per column (cross-entropy);
- `map`: the bricks on every plan cell, scaled like the observation (mean squared error);
- `move`: how many cells the last move carried the robot, 0..3 (cross-entropy): the drawn stride
  unless a wall or an obstacle cut the move short, so always what the window's shift shows.

Each is on when its coefficient is above 0 (`AuxiliaryOptions`); its head then exists and its loss
is added to the learner's. The heads read the memory, never feed the policy: the greedy policy's
action is the same function of its observations whatever the heads hold, and it never sees the
privileged state. `agents.research.ppo_privileged` adds them to PPO, `DRQNAux` here to DRQN, and
`agents.research.pqn_aux` to PQN-RNN.

`stride_curriculum` anneals the stride noise from none (every move one cell, the paper's
"-uncertainty") to the task's distribution over a share of the run, through `EnvParams`, which the
update takes as an argument; the evaluation always uses the task's distribution.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from agents.common.inputs import ObsLayout
from agents.common.networks import mlp_head
from agents.common.offpolicy import Step
from agents.learners.drqn import DRQN, DRQNConfig
from agents.training.config import option
from snac_jax.config import MAX_STRIDE
from snac_jax.state import EnvParams


@dataclasses.dataclass(frozen=True)
class AuxiliaryOptions:
    """The auxiliary losses' weights (0: off) and the stride curriculum, shared by the learners
    that train with them (`agents.research.ppo_privileged.PrivilegedPPOConfig`, `DRQNAuxConfig`, `PQNAuxConfig`)."""

    position_coef: float = option(
        0.05, "weight of the loss predicting the true plan position from the recurrent state (0: off)", low=0
    )
    map_coef: float = option(
        0.0, "weight of the loss predicting the bricks on every plan cell from the recurrent state (0: off)", low=0
    )
    move_coef: float = option(
        0.0, "weight of the loss predicting how many cells the last move carried the robot (0: off)", low=0
    )
    stride_curriculum: float = option(
        0.0,
        "share of the run over which the stride noise grows from none (every move one cell) to the task's (0: off)",
        low=0,
        high=1,
    )


# --- pure pieces, each checked by hand in tests/test_privileged.py --------------------------------


def weighted_mean(values: jax.Array, weights: jax.Array) -> jax.Array:
    return (values * weights).sum() / jnp.maximum(weights.sum(), 1.0)


def position_loss(logits: jax.Array, position: jax.Array, plan_shape: tuple[int, int], weights: jax.Array) -> jax.Array:
    """Cross-entropy of the true row plus that of the true column. `logits (..., rows + cols)`,
    `position (..., 2)`, `weights (...)`. (1D has one row: its term is 0.)"""
    rows = plan_shape[0]
    ce = optax.softmax_cross_entropy_with_integer_labels
    per_step = ce(logits[..., :rows], position[..., 0]) + ce(logits[..., rows:], position[..., 1])
    return weighted_mean(per_step, weights)


def map_loss(prediction: jax.Array, built: jax.Array, scale: float, weights: jax.Array) -> jax.Array:
    """Mean over the plan cells of the squared error of `prediction (..., cells)` against
    `built (..., rows, cols) / scale`, weighted over steps."""
    target = built.reshape(built.shape[:-2] + (-1,)).astype(jnp.float32) / scale
    return weighted_mean(((prediction - target) ** 2).mean(axis=-1), weights)


def move_targets(position: jax.Array, action: jax.Array, reset: jax.Array, is_move: jax.Array):
    """Time-major `(cells, valid)`: at step t, how many cells the move of step t - 1 carried the
    robot, and whether that is defined (step t - 1 was a move of this episode). Step 0 has none."""
    cells = jnp.abs(position[1:].astype(jnp.int32) - position[:-1].astype(jnp.int32)).sum(axis=-1)
    valid = is_move[action[:-1].astype(jnp.int32)] & ~reset[1:]
    first = jnp.zeros_like(cells[:1])
    return jnp.concatenate([first, cells]), jnp.concatenate([first.astype(bool), valid])


def move_loss(logits: jax.Array, cells: jax.Array, valid: jax.Array, weights: jax.Array) -> jax.Array:
    """Cross-entropy of the cells moved (`logits (..., MAX_STRIDE + 1)`) where `valid`."""
    ce = optax.softmax_cross_entropy_with_integer_labels(logits, jnp.clip(cells, 0, MAX_STRIDE))
    return weighted_mean(ce, weights * valid)


def stride_curriculum(env_params: EnvParams, update: jax.Array, num_updates: int, fraction: float) -> EnvParams:
    """`env_params` for update number `update`: strides drawn from a mix of "always 1" and the
    task's distribution, the task's share growing linearly from 0 to 1 over the first `fraction`
    of the `num_updates` updates."""
    progress = jnp.clip(update / max(1.0, fraction * num_updates), 0.0, 1.0)
    certain = jnp.array([1.0, 0.0, 0.0], jnp.float32)
    return env_params.replace(stride_probs=(1.0 - progress) * certain + progress * env_params.stride_probs)


# --- the heads and their losses -------------------------------------------------------------------


class AuxiliaryHeads(nn.Module):
    """Predictions from the recurrent state: a dict with "position" (row and column logits),
    "map" (scaled bricks per plan cell) and "move" (cells moved, logits), the switched-on ones."""

    plan_shape: tuple[int, int]
    hidden_size: int
    heads: tuple[str, ...]

    @nn.compact
    def __call__(self, features: jax.Array) -> dict[str, jax.Array]:
        rows, cols = self.plan_shape
        sizes = {"position": rows + cols, "map": rows * cols, "move": MAX_STRIDE + 1}
        return {name: mlp_head(features, self.hidden_size, sizes[name], 1.0) for name in self.heads}


def move_directions(env_config) -> np.ndarray:
    """`(num_actions, 2)`: each action's (row, column) direction, (0, 0) for a drop and for the
    landmark placement (SPEC §14, the index after the table's): the axis and sign a move can carry
    the robot along (`EnvConfig.actions` rows are (is_drop, d_row, d_col))."""
    table = [(0, 0) if is_drop else (d_row, d_col) for is_drop, d_row, d_col in env_config.actions]
    table += [(0, 0)] * (env_config.num_actions - len(table))
    return np.asarray(table, np.int32)


@dataclasses.dataclass(frozen=True)
class Auxiliary:
    """The static pieces of a learner's auxiliary losses: which are on, their weights, and what
    their targets need to know about the task."""

    coefs: dict[str, float]  # head name -> weight, the heads that are on
    plan_shape: tuple[int, int]
    height_scale: float
    is_move: np.ndarray  # bool per action: a move (not a drop)

    @classmethod
    def from_config(cls, config) -> Auxiliary:
        """From a config with `AuxiliaryOptions` (its task's environment is built once and cached)."""
        env, env_params = config.make_env()
        layout = ObsLayout.from_env(env, env_params)
        coefs = {"position": config.position_coef, "map": config.map_coef, "move": config.move_coef}
        return cls(
            coefs={name: coef for name, coef in coefs.items() if coef > 0},
            plan_shape=layout.plan_shape,
            height_scale=layout.height_scale,
            is_move=move_directions(env.config).any(axis=-1),
        )

    def heads(self, hidden_size: int) -> AuxiliaryHeads | None:
        """The heads to put on the recurrent state, None when every loss is off."""
        if not self.coefs:
            return None
        return AuxiliaryHeads(plan_shape=self.plan_shape, hidden_size=hidden_size, heads=tuple(self.coefs))

    def losses(self, outputs: dict, position, built, cells, valid, weights) -> dict[str, tuple[float, jax.Array]]:
        """Name -> (weight, loss) of the heads' `outputs` against the targets of the same steps:
        `position (..., 2)`, `built (..., rows, cols)` (None without the map loss), the cells
        moved and their validity (`move_targets`), and per-step `weights`."""
        losses = {}
        if "position" in self.coefs:
            losses["position_loss"] = position_loss(outputs["position"], position, self.plan_shape, weights)
        if "map" in self.coefs:
            losses["map_loss"] = map_loss(outputs["map"], built, self.height_scale, weights)
        if "move" in self.coefs:
            losses["move_loss"] = move_loss(outputs["move"], cells, valid, weights)
        return {name: (self.coefs[name.removesuffix("_loss")], loss) for name, loss in losses.items()}


class StrideCurriculum:
    """Mixed into a learner before its algorithm class (`class L(StrideCurriculum, PPO)`): each
    update runs with `stride_curriculum`'s stride distribution and reports P(d = 1) as
    `p_stride_1`; off (`stride_curriculum = 0`), the update is the algorithm's own."""

    def update(self, state, env_params) -> tuple[Any, dict]:
        fraction = self.config.stride_curriculum
        if not fraction:
            return super().update(state, env_params)
        env_params = stride_curriculum(env_params, state.update, self.config.num_updates, fraction)
        state, metrics = super().update(state, env_params)
        return state, {**metrics, "p_stride_1": env_params.stride_probs[0]}


def add_losses(total: jax.Array, info: dict, losses: dict[str, tuple[float, jax.Array]]) -> tuple[jax.Array, dict]:
    """`total` plus every weighted loss, and `info` with each loss reported under its name."""
    for coef, loss in losses.values():
        total = total + coef * loss
    return total, {**info, **{name: loss for name, (_, loss) in losses.items()}}


def add_rollout_losses(
    auxiliary: Auxiliary,
    total: jax.Array,
    info: dict,
    sown: dict,
    position: jax.Array,
    built: jax.Array | None,
    action: jax.Array,
    reset: jax.Array,
) -> tuple[jax.Array, dict]:
    """The auxiliary losses of an on-policy learner (PPO, PQN), whose minibatch is whole rollout
    sequences `(T, B)`: every step of them is learned from, with the heads' outputs sown along
    them, the true `position (T, B, 2)` and `built` plan where each observation was made."""
    if not auxiliary.coefs:
        return total, info
    outputs = sown["intermediates"]["auxiliary"][0]
    cells, valid = move_targets(position, action, reset, jnp.asarray(auxiliary.is_move))
    weights = jnp.ones(action.shape, jnp.float32)
    return add_losses(total, info, auxiliary.losses(outputs, position, built, cells, valid, weights))


# --- DRQN with the auxiliary losses ---------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class DRQNAuxConfig(AuxiliaryOptions, DRQNConfig):
    """DRQN (`agents.learners.drqn`) with auxiliary localisation and map losses on its LSTM state, trained
    with DRQN's tuned settings per task (`tuned_as`)."""

    algorithm: ClassVar[str] = "drqn-aux"
    paper_method: ClassVar[str] = "drqn"
    tuned_as: ClassVar[str] = "drqn"


@struct.dataclass
class AuxiliaryStep(Step):
    position: jax.Array  # int8 (2,), the true plan position where `obs` was observed
    built: jax.Array | None  # int16 plan-shaped bricks there; None without the map loss (it is large)


class DRQNAux(StrideCurriculum, DRQN):
    """DRQN whose replayed steps also record the privileged targets, and whose loss adds the
    auxiliary losses on the LSTM outputs of the learning steps (the burn-in has none)."""

    def __init__(self, config: DRQNAuxConfig):
        self.auxiliary = Auxiliary.from_config(config)  # first: the replay's memory check reads `_example_step`
        super().__init__(config)
        self.network = self.network.clone(auxiliary_heads=self.auxiliary.heads(config.hidden_size))

    def _example_step(self) -> AuxiliaryStep:
        base = super()._example_step()
        built = jnp.zeros(self.layout.plan_shape, jnp.int16) if "map" in self.auxiliary.coefs else None
        return AuxiliaryStep(
            **{f.name: getattr(base, f.name) for f in dataclasses.fields(Step)},
            position=jnp.zeros((2,), jnp.int8),
            built=built,
        )

    def _world_step(self, worlds, keys: jax.Array, action: jax.Array, env_params):
        env_state, obs, reward, done, info, step, after = super()._world_step(worlds, keys, action, env_params)
        privileged = jax.vmap(self.env.privileged, in_axes=(0, None))(worlds.env_state, env_params)
        built = privileged.built.astype(jnp.int16) if "map" in self.auxiliary.coefs else None
        step = AuxiliaryStep(
            **{f.name: getattr(step, f.name) for f in dataclasses.fields(Step)},
            position=privileged.position.astype(jnp.int8),
            built=built,
        )
        return env_state, obs, reward, done, info, step, after

    def loss(self, params, target_params, batch: AuxiliaryStep, obs, rewards, mask):
        """DQN's loss plus the auxiliary losses on the LSTM outputs of the learning steps."""
        frames, resets = self.replayed_frames(batch, obs)
        carry = self.burned_in_carry(params, frames, resets)
        (_, q), sown = self.network.apply(
            params, carry, frames[self.burn_in :], resets[self.burn_in :], mutable="intermediates"
        )
        loss, info = self.td_loss(q, target_params, frames, resets, batch, rewards, mask)
        if not self.auxiliary.coefs:
            return loss, info
        c, length = self.config.context, self.config.sequence_length
        weights = mask[c : c + length]
        outputs = jax.tree.map(lambda x: x[:length], sown["intermediates"]["auxiliary"][0])
        cells, valid = move_targets(batch.position, batch.action, batch.reset, jnp.asarray(self.auxiliary.is_move))
        steps = slice(c, c + length)  # the learning steps: output 0 is batch row c
        built = None if batch.built is None else batch.built[steps]
        losses = self.auxiliary.losses(
            outputs, batch.position[steps].astype(jnp.int32), built, cells[steps], valid[steps], weights
        )
        return add_losses(loss, info, losses)
