"""Asymmetric PPO: the critic also reads the environment's privileged state (SPEC §12), the actor
only its observations; optionally with the auxiliary localisation and map losses of
`agents.auxiliary` on the recurrent state, and the stride curriculum.

Why: in SNAC the robot never sees its position, and recurrent PPO's value must guess it from the
same memory the policy localises with, so the advantages it learns from are noisy exactly where
localisation fails. A critic that knows the true position, the bricks built and the design
(Pinto et al. 2018, "Asymmetric Actor Critic") values states well from the start; the actor is
trained by its advantages but acts on what it observes. The critic is used only in training:
the greedy `Policy` the evaluator runs is PPO's, the actor's logits from the observation and the
policy's own memory (`act(params, policy_state, obs, key)`); the privileged state never reaches it.

The critic reads the actor's memory features (the GRU output, as PPO's critic does) beside an
encoding of the privileged state: the position one-hot per row and per column, the built plan
and what is left to build (the design minus the built plan), each flattened, and the stuck flag
(`PrivilegedEncoder`). With `privileged_critic=False` and every auxiliary weight
0 this is PPO, update for update.

Everything else is PPO's (`agents.ppo`), through its hooks: `_privileged` records the privileged
state of every step, `_step` the ended episodes' last one (the truncation bootstrap values it),
and `_auxiliary_losses` adds the heads' losses.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from agents.auxiliary import Auxiliary, AuxiliaryOptions, StrideCurriculum, add_rollout_losses
from agents.config import option
from agents.inputs import ObsLayout
from agents.networks import ActorCritic, ObservationEncoder, ScannedRNN, mlp_head, scaled_init
from agents.ppo import PPO, PPOConfig, Transition
from snac_jax.state import PrivilegedState


@dataclasses.dataclass(frozen=True)
class PrivilegedPPOConfig(AuxiliaryOptions, PPOConfig):
    """PPO whose critic reads the privileged state, with optional auxiliary losses. It trains with
    PPO's tuned settings per task (`tuned_as`), so the comparison with PPO is of the training
    signals alone."""

    algorithm: ClassVar[str] = "ppo-privileged"
    paper_method: ClassVar[str] = "ppo"
    tuned_as: ClassVar[str] = "ppo"

    privileged_critic: bool = option(True, "the critic also reads the privileged state (position, built plan, "
                                     "design, stuck); the actor never does")


class PrivilegedEncoder(nn.Module):
    """Features of a batch of `PrivilegedState`s `(..., )` for the critic: the position one-hot
    per row and per column, the built plan and what is left to build, each flattened, and the
    stuck flag, through one dense layer.

    Why flat maps rather than the design encoder's strided convolutions: the critic runs on every
    step the learner trains on, and two convolutional encoders made training several times slower
    on the 2D and 3D plans (`bench/results/beyond.md`); one matrix product over the 400 cells of
    each map keeps every cell's exact height at a fraction of the cost."""

    layout: ObsLayout
    hidden_size: int

    @nn.compact
    def __call__(self, privileged: PrivilegedState) -> jax.Array:
        rows, cols = self.layout.plan_shape
        lead = privileged.position.shape[:-1]
        built = privileged.built.astype(jnp.float32) / self.layout.height_scale
        remaining = privileged.design.astype(jnp.float32) / self.layout.height_scale - built
        x = jnp.concatenate([
            jax.nn.one_hot(privileged.position[..., 0], rows),
            jax.nn.one_hot(privileged.position[..., 1], cols),
            built.reshape(lead + (rows * cols,)),
            remaining.reshape(lead + (rows * cols,)),
            privileged.stuck[..., None].astype(jnp.float32),
        ], axis=-1)
        return nn.relu(nn.Dense(self.hidden_size, kernel_init=scaled_init(np.sqrt(2)))(x))


class AsymmetricActorCritic(ActorCritic):
    """`ActorCritic` whose critic reads the memory features and the privileged state, with
    optional auxiliary heads on the memory features (sown into "intermediates", read by the
    loss only). Acting passes no privileged state: the actor alone runs, and the value is None."""

    privileged_critic: bool = True
    auxiliary_heads: nn.Module | None = None

    @nn.compact
    def __call__(self, carry: jax.Array, obs: jax.Array, resets: jax.Array, privileged=None):
        x = ObservationEncoder(self.layout, self.hidden_size)(obs)
        if self.rnn_size:
            carry, x = ScannedRNN(self.rnn_size, "gru")(carry, (x, resets))
        logits = mlp_head(x, self.hidden_size, self.num_actions, 0.01)
        if privileged is None:
            return carry, logits, None
        critic = x
        if self.privileged_critic:
            critic = jnp.concatenate([x, PrivilegedEncoder(self.layout, self.hidden_size)(privileged)], axis=-1)
        value = mlp_head(critic, self.hidden_size, 1, 1.0)[..., 0]
        if self.auxiliary_heads is not None:
            self.sow("intermediates", "auxiliary", self.auxiliary_heads(x))
        return carry, logits, value


class PrivilegedPPO(StrideCurriculum, PPO):
    def __init__(self, config: PrivilegedPPOConfig):
        super().__init__(config)
        self.auxiliary = Auxiliary.from_config(config)
        base = self.network
        self.network = AsymmetricActorCritic(
            layout=base.layout, num_actions=base.num_actions, hidden_size=base.hidden_size, rnn_size=base.rnn_size,
            privileged_critic=config.privileged_critic, auxiliary_heads=self.auxiliary.heads(config.hidden_size),
        )

    def _privileged(self, env_state, env_params) -> PrivilegedState:
        return jax.vmap(self.env.privileged, in_axes=(0, None))(env_state, env_params)

    def _step(self, keys: jax.Array, env_state, action: jax.Array, env_params):
        """PPO's step, and in `info["final_privileged"]` the privileged state each world reached
        before any auto-reset."""
        *outputs, info, stepped = jax.vmap(self.env.step_keeping_final_state, in_axes=(0, 0, 0, None))(
            keys, env_state, action, env_params
        )
        return (*outputs, {**info, "final_privileged": self._privileged(stepped, env_params)})

    def _auxiliary_losses(self, loss, info, sown, batch: Transition) -> tuple[jax.Array, dict]:
        privileged = batch.privileged
        return add_rollout_losses(self.auxiliary, loss, info, sown, privileged.position, privileged.built,
                                  batch.action, batch.reset)
