"""PQN and PQN-RNN (Gallici et al. 2024, "Simplifying Deep Temporal Difference Learning"): Q-learning
with neither replay buffer nor target network, made stable by LayerNorm in the Q-network and
made fast by many vectorised worlds, trained end-to-end inside `jit`, PureJaxRL-style.

One update: every world acts epsilon-greedily for `rollout_steps` steps (epsilon decays linearly),
the rollout's Q(lambda) returns are computed (`agents.common.targets.q_lambda`), then `update_epochs`
passes over `num_minibatches` minibatches of worlds regress Q(s, a) on them, as PPO's epochs do.
PQN-RNN (`recurrent=True`, the default) has a GRU core and learns on each world's whole
rollout from the carry it had at the rollout's start, as recurrent PPO does.

`PQN(config)`'s methods are pure and plug into the shared driver (`agents.training.driver`): `init`,
`rollout`, `update`, `train_chunk` and `policy` (the greedy policy the evaluator runs).
`make_train(config)` returns the whole run as a pure `train(key)`.

The targets bootstrap from the Q-values the rollout itself computed: the parameters do not change
during a rollout, and the GRU's state at each step is the one a pass over the sequence from the
rollout's start carry gives, so recomputing them would give the same numbers. A truncated episode
bootstraps from `max_a Q` of `info["final_observation"]` (before the auto-reset), scored with the
carry that saw the episode; a terminated one bootstraps nothing. With `time_limit_ends` the step
limit ends the return as a termination does: the observation holds the step count, so the limit is
part of the task, and the bootstrap reads a state (the count at the limit) no update trains on.
DRQN and Rainbow treat the limit so.

The module forks alone: besides `snac_jax` it reads only the library modules `agents.training.config`,
`agents.common.inputs`, `agents.common.networks`, `agents.common.safe_drops` and `agents.common.targets`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from agents.common.inputs import ObsLayout
from agents.common.networks import LayerNormQNetwork, apply_with_design_cache, first_design_cache
from agents.common.safe_drops import allowed_actions, masked_q, random_allowed, require_obstacles
from agents.common.targets import q_lambda, truncation_values
from agents.training.config import TrainConfig, option
from snac_jax.policy import Policy


@dataclasses.dataclass(frozen=True)
class PQNConfig(TrainConfig):
    """PQN: epsilon-greedy Q(lambda) over parallel worlds, LayerNorm Q-network, optional GRU. The
    defaults are the settings tuned on 1d-static-sin (`agents/tuned/pqn.toml` overrides them per
    task)."""

    algorithm: ClassVar[str] = "pqn"
    paper_method: ClassVar[str] = "pqn"  # the paper has no PQN row: its columns stay empty
    acting_options: ClassVar[tuple[str, ...]] = ("safe_drops",)

    recurrent: bool = option(True, "GRU Q-network (PQN-RNN) instead of a feed-forward one")
    total_steps: int = option(10_000_000, "env steps per seed", low=1)
    num_envs: int = option(64, "parallel worlds per seed (split over devices)", low=1)
    rollout_steps: int = option(64, "steps per world between updates", low=1)
    update_epochs: int = option(2, "passes over each rollout", low=1)
    num_minibatches: int = option(4, "minibatches per pass; they split the worlds (whole sequences for the GRU)", low=1)
    learning_rate: float = option(3e-3, "RAdam step size", low=0, low_open=True)
    anneal_lr: bool = option(True, "decay the learning rate linearly to 0 over the run")
    gamma: float = option(0.99, "discount", low=0, high=1)
    q_lambda: float = option(0.8, "lambda of the Q(lambda) returns (0: one-step Q-learning targets)", low=0, high=1)
    eps_start: float = option(1.0, "exploration rate at the first update", low=0, high=1)
    eps_end: float = option(0.01, "exploration rate after the decay", low=0, high=1)
    exploration_fraction: float = option(0.2, "share of the updates over which epsilon decays linearly", low=0, high=1)
    max_grad_norm: float = option(10.0, "global gradient norm clip", low=0, low_open=True)
    hidden_size: int = option(64, "width of the encoder and the Q head", low=1)
    rnn_size: int = option(32, "GRU units (recurrent only)", low=1)
    reward_scale: float = option(
        0.01, "rewards are multiplied by this for learning (not for reporting)", low=0, low_open=True
    )
    time_limit_ends: bool = option(
        False,
        "the step limit ends the return (no bootstrap from the final observation), "
        "as a termination does: the observation holds the step count",
    )
    stagger_starts: bool = option(
        True,
        "start each world a random number (up to an episode) of random steps in, "
        "so that the worlds' rollouts hold different parts of their episodes",
    )
    safe_drops: bool = option(
        False,
        "never drop on the robot's last free neighbour, read from the window: that drop "
        "walls it in under the obstacle rule (agents.common.safe_drops)",
    )

    def check(self) -> None:
        if self.safe_drops:
            require_obstacles(self.env_config(), self.task)
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
    value: jax.Array  # max_a Q(obs, a) as the rollout computed it
    reward: jax.Array
    terminated: jax.Array
    truncated: jax.Array
    final_obs: jax.Array  # the episode's last observation where it ended
    carry_after: jax.Array  # carry after seeing `obs`: scores `final_obs` for truncation bootstrap


class PQN:
    """Static pieces of a PQN run; see the module docstring."""

    def __init__(self, config: PQNConfig):
        config.validate()
        self.config = config
        self.env, self.env_params = config.make_env()
        self.layout = ObsLayout.from_env(self.env, self.env_params, previous_step=config.previous_step)
        self.network = LayerNormQNetwork(
            layout=self.layout,
            num_actions=self.env.num_actions,
            hidden_size=config.hidden_size,
            rnn_size=config.rnn_size if config.recurrent else 0,
        )
        gradient_steps = config.num_updates * config.update_epochs * config.num_minibatches
        lr = (
            optax.linear_schedule(config.learning_rate, 0.0, gradient_steps)
            if config.anneal_lr
            else config.learning_rate
        )
        # RAdam as in the paper's code: its rectified early steps need no warm-up while the
        # bootstrapped targets are still moving fast.
        self.optimizer = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.radam(lr))
        self.epsilon = optax.linear_schedule(
            config.eps_start, config.eps_end, max(1, int(config.exploration_fraction * config.num_updates))
        )

    # --- pure functions -------------------------------------------------------------------------

    def init(self, key: jax.Array) -> RunnerState:
        n = self.config.num_envs
        key, key_params, key_reset = jax.random.split(key, 3)
        obs, env_state = jax.vmap(self.env.reset, in_axes=(0, None))(jax.random.split(key_reset, n), self.env_params)
        if self.config.stagger_starts:
            obs, env_state = self._stagger(jax.random.fold_in(key_reset, 1), obs, env_state)
        worlds = Worlds(
            env_state=env_state,
            obs=obs,
            previous_obs=obs,
            last_action=jnp.zeros((n,), jnp.int32),
            reset=jnp.ones((n,), bool),
            carry=self.network.initial_carry(n),
            episode_return=jnp.zeros((n,), jnp.float32),
        )
        params = self.network.init(
            key_params, worlds.carry[:1], self._network_obs(worlds)[None, :1], jnp.ones((1, 1), bool)
        )
        return RunnerState(
            params=params,
            opt_state=self.optimizer.init(params),
            worlds=worlds,
            key=key,
            update=jnp.zeros((), jnp.int32),
        )

    def _stagger(self, key: jax.Array, obs: jax.Array, env_state) -> tuple[jax.Array, Any]:
        """Each world takes a uniformly random number (below the step limit) of uniformly random
        actions before training starts. Why: all worlds start together, and on the tasks whose
        episodes all run to the step limit (1D static) they stay in phase, so every rollout
        would hold the same slice of the episode in every world and each update would learn from
        one part of the episode only. These steps are neither learned from nor counted; the
        first episode of each world is reported from its true start (its IoU) but its return
        counts only the steps after them."""
        n, limit = self.config.num_envs, int(self.env_params.max_steps_in_episode)
        step = jax.vmap(self.env.step, in_axes=(0, 0, 0, None))
        key_count, key = jax.random.split(key)
        count = jax.random.randint(key_count, (n,), 0, limit)

        def random_step(t, carry):
            obs, env_state, key = carry
            key, key_action, key_step = jax.random.split(key, 3)
            action = jax.random.randint(key_action, (n,), 0, self.env.num_actions)
            stepped = step(jax.random.split(key_step, n), env_state, action, self.env_params)[:2]
            keep = lambda new, old: jnp.where((t < count).reshape((n,) + (1,) * (new.ndim - 1)), new, old)
            return (*jax.tree.map(keep, stepped, (obs, env_state)), key)

        obs, env_state, _ = jax.lax.fori_loop(0, limit, random_step, (obs, env_state, key))
        return obs, env_state

    def _network_obs(self, worlds: Worlds) -> jax.Array:
        return self.layout.with_previous_step(worlds.obs, worlds.previous_obs, worlds.last_action, worlds.reset)

    def epsilon_greedy(
        self, key_explore: jax.Array, key_random: jax.Array, q: jax.Array, net_obs: jax.Array, epsilon: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """Each world's action `(B,)`, epsilon-greedy over the actions `allowed` on `net_obs`, and
        the Q-values `(B, A)` with the refused ones at -inf: their max is what the targets bootstrap
        from. The rollouts of the PQN learners all act through it."""
        allowed = self.allowed(net_obs)
        q = masked_q(q, allowed)
        explore = jax.random.uniform(key_explore, q.shape[:1]) < epsilon
        return jnp.where(explore, random_allowed(key_random, allowed, q.shape[:1], q.shape[-1]), jnp.argmax(q, -1)), q

    def allowed(self, net_obs: jax.Array) -> jax.Array | None:
        """`(..., num_actions)` the actions open to the policy on `net_obs` (which starts with the
        window, `ObsLayout`): all but the drops that wall the robot in with `safe_drops`; None
        (all of them) without it."""
        if not self.config.safe_drops:
            return None
        return allowed_actions(self.env.config, net_obs[..., : self.layout.window_size])

    def rollout(self, state: RunnerState, env_params) -> tuple[RunnerState, Transition, dict]:
        """`rollout_steps` epsilon-greedy steps in every world, no learning."""
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
            transition = Transition(
                obs=net_obs,
                reset=worlds.reset,
                action=action,
                value=q.max(-1),
                reward=reward,
                terminated=terminated,
                truncated=truncated,
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
        return state.replace(worlds=worlds, key=key), batch, jax.tree.map(jnp.sum, stats)

    def targets(self, params, batch: Transition, worlds: Worlds) -> jax.Array:
        """`(T, B)` Q(lambda) returns of a rollout; `worlds` is where the rollout stopped."""
        cfg = self.config
        last_obs = self._network_obs(worlds)
        _, last_q = self.network.apply(params, worlds.carry, last_obs[None], worlds.reset[None])
        next_values = jnp.concatenate(
            [batch.value[1:], masked_q(last_q[0], self.allowed(last_obs)).max(-1)[None]], axis=0
        )

        def score(carry, obs):
            _, q = self.network.apply(params, carry, obs[None], jnp.zeros((1, obs.shape[0]), bool))
            return masked_q(q[0], self.allowed(obs)).max(-1)

        if cfg.time_limit_ends:
            terminated, truncated = batch.terminated | batch.truncated, jnp.zeros_like(batch.truncated)
            final_values = jnp.zeros_like(batch.reward)
        else:
            terminated, truncated = batch.terminated, batch.truncated & ~batch.terminated
            final_values = truncation_values(
                score, truncated, batch.final_obs, batch.carry_after, self.layout.max_truncations(truncated.shape[0])
            )
        return q_lambda(
            batch.reward * cfg.reward_scale, next_values, final_values, terminated, truncated, cfg.gamma, cfg.q_lambda
        )

    def _loss(self, params, carry0, batch: Transition, targets):
        _, q = self.network.apply(params, carry0, batch.obs, batch.reset)
        return td_loss(q, batch.action, targets)

    def update(self, state: RunnerState, env_params) -> tuple[RunnerState, dict[str, jax.Array]]:
        cfg, m = self.config, self.config.num_minibatches
        carry0 = state.worlds.carry
        epsilon = self.epsilon(state.update)
        state, batch, stats = self.rollout(state, env_params)
        targets = self.targets(state.params, batch, state.worlds)
        batch = batch._replace(final_obs=None, carry_after=None)  # only the bootstrap values read them
        grad_fn = jax.value_and_grad(self._loss, has_aux=True)

        def epoch(carry, _):
            params, opt_state, key = carry
            key, key_perm = jax.random.split(key)
            perm = jax.random.permutation(key_perm, cfg.num_envs)

            def split(x, axis):  # shuffle the worlds, cut them into m minibatches along a new axis 0
                x = jnp.take(x, perm, axis=axis)
                return jnp.moveaxis(x.reshape(x.shape[:axis] + (m, -1) + x.shape[axis + 1 :]), axis, 0)

            minibatches = (split(carry0, 0), jax.tree.map(lambda x: split(x, 1), batch), split(targets, 1))

            def minibatch_step(carry, minibatch):
                params, opt_state = carry
                (_, info), grads = grad_fn(params, *minibatch)
                updates, opt_state = self.optimizer.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), info

            (params, opt_state), info = jax.lax.scan(minibatch_step, (params, opt_state), minibatches)
            return (params, opt_state, key), info

        (params, opt_state, key), info = jax.lax.scan(
            epoch, (state.params, state.opt_state, state.key), None, length=cfg.update_epochs
        )
        metrics = {**jax.tree.map(jnp.mean, info), **stats, "epsilon": epsilon, "target_mean": targets.mean()}
        return state.replace(params=params, opt_state=opt_state, key=key, update=state.update + 1), metrics

    def train_chunk(self, state: RunnerState, env_params, num_updates: int) -> tuple[RunnerState, dict]:
        """`num_updates` updates; metrics stacked along a leading axis of that length."""
        return jax.lax.scan(lambda s, _: self.update(s, env_params), state, None, length=num_updates)

    # --- acting ---------------------------------------------------------------------------------

    def policy(self, params) -> Policy:
        """The greedy policy (argmax Q) for one environment (vmap it for a batch)."""
        network, layout, allowed = self.network, self.layout, self.allowed

        def init(key, design):
            return {"carry": network.initial_carry(1)[0], **layout.episode_start_memory()}

        def act(params, policy_state, obs, key):
            net_obs = layout.acting_inputs(obs, policy_state)
            carry, q = network.apply(
                params, policy_state["carry"][None], net_obs[None, None], policy_state["reset"][None, None]
            )
            action = jnp.argmax(masked_q(q[0, 0], allowed(net_obs))).astype(jnp.int32)
            return action, {"carry": carry[0], **layout.remember(obs, action)}

        kind = "recurrent" if self.config.recurrent else "feed-forward"
        return Policy(init=init, act=act, params=params, name=f"{self.config.algorithm}-{kind}")


def td_loss(q: jax.Array, action: jax.Array, targets: jax.Array) -> tuple[jax.Array, dict]:
    """Half the mean squared error of Q(s, a) `(T, B)` of the taken actions against the targets."""
    q_taken = jnp.take_along_axis(q, action[..., None].astype(jnp.int32), axis=-1)[..., 0]
    loss = 0.5 * jnp.mean((q_taken - targets) ** 2)
    return loss, {"loss": loss, "q_mean": q_taken.mean()}


def make_train(config: PQNConfig):
    """The whole run as a pure function of a key: `jax.jit(jax.vmap(make_train(c)))(keys)`."""
    pqn = PQN(config)

    def train(key: jax.Array) -> tuple[RunnerState, dict[str, jax.Array]]:
        return pqn.train_chunk(pqn.init(key), pqn.env_params, pqn.config.num_updates)

    return train
