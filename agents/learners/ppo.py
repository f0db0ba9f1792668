"""PPO trained end-to-end inside `jit`, PureJaxRL-style: environment stepping, rollouts, GAE and
the clipped-objective updates are one pure function of a key, vmappable over seeds.

`PPO(config)` holds the static pieces (environment, network, optimiser); its methods are pure:

- `init(key) -> RunnerState` for one seed;
- `rollout(state, env_params) -> (state, batch, stats)`: `rollout_steps` sampled steps in every
  world, no learning (the training benchmark times it as its baseline);
- `update(state, env_params) -> (state, metrics)`: one rollout of `rollout_steps` in every
  world, then `update_epochs` passes over `num_minibatches` minibatches of worlds;
- `train_chunk(state, env_params, n)`: `n` updates in a `lax.scan` (the driver runs chunks);
- `policy(params) -> snac_jax.policy.Policy`: the greedy policy the evaluator runs.

`make_train(config)` returns the whole run as a pure `train(key)`.

Truncated episodes bootstrap from the value of `info["final_observation"]` (the last observation
of the episode, before the auto-reset), computed with the hidden state that saw the episode.

The module forks alone: besides `snac_jax` it reads only the library modules `agents.training.config`,
`agents.common.inputs`, `agents.common.networks` and `agents.common.targets`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, NamedTuple

import distrax
import jax
import jax.numpy as jnp
import optax
from flax import struct

from agents.common.inputs import ObsLayout
from agents.common.networks import ActorCritic, apply_with_design_cache, first_design_cache
from agents.common.targets import gae, truncation_values
from agents.training.config import TrainConfig, option
from snac_jax.policy import Policy


@dataclasses.dataclass(frozen=True)
class PPOConfig(TrainConfig):
    """PPO with the clipped objective, GAE, and an optional recurrent (GRU) core. The defaults
    are the settings tuned on 1d-static-sin (`agents/tuned/ppo.toml` overrides them per task)."""

    algorithm: ClassVar[str] = "ppo"
    paper_method: ClassVar[str] = "ppo"

    recurrent: bool = option(True, "GRU actor-critic instead of a feed-forward one")
    total_steps: int = option(30_000_000, "env steps per seed", low=1)
    num_envs: int = option(1024, "parallel worlds per seed (split over devices)", low=1)
    rollout_steps: int = option(64, "steps per world between updates", low=1)
    update_epochs: int = option(2, "passes over each rollout", low=1)
    num_minibatches: int = option(2, "minibatches per pass; they split the worlds (whole sequences for the GRU)", low=1)
    learning_rate: float = option(1e-3, "Adam step size", low=0, low_open=True)
    anneal_lr: bool = option(True, "decay the learning rate linearly to 0 over the run")
    gamma: float = option(0.99, "discount", low=0, high=1)
    gae_lambda: float = option(0.95, "GAE lambda", low=0, high=1)
    clip_eps: float = option(0.2, "PPO clip range of the ratio and the value", low=0, low_open=True)
    ent_coef: float = option(0.01, "entropy coefficient at the first update", low=0)
    ent_coef_end: float | None = option(
        None,
        "entropy coefficient at the last update, annealed linearly from ent_coef (None: constant); "
        "below 0 it pushes the policy toward the deterministic one the protocol scores",
        low=-1,
    )
    vf_coef: float = option(0.5, "value loss weight", low=0)
    max_grad_norm: float = option(0.5, "global gradient norm clip", low=0, low_open=True)
    hidden_size: int = option(64, "width of the encoder and the heads", low=1)
    rnn_size: int = option(32, "GRU units (recurrent only)", low=1)
    reward_scale: float = option(
        0.01, "rewards are multiplied by this for learning (not for reporting)", low=0, low_open=True
    )

    def check(self) -> None:
        if self.num_envs % self.num_minibatches:
            raise ValueError(
                f"num_envs ({self.num_envs}) must be a multiple of num_minibatches ({self.num_minibatches}): "
                "minibatches split the worlds"
            )


@struct.dataclass
class Worlds:
    """Everything with one entry per parallel world (the axis the driver shards over devices)."""

    env_state: Any
    obs: jax.Array  # (B, O), the environment's observation the next action sees
    previous_obs: jax.Array  # (B, O), the observation before it (ignored where `reset`)
    last_action: jax.Array  # (B,) int32, the action that led to `obs` (ignored where `reset`)
    reset: jax.Array  # (B,) bool, True where `obs` starts an episode (resets the GRU carry)
    carry: jax.Array  # (B, C) recurrent state (a placeholder for feed-forward)
    episode_return: jax.Array  # (B,) return of the running episode so far

    def after_step(
        self, env_state, obs, action: jax.Array, done: jax.Array, carry: jax.Array, episode_return: jax.Array
    ) -> Worlds:
        """The worlds after one step: the new observation, this one as the previous, the action
        taken, the carry after it, and the return restarted where the episode ended (`done`)."""
        return Worlds(
            env_state=env_state,
            obs=obs,
            previous_obs=self.obs,
            last_action=action.astype(jnp.int32),
            reset=done,
            carry=carry,
            episode_return=jnp.where(done, 0.0, episode_return),
        )


def episode_stats(done: jax.Array, final_iou: jax.Array, episode_return: jax.Array) -> dict[str, jax.Array]:
    """What the driver logs of the episodes that ended this step: how many, their IoU and return."""
    return {
        "episodes": done.sum(),
        "iou_sum": jnp.where(done, final_iou, 0.0).sum(),
        "return_sum": jnp.where(done, episode_return, 0.0).sum(),
    }


@struct.dataclass
class RunnerState:
    params: Any
    opt_state: Any
    worlds: Worlds
    key: jax.Array
    update: jax.Array  # int32, updates done


class Transition(NamedTuple):
    obs: jax.Array  # what the network read: the observation (+ the previous step, see ObsLayout)
    reset: jax.Array
    action: jax.Array
    log_prob: jax.Array
    value: jax.Array
    reward: jax.Array
    terminated: jax.Array
    done: jax.Array
    final_obs: jax.Array  # the episode's last observation where `done`
    carry_after: jax.Array  # carry after seeing `obs`: scores `final_obs` for truncation bootstrap


class PPO:
    """Static pieces of a PPO run; see the module docstring."""

    def __init__(self, config: PPOConfig):
        config.validate()
        self.config = config
        self.env, self.env_params = config.make_env()
        self.layout = ObsLayout.from_env(self.env, self.env_params, previous_step=config.previous_step)
        self.network = ActorCritic(
            layout=self.layout,
            num_actions=self.env.num_actions,
            hidden_size=config.hidden_size,
            rnn_size=config.rnn_size if config.recurrent else 0,
        )
        minibatch_steps = config.update_epochs * config.num_minibatches
        lr = (
            optax.linear_schedule(config.learning_rate, 0.0, config.num_updates * minibatch_steps)
            if config.anneal_lr
            else config.learning_rate
        )
        self.optimizer = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(lr, eps=1e-5))
        # Entropy bonus per update: annealing it lets the greedy policy the protocol scores
        # settle on the actions sampling preferred. Why it may end below 0: a partially
        # observed task rewards a stochastic policy (a coin flip breaks a left-right loop), so
        # PPO keeps a few states near 50/50 even at zero bonus, and its argmax then loops. A
        # small entropy *penalty* at the end makes the sampled rollouts the greedy ones, so PPO
        # sees and repairs those loops.
        end = config.ent_coef if config.ent_coef_end is None else config.ent_coef_end
        self.ent_coef = optax.linear_schedule(config.ent_coef, end, max(1, config.num_updates - 1))

    # --- pure functions -------------------------------------------------------------------------

    def init(self, key: jax.Array) -> RunnerState:
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
        params = self.network.init(key_params, carry[:1], self._network_obs(worlds)[None, :1], jnp.ones((1, 1), bool))
        return RunnerState(
            params=params,
            opt_state=self.optimizer.init(params),
            worlds=worlds,
            key=key,
            update=jnp.zeros((), jnp.int32),
        )

    def _network_obs(self, worlds: Worlds) -> jax.Array:
        return self.layout.with_previous_step(worlds.obs, worlds.previous_obs, worlds.last_action, worlds.reset)

    def rollout(self, state: RunnerState, env_params) -> tuple[RunnerState, Transition, dict]:
        n = self.config.num_envs
        step = jax.vmap(self.env.step, in_axes=(0, 0, 0, None))  # every world's auto-resetting step

        def env_step(carry, _):
            worlds, design_cache, key = carry
            key, key_act, key_step = jax.random.split(key, 3)
            net_obs = self._network_obs(worlds)
            (new_carry, logits, value), design_cache = apply_with_design_cache(
                self.network, state.params, design_cache, worlds.carry, net_obs[None], worlds.reset[None]
            )
            pi = distrax.Categorical(logits=logits[0])
            action = pi.sample(seed=key_act)
            obs, env_state, reward, terminated, truncated, info = step(
                jax.random.split(key_step, n), worlds.env_state, action, env_params
            )
            done = terminated | truncated
            episode_return = worlds.episode_return + reward
            final_obs = self.layout.with_previous_step(
                info["final_observation"], worlds.obs, action, jnp.zeros_like(done)
            )
            transition = Transition(
                obs=net_obs,
                reset=worlds.reset,
                action=action,
                log_prob=pi.log_prob(action),
                value=value[0],
                reward=reward,
                terminated=terminated,
                done=done,
                final_obs=final_obs,
                carry_after=new_carry,
            )
            stats = episode_stats(done, info["final_iou"], episode_return)
            worlds = worlds.after_step(env_state, obs, action, done, new_carry, episode_return)
            return (worlds, design_cache, key), (transition, stats)

        inputs = (state.worlds.carry, self._network_obs(state.worlds)[None], state.worlds.reset[None])
        design_cache = first_design_cache(self.network, state.params, *inputs)
        (worlds, _, key), (batch, stats) = jax.lax.scan(
            env_step, (state.worlds, design_cache, state.key), None, length=self.config.rollout_steps
        )
        stats = jax.tree.map(jnp.sum, stats)
        return state.replace(worlds=worlds, key=key), batch, stats

    def _advantages(self, params, batch: Transition, worlds: Worlds, env_params) -> tuple[jax.Array, jax.Array]:
        """GAE advantages and value targets `(T, B)` of a rollout; `worlds` is where it stopped.
        A truncated episode bootstraps from its final observation's value (a termination
        bootstraps nothing)."""
        cfg = self.config
        _, _, last_value = self.network.apply(params, worlds.carry, self._network_obs(worlds)[None], worlds.reset[None])
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

    def _final_values(self, params, batch: Transition) -> jax.Array:
        """`(T, B)` values of the final observations where an episode was truncated (0 elsewhere),
        each from the carry that saw its episode."""

        def score(carry, obs):
            _, _, value = self.network.apply(params, carry, obs[None], jnp.zeros((1, obs.shape[0]), bool))
            return value[0]

        return truncation_values(
            score,
            batch.done & ~batch.terminated,
            batch.final_obs,
            batch.carry_after,
            self.layout.max_truncations(batch.done.shape[0]),
        )

    def _loss(self, params, carry0, batch: Transition, advantages, targets, ent_coef):
        _, logits, value = self.network.apply(params, carry0, batch.obs, batch.reset)
        return clipped_objective(logits, value, batch, advantages, targets, ent_coef, self.config)

    def update(self, state: RunnerState, env_params) -> tuple[RunnerState, dict[str, jax.Array]]:
        cfg = self.config
        carry0 = state.worlds.carry
        state, batch, stats = self.rollout(state, env_params)
        # The final observations are only needed for the bootstrap values.
        advantages, targets = self._advantages(state.params, batch, state.worlds, env_params)
        batch = batch._replace(final_obs=None, carry_after=None)
        grad_fn = jax.value_and_grad(self._loss, has_aux=True)
        ent_coef = self.ent_coef(state.update)
        m = cfg.num_minibatches

        def epoch(carry, _):
            params, opt_state, key = carry
            key, key_perm = jax.random.split(key)
            perm = jax.random.permutation(key_perm, cfg.num_envs)

            def split(x, axis):  # shuffle the worlds, then cut them into m minibatches
                x = jnp.take(x, perm, axis=axis)
                x = x.reshape(x.shape[:axis] + (m, -1) + x.shape[axis + 1 :])
                return jnp.moveaxis(x, axis, 0)

            minibatches = (
                split(carry0, 0),
                jax.tree.map(lambda x: split(x, 1), batch),
                split(advantages, 1),
                split(targets, 1),
            )

            def minibatch_step(carry, minibatch):
                params, opt_state = carry
                (_, info), grads = grad_fn(params, *minibatch, ent_coef)
                updates, opt_state = self.optimizer.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), info

            (params, opt_state), info = jax.lax.scan(minibatch_step, (params, opt_state), minibatches)
            return (params, opt_state, key), info

        (params, opt_state, key), info = jax.lax.scan(
            epoch, (state.params, state.opt_state, state.key), None, length=cfg.update_epochs
        )
        metrics = {**jax.tree.map(jnp.mean, info), **stats}
        state = state.replace(params=params, opt_state=opt_state, key=key, update=state.update + 1)
        return state, metrics

    def train_chunk(self, state: RunnerState, env_params, num_updates: int) -> tuple[RunnerState, dict]:
        """`num_updates` updates; metrics stacked along a leading axis of that length."""
        return jax.lax.scan(lambda s, _: self.update(s, env_params), state, None, length=num_updates)

    # --- acting ---------------------------------------------------------------------------------

    def policy(self, params) -> Policy:
        """The trained network as a greedy `Policy` for one environment (vmap it for a batch)."""
        network, layout = self.network, self.layout

        def init(key, design):
            return {"carry": network.initial_carry(1)[0], **layout.episode_start_memory()}

        def act(params, policy_state, obs, key):
            net_obs = layout.acting_inputs(obs, policy_state)
            carry, logits, _ = network.apply(
                params, policy_state["carry"][None], net_obs[None, None], policy_state["reset"][None, None]
            )
            action = jnp.argmax(logits[0, 0]).astype(jnp.int32)
            return action, {"carry": carry[0], **layout.remember(obs, action)}

        kind = "recurrent" if self.config.recurrent else "feed-forward"
        return Policy(init, act, params, f"{self.config.algorithm}-{kind}")


def clipped_objective(logits, value, batch: Transition, advantages, targets, ent_coef, cfg: PPOConfig):
    """PPO's loss on a minibatch `(T, B)`: the clipped surrogate, the clipped value loss and the
    entropy bonus; returns `(loss, info)`."""
    pi = distrax.Categorical(logits=logits)
    log_prob = pi.log_prob(batch.action)
    clipped_value = batch.value + jnp.clip(value - batch.value, -cfg.clip_eps, cfg.clip_eps)
    value_loss = 0.5 * jnp.maximum((value - targets) ** 2, (clipped_value - targets) ** 2).mean()
    ratio = jnp.exp(log_prob - batch.log_prob)
    advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    actor_loss = -jnp.minimum(
        ratio * advantages, jnp.clip(ratio, 1 - cfg.clip_eps, 1 + cfg.clip_eps) * advantages
    ).mean()
    entropy = pi.entropy().mean()
    total = actor_loss + cfg.vf_coef * value_loss - ent_coef * entropy
    approx_kl = ((ratio - 1) - jnp.log(ratio)).mean()
    info = {
        "loss": total,
        "value_loss": value_loss,
        "actor_loss": actor_loss,
        "entropy": entropy,
        "approx_kl": approx_kl,
    }
    return total, info


def make_train(config: PPOConfig):
    """The whole run as a pure function of a key: `jax.jit(jax.vmap(make_train(c)))(keys)`."""
    ppo = PPO(config)

    def train(key: jax.Array) -> tuple[RunnerState, dict[str, jax.Array]]:
        return ppo.train_chunk(ppo.init(key), ppo.env_params, ppo.config.num_updates)

    return train
