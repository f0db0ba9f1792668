"""Asymmetric PPO: the critic also reads the environment's privileged state (SPEC §12), the actor
only its observations; optionally with the auxiliary localisation and map losses of
`agents.research.drqn_aux` on the recurrent state, and the stride curriculum.

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

The learner is PPO (`agents.learners.ppo`) with the steps the critic changes written out here: the
rollout also records the privileged state of every step and, through `step_keeping_final_state`,
the one each ended episode ended in (the truncation bootstrap values it); the advantages score
both with the critic; the loss adds the heads' losses to PPO's (`clipped_objective`). The update,
its minibatches and the greedy policy are PPO's.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, NamedTuple

import distrax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from agents.common.inputs import ObsLayout
from agents.common.networks import (
    ActorCritic,
    ObservationEncoder,
    ScannedRNN,
    apply_with_design_cache,
    first_design_cache,
    mlp_head,
    scaled_init,
)
from agents.common.targets import gae, truncation_values
from agents.learners.ppo import PPO, PPOConfig, RunnerState, Worlds, clipped_objective, episode_stats
from agents.research.drqn_aux import Auxiliary, AuxiliaryOptions, StrideCurriculum, add_rollout_losses
from agents.training.config import option
from snac_jax.state import PrivilegedState


@dataclasses.dataclass(frozen=True)
class PrivilegedPPOConfig(AuxiliaryOptions, PPOConfig):
    """PPO whose critic reads the privileged state, with optional auxiliary losses. It trains with
    PPO's tuned settings per task (`tuned_as`), so the comparison with PPO is of the training
    signals alone."""

    algorithm: ClassVar[str] = "ppo-privileged"
    paper_method: ClassVar[str] = "ppo"
    tuned_as: ClassVar[str] = "ppo"

    privileged_critic: bool = option(
        True, "the critic also reads the privileged state (position, built plan, design, stuck); the actor never does"
    )


class PrivilegedEncoder(nn.Module):
    """Features of a batch of `PrivilegedState`s `(..., )` for the critic: the position one-hot
    per row and per column, the built plan and what is left to build, each flattened, and the
    stuck flag, through one dense layer.

    Why flat maps rather than the design encoder's strided convolutions: the critic runs on every
    step the learner trains on, and two convolutional encoders cost more than the rest of training
    on the 2D and 3D plans (`bench/results/ppo.md`, its privileged critic's section); one matrix
    product over the 400 cells of each map keeps every cell's exact height at a fraction of the
    cost."""

    layout: ObsLayout
    hidden_size: int

    @nn.compact
    def __call__(self, privileged: PrivilegedState) -> jax.Array:
        rows, cols = self.layout.plan_shape
        lead = privileged.position.shape[:-1]
        built = privileged.built.astype(jnp.float32) / self.layout.height_scale
        remaining = privileged.design.astype(jnp.float32) / self.layout.height_scale - built
        x = jnp.concatenate(
            [
                jax.nn.one_hot(privileged.position[..., 0], rows),
                jax.nn.one_hot(privileged.position[..., 1], cols),
                built.reshape(lead + (rows * cols,)),
                remaining.reshape(lead + (rows * cols,)),
                privileged.stuck[..., None].astype(jnp.float32),
            ],
            axis=-1,
        )
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


class PrivilegedTransition(NamedTuple):
    """PPO's `Transition` with the privileged state the critic reads: `privileged` where `obs` was
    observed, and in `final_obs` beside the episode's last observation the state it ended in."""

    obs: jax.Array
    reset: jax.Array
    action: jax.Array
    log_prob: jax.Array
    value: jax.Array
    reward: jax.Array
    terminated: jax.Array
    done: jax.Array
    final_obs: tuple[jax.Array, PrivilegedState]
    carry_after: jax.Array
    privileged: PrivilegedState


def _one_step(tree: Any) -> Any:
    """A per-world pytree `(B, ...)` as one time step `(1, B, ...)`."""
    return jax.tree.map(lambda x: x[None], tree)


class PrivilegedPPO(StrideCurriculum, PPO):
    def __init__(self, config: PrivilegedPPOConfig):
        super().__init__(config)
        self.auxiliary = Auxiliary.from_config(config)
        base = self.network
        self.network = AsymmetricActorCritic(
            layout=base.layout,
            num_actions=base.num_actions,
            hidden_size=base.hidden_size,
            rnn_size=base.rnn_size,
            privileged_critic=config.privileged_critic,
            auxiliary_heads=self.auxiliary.heads(config.hidden_size),
        )

    def privileged_state(self, env_state, env_params) -> PrivilegedState:
        return jax.vmap(self.env.privileged, in_axes=(0, None))(env_state, env_params)

    def init(self, key: jax.Array) -> RunnerState:
        """PPO's, with the critic's parameters made from one world's privileged state."""
        n = self.config.num_envs
        key, key_params, key_reset = jax.random.split(key, 3)
        carry = self.network.initial_carry(n)
        obs, env_state = jax.vmap(self.env.reset, in_axes=(0, None))(jax.random.split(key_reset, n), self.env_params)
        worlds = Worlds(
            env_state=env_state,
            obs=obs,
            previous_obs=obs,
            last_action=jnp.zeros((n,), jnp.int32),
            reset=jnp.ones((n,), bool),
            carry=carry,
            episode_return=jnp.zeros((n,), jnp.float32),
        )
        privileged = jax.tree.map(lambda x: x[None, :1], self.privileged_state(env_state, self.env_params))
        params = self.network.init(
            key_params, carry[:1], self._network_obs(worlds)[None, :1], jnp.ones((1, 1), bool), privileged
        )
        return RunnerState(
            params=params,
            opt_state=self.optimizer.init(params),
            worlds=worlds,
            key=key,
            update=jnp.zeros((), jnp.int32),
        )

    def rollout(self, state: RunnerState, env_params) -> tuple[RunnerState, PrivilegedTransition, dict]:
        """PPO's rollout; the critic reads each step's privileged state, and each ended episode's
        last one (before the auto-reset) is kept for its truncation bootstrap."""
        n = self.config.num_envs
        step = jax.vmap(self.env.step_keeping_final_state, in_axes=(0, 0, 0, None))

        def env_step(carry, _):
            worlds, design_cache, key = carry
            key, key_act, key_step = jax.random.split(key, 3)
            net_obs = self._network_obs(worlds)
            privileged = self.privileged_state(worlds.env_state, env_params)
            (new_carry, logits, value), design_cache = apply_with_design_cache(
                self.network,
                state.params,
                design_cache,
                worlds.carry,
                net_obs[None],
                worlds.reset[None],
                _one_step(privileged),
            )
            pi = distrax.Categorical(logits=logits[0])
            action = pi.sample(seed=key_act)
            obs, env_state, reward, terminated, truncated, info, stepped = step(
                jax.random.split(key_step, n), worlds.env_state, action, env_params
            )
            done = terminated | truncated
            episode_return = worlds.episode_return + reward
            final_obs = self.layout.with_previous_step(
                info["final_observation"], worlds.obs, action, jnp.zeros_like(done)
            )
            transition = PrivilegedTransition(
                obs=net_obs,
                reset=worlds.reset,
                action=action,
                log_prob=pi.log_prob(action),
                value=value[0],
                reward=reward,
                terminated=terminated,
                done=done,
                final_obs=(final_obs, self.privileged_state(stepped, env_params)),
                carry_after=new_carry,
                privileged=privileged,
            )
            stats = episode_stats(done, info["final_iou"], episode_return)
            worlds = worlds.after_step(env_state, obs, action, done, new_carry, episode_return)
            return (worlds, design_cache, key), (transition, stats)

        worlds = state.worlds
        inputs = (worlds.carry, self._network_obs(worlds)[None], worlds.reset[None])
        privileged = _one_step(self.privileged_state(worlds.env_state, env_params))
        design_cache = first_design_cache(self.network, state.params, *inputs, privileged)
        (worlds, _, key), (batch, stats) = jax.lax.scan(
            env_step, (worlds, design_cache, state.key), None, length=self.config.rollout_steps
        )
        return state.replace(worlds=worlds, key=key), batch, jax.tree.map(jnp.sum, stats)

    def _advantages(self, params, batch: PrivilegedTransition, worlds: Worlds, env_params):
        """PPO's advantages, every value from the critic that reads the privileged state."""
        cfg = self.config
        privileged = _one_step(self.privileged_state(worlds.env_state, env_params))
        _, _, last_value = self.network.apply(
            params, worlds.carry, self._network_obs(worlds)[None], worlds.reset[None], privileged
        )
        following = jnp.concatenate([batch.value[1:], last_value], axis=0)
        next_values = jnp.where(batch.done, self._final_values(params, batch), following)
        return gae(
            batch.reward * cfg.reward_scale,
            batch.value,
            next_values,
            batch.terminated.astype(jnp.float32),
            batch.done,
            cfg.gamma,
            cfg.gae_lambda,
        )

    def _final_values(self, params, batch: PrivilegedTransition) -> jax.Array:
        """PPO's truncation bootstrap values, the critic reading the privileged state each
        episode ended in."""

        def score(carry, final):
            obs, privileged = final
            resets = jnp.zeros((1, obs.shape[0]), bool)
            _, _, value = self.network.apply(params, carry, obs[None], resets, _one_step(privileged))
            return value[0]

        return truncation_values(
            score,
            batch.done & ~batch.terminated,
            batch.final_obs,
            batch.carry_after,
            self.layout.max_truncations(batch.done.shape[0]),
        )

    def _loss(self, params, carry0, batch: PrivilegedTransition, advantages, targets, ent_coef):
        """PPO's loss, the critic reading the privileged state, plus the auxiliary heads' losses."""
        (_, logits, value), sown = self.network.apply(
            params, carry0, batch.obs, batch.reset, batch.privileged, mutable="intermediates"
        )
        loss, info = clipped_objective(logits, value, batch, advantages, targets, ent_coef, self.config)
        privileged = batch.privileged
        return add_rollout_losses(
            self.auxiliary, loss, info, sown, privileged.position, privileged.built, batch.action, batch.reset
        )
