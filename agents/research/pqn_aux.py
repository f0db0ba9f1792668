"""PQN-RNN trained with the auxiliary localisation and map losses of `agents.research.drqn_aux` on its GRU
state (`pqn-aux`): PQN's rollout also records the true position (and the built plan, with the map
loss) where each observation was made, and its loss adds the heads' losses. The update, the
epsilon schedule and the greedy policy are PQN's (`agents.learners.pqn`); the heads never feed the policy.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from agents.common.networks import (
    LayerNormQNetwork,
    ObservationEncoder,
    ScannedRNN,
    apply_with_design_cache,
    first_design_cache,
    scaled_init,
)
from agents.learners.pqn import PQN, PQNConfig, RunnerState, episode_stats, td_loss
from agents.research.drqn_aux import Auxiliary, AuxiliaryOptions, StrideCurriculum, add_rollout_losses
from agents.training.config import option


@dataclasses.dataclass(frozen=True)
class PQNAuxConfig(AuxiliaryOptions, PQNConfig):
    """PQN-RNN (`agents.learners.pqn`, recurrent) with auxiliary localisation and map losses on its GRU
    state. It trains with PQN's tuned settings per task (`tuned_as`), so a comparison with PQN-RNN
    is of the losses alone; where PQN's entry turns the GRU off, `agents/tuned/pqn-aux.toml` turns
    it back on, as the heads read its state. The position loss's default weight is a hundredth of
    the other learners', as PQN's TD loss is about that much smaller (rewards scaled by 0.01): at
    their weight the position loss takes over the shared GRU (bench/results/pqn.md)."""

    algorithm: ClassVar[str] = "pqn-aux"
    paper_method: ClassVar[str] = "pqn"
    tuned_as: ClassVar[str] = "pqn"

    position_coef: float = option(
        5e-4, "weight of the loss predicting the true plan position from the GRU state (0: off)", low=0
    )

    def check(self) -> None:
        super().check()
        require_recurrent(self)


def require_recurrent(config: PQNConfig) -> None:
    """A learner whose heads read PQN-RNN's GRU state refuses a feed-forward network."""
    if not config.recurrent:
        raise ValueError(
            f"{config.algorithm} needs recurrent=True: its auxiliary heads read the GRU's state "
            "(use pqn for a feed-forward PQN)"
        )


class AuxiliaryQNetwork(LayerNormQNetwork):
    """PQN-RNN's network with heads on the GRU's features (`AuxiliaryHeads`), sown into
    "intermediates": computed on every call, but only an apply with mutable="intermediates" (the
    training loss) keeps them, so the Q-values are PQN-RNN's."""

    auxiliary_heads: nn.Module | None = None

    @nn.compact
    def __call__(self, carry: jax.Array, obs: jax.Array, resets: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = ObservationEncoder(self.layout, self.hidden_size, layer_norm=True)(obs)
        if self.rnn_size:
            carry, x = ScannedRNN(self.rnn_size, "gru")(carry, (x, resets))
        if self.auxiliary_heads is not None:
            self.sow("intermediates", "auxiliary", self.auxiliary_heads(x))
        return carry, nn.Dense(self.num_actions, kernel_init=scaled_init(1.0))(x)


class AuxiliaryTransition(NamedTuple):
    """PQN's `Transition` with the auxiliary losses' targets where `obs` was observed (None when
    every loss is off)."""

    obs: jax.Array
    reset: jax.Array
    action: jax.Array
    value: jax.Array
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    final_obs: jax.Array
    carry_after: jax.Array
    auxiliary: dict | None


class PQNAux(StrideCurriculum, PQN):
    """PQN-RNN whose rollout also records the true position (and the built plan, with the map
    loss) where each observation was made, and whose loss adds the auxiliary losses on the GRU
    outputs of every rollout step, as `agents.research.ppo_privileged.PrivilegedPPO` does for PPO. The rollout
    and the loss are PQN's with those additions; the update and the policy are PQN's."""

    def __init__(self, config: PQNAuxConfig):
        super().__init__(config)
        self.auxiliary = Auxiliary.from_config(config)
        base = self.network
        self.network = AuxiliaryQNetwork(
            layout=base.layout,
            num_actions=base.num_actions,
            hidden_size=base.hidden_size,
            rnn_size=base.rnn_size,
            auxiliary_heads=self.auxiliary.heads(config.hidden_size),
        )

    def auxiliary_targets(self, env_state, env_params) -> dict | None:
        """What the auxiliary losses learn from, per world: the true position, and the built plan
        with the map loss; None when every loss is off."""
        if not self.auxiliary.coefs:
            return None
        privileged = jax.vmap(self.env.privileged, in_axes=(0, None))(env_state, env_params)
        return {
            "position": privileged.position,
            "built": privileged.built.astype(jnp.int16) if "map" in self.auxiliary.coefs else None,
        }

    def rollout(self, state: RunnerState, env_params) -> tuple[RunnerState, AuxiliaryTransition, dict]:
        """PQN's rollout, recording each step's auxiliary targets."""
        n = self.config.num_envs
        step = jax.vmap(self.env.step, in_axes=(0, 0, 0, None))
        epsilon = self.epsilon(state.update)

        def env_step(carry, _):
            worlds, design_cache, key = carry
            key, key_explore, key_random, key_step = jax.random.split(key, 4)
            net_obs = self._network_obs(worlds)
            (new_carry, q), design_cache = apply_with_design_cache(
                self.network, state.params, design_cache, worlds.carry, net_obs[None], worlds.reset[None]
            )
            action, q = self.epsilon_greedy(key_explore, key_random, q[0], net_obs, epsilon)
            obs, env_state, reward, terminated, truncated, info = step(
                jax.random.split(key_step, n), worlds.env_state, action, env_params
            )
            done = terminated | truncated
            episode_return = worlds.episode_return + reward
            final_obs = self.layout.with_previous_step(
                info["final_observation"], worlds.obs, action, jnp.zeros_like(done)
            )
            transition = AuxiliaryTransition(
                obs=net_obs,
                reset=worlds.reset,
                action=action,
                value=q.max(-1),
                reward=reward,
                terminated=terminated,
                truncated=truncated,
                final_obs=final_obs,
                carry_after=new_carry,
                auxiliary=self.auxiliary_targets(worlds.env_state, env_params),
            )
            stats = episode_stats(done, info["final_iou"], episode_return)
            worlds = worlds.after_step(env_state, obs, action, done, new_carry, episode_return)
            return (worlds, design_cache, key), (transition, stats)

        inputs = (state.worlds.carry, self._network_obs(state.worlds)[None], state.worlds.reset[None])
        design_cache = first_design_cache(self.network, state.params, *inputs)
        (worlds, _, key), (batch, stats) = jax.lax.scan(
            env_step, (state.worlds, design_cache, state.key), None, length=self.config.rollout_steps
        )
        return state.replace(worlds=worlds, key=key), batch, jax.tree.map(jnp.sum, stats)

    def _loss(self, params, carry0, batch: AuxiliaryTransition, targets):
        """PQN's TD loss plus the auxiliary losses on what the heads sowed along the minibatch."""
        (_, q), sown = self.network.apply(params, carry0, batch.obs, batch.reset, mutable="intermediates")
        loss, info = td_loss(q, batch.action, targets)
        recorded = batch.auxiliary or {}  # None where every weight is 0 (nothing recorded, nothing added)
        return add_rollout_losses(
            self.auxiliary, loss, info, sown, recorded.get("position"), recorded.get("built"), batch.action, batch.reset
        )
