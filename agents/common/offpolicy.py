"""Acting into a replay buffer on device and learning from windows sampled from it, in one jitted
loop: what the Q-learners (`agents.learners.dqn` and its extensions) and SAC (`agents.learners.sac`) share.

`ReplayLearner(config)`'s methods are pure and plug into the shared driver (`agents.training.driver`):

- `init(key) -> RunnerState` for one seed;
- `update(state, env_params)`: every world acts for `rollout_steps` steps (`act`, the learner's
  exploration), the steps are appended to the replay buffer, then `gradient_steps` gradient steps
  are taken on sampled windows (once the buffer holds `learning_starts` steps);
- `train_chunk(state, env_params, n)`: `n` updates in a `lax.scan`;
- `policy(params)`: the greedy `snac_jax.policy.Policy` the evaluator runs (argmax of
  `action_scores`).

A learner subclass supplies its networks and optimiser (in `__init__`, after this class's),
`init_params`, `action_scores`, `act`, `loss`, `update_target` and `acting_metrics`; it may replace
the replay (`make_buffer`), take more keys to act with (`acting_keys`), and a gradient step of its
own can reuse the optimiser step and target update (`apply_gradients`), as Rainbow's prioritised
replay does (`agents.learners.rainbow`).

Replay is a flashbax trajectory buffer on device: one row per world, time along the row, each
entry a `Step`. A sample is `batch_size` windows of `sample_length` consecutive steps of one world
(`ReplayConfig.sample_length`): first the context (the previous step's row, the frame stack's
earlier frames, a recurrent burn-in), then `sequence_length` steps that get a loss, then `n_step`
steps to bootstrap from. A window can cross episode boundaries: `reset` (this observation starts
an episode) zeroes a recurrent state and the frame stack there, and `done` (the episode ended at
this step) cuts the n-step return. Reaching the step limit is an end like any other: the step
counter N_s is in the observation, so the limit is part of the observed state and nothing lies
beyond it to bootstrap from.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flashbax as fbx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from agents.common.inputs import ObsLayout
from agents.common.networks import frames_with_history
from agents.training.config import TrainConfig, option
from snac_jax.policy import Policy


@dataclasses.dataclass(frozen=True)
class ReplayConfig(TrainConfig):
    """The acting loop, the replay buffer and the n-step targets of an off-policy learner."""

    rollout_steps: int = option(8, "steps per world between learning phases", low=1)
    gradient_steps: int = option(1, "gradient steps per learning phase", low=1)
    batch_size: int = option(256, "sampled sequences per gradient step", low=1)
    sequence_length: int = option(1, "steps per sampled sequence that get a loss", low=1)
    buffer_size: int = option(500_000, "replay capacity in env steps, over all worlds of a seed", low=1)
    max_buffer_mb: float = option(
        2048.0, "the config is refused when the replay memory would exceed this", low=0, low_open=True
    )
    gamma: float = option(0.99, "discount", low=0, high=1)
    n_step: int = option(3, "steps of reward before the bootstrap", low=1)
    learning_starts: int = option(20_000, "env steps per seed before the first gradient step", low=0)
    reward_scale: float = option(
        0.1, "rewards are multiplied by this for learning (not for reporting)", low=0, low_open=True
    )

    @property
    def context(self) -> int:
        """Steps before the first learning step of a sampled sequence: one whose observation is
        read only as the next step's previous step (with `previous_step`); DQN adds its frame
        stack's context, DRQN its burn-in."""
        return int(self.previous_step)

    @property
    def sample_length(self) -> int:
        """Steps per sampled sequence: context, learning steps, and n more to bootstrap from."""
        return self.context + self.sequence_length + self.n_step

    def first_learning_update(self) -> int:
        """The first update (counting from 1) that takes gradient steps: the replay must hold a
        sampled window (`sample_length` steps per world; each update adds `rollout_steps`) and
        the run must have taken `learning_starts` env steps (`steps_per_update` per update)."""
        return max(1, -(-self.sample_length // self.rollout_steps), -(-self.learning_starts // self.steps_per_update))

    def check(self) -> None:
        per_world = self.buffer_size // self.num_envs
        if per_world < self.sample_length + self.rollout_steps:
            raise ValueError(
                f"buffer_size ({self.buffer_size}) holds {per_world} steps per world; it must hold at least "
                f"sample_length + rollout_steps = {self.sample_length + self.rollout_steps} (raise buffer_size or lower num_envs)"
            )
        self._check_learns()

    def _check_learns(self) -> None:
        """A run must take at least one gradient step: a run that never learns would still be
        scored and reported as trained."""
        if self.first_learning_update() <= self.num_updates:
            return
        run_steps = self.num_updates * self.steps_per_update
        if self.learning_starts > run_steps:
            raise ValueError(
                f"learning_starts ({self.learning_starts:,}) is beyond the run's {run_steps:,} env steps per seed "
                f"({self.num_updates:,} update(s) of {self.steps_per_update:,}): no gradient step would be taken; "
                f"learning_starts must be at most {run_steps:,} (or raise total_steps)"
            )
        needed = -(-self.sample_length // self.rollout_steps) * self.steps_per_update
        raise ValueError(
            f"the run's {self.num_updates:,} update(s) of rollout_steps {self.rollout_steps} put "
            f"{self.num_updates * self.rollout_steps} steps per world in the replay, fewer than one sampled window "
            f"(sample_length {self.sample_length}): no gradient step would be taken; total_steps must be at least {needed:,}"
        )


# --- replay contents ---------------------------------------------------------------------------------


@struct.dataclass
class Step:
    """One env step of one world as the buffer stores it. Observations are integer counts, so
    they are kept as int16 (half the memory of float32, exact)."""

    obs: jax.Array  # int16 (O,), the observation the action was chosen on
    reset: jax.Array  # bool, `obs` starts an episode
    action: jax.Array  # int8
    reward: jax.Array  # float32, the environment's reward
    done: jax.Array  # bool, the episode ended at this step (terminated or truncated)


@struct.dataclass
class Worlds:
    """Everything with one entry per parallel world (the axis the driver shards over devices)."""

    env_state: Any
    obs: jax.Array  # (B, O) float32, the environment's observation the next action sees
    previous_obs: jax.Array  # (B, O) the observation before it (ignored where `reset`)
    last_action: jax.Array  # (B,) int32, the action that led to `obs` (ignored where `reset`)
    history: jax.Array | None  # (B, k-1, O') the network inputs before this one, oldest first, zeros
    # before the episode; None without a frame stack (orbax cannot save empty arrays)
    reset: jax.Array  # (B,) bool, `obs` starts an episode
    carry: jax.Array  # (B, C) LSTM state (a placeholder for feed-forward)
    episode_return: jax.Array  # (B,)
    episode: jax.Array  # (B,) int32, episodes started so far in this world


@struct.dataclass
class RunnerState:
    params: Any
    target_params: Any
    opt_state: Any
    worlds: Worlds
    buffer: Any  # flashbax TrajectoryBufferState of `Step`s
    key: jax.Array
    update: jax.Array  # int32, iterations done
    gradient_step: jax.Array  # int32, gradient steps done
    env_steps: jax.Array  # int32, env steps taken per world batch (all worlds of the seed)


class ReplayLearner:
    """Static pieces of an off-policy run; see the module docstring. Subclasses may also change
    what a stored step records (`_example_step`, `_world_step`) and how a sampled batch is read
    (`sample`)."""

    frame_stack = 1  # observations per network input (DQN's frame stack)
    acting_keys = 2  # keys `act` gets each step
    optimizer: optax.GradientTransformation  # set by the subclass

    def __init__(self, config: ReplayConfig):
        config.validate()
        self.config = config
        self.env, self.env_params = config.make_env()
        self.layout = ObsLayout.from_env(self.env, self.env_params, previous_step=config.previous_step)
        self.per_world = config.buffer_size // config.num_envs
        self.buffer = self.make_buffer()
        high = self.env.observation_space(self.env_params).high
        if np.max(high) >= np.iinfo(np.int16).max:
            raise ValueError(f"observations reach {np.max(high)}, beyond the int16 the replay stores them in")
        self.check_memory()

    def make_buffer(self):
        """The replay: one row of `per_world` steps per world, sampled as windows of `sample_length`."""
        cfg = self.config
        return fbx.make_trajectory_buffer(
            add_batch_size=cfg.num_envs,
            sample_batch_size=cfg.batch_size,
            sample_sequence_length=cfg.sample_length,
            period=1,
            min_length_time_axis=cfg.sample_length,
            max_length_time_axis=self.per_world,
        )

    def check_memory(self) -> None:
        """Refuse a config whose replay memory exceeds `max_buffer_mb`, before anything is allocated."""
        total = sum(self.memory_bytes().values())
        if total > self.config.max_buffer_mb * 2**20:
            raise ValueError(
                f"replay memory {total / 2**20:.1f} MiB per seed exceeds max_buffer_mb "
                f"({self.config.max_buffer_mb}); lower buffer_size or raise max_buffer_mb"
            )

    def _example_step(self) -> Step:
        return Step(
            obs=jnp.zeros((self.layout.env_obs_size,), jnp.int16),
            reset=jnp.zeros((), bool),
            action=jnp.zeros((), jnp.int8),
            reward=jnp.zeros((), jnp.float32),
            done=jnp.zeros((), bool),
        )

    def memory_bytes(self) -> dict[str, int]:
        """Bytes per seed of what the learner keeps on device beside the networks."""
        buffer = jax.eval_shape(self.buffer.init, self._example_step())
        return {"buffer": sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(buffer))}

    def describe_memory(self) -> str:
        parts = ", ".join(f"{name} {size / 2**20:.1f} MiB" for name, size in self.memory_bytes().items())
        return (
            f"replay on device: {self.per_world} steps x {self.config.num_envs} worlds per seed; {parts} "
            f"(limit {self.config.max_buffer_mb:g} MiB)"
        )

    # --- the learner's hooks -------------------------------------------------------------------

    def initial_carry(self, batch: int) -> jax.Array:
        """The recurrent state at an episode start, `(batch, C)` (a placeholder when feed-forward)."""
        return jnp.zeros((batch, 1), jnp.float32)

    def init_params(self, key: jax.Array, frames: jax.Array) -> tuple[Any, Any]:
        """`(params, target_params)` of a new run, from one network input `frames (1, 1, k, O)`."""
        raise NotImplementedError

    def action_scores(
        self, params, carry: jax.Array, frames: jax.Array, resets: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """`(carry, scores (T, B, A))` whose argmax is the greedy action, from `frames (T, B, k, O)`."""
        raise NotImplementedError

    def act(self, params, worlds: Worlds, frames: jax.Array, keys: jax.Array, env_steps: jax.Array, cache):
        """`(carry, action (B,), cache)`: the exploring action of every world, with `acting_keys`
        keys, its network applied with the design cache `cache` (`apply_with_design_cache`)."""
        raise NotImplementedError

    def loss(self, params, target_params, batch: Step, obs, rewards, mask) -> tuple[jax.Array, dict]:
        """`(loss, metrics)` of a sampled batch (see `sample`), differentiated w.r.t. `params`."""
        raise NotImplementedError

    def update_target(self, params, target_params, gradient_step: jax.Array):
        """The target parameters after gradient step number `gradient_step`."""
        raise NotImplementedError

    def acting_metrics(self, env_steps: jax.Array) -> dict[str, jax.Array]:
        """Metrics of the exploration schedule, logged with each update."""
        return {}

    # --- pure functions ----------------------------------------------------------------------------

    def _initial_worlds(self, env_state, obs: jax.Array) -> Worlds:
        n, k = self.config.num_envs, self.frame_stack
        history = jnp.zeros((n, k - 1, self.layout.obs_size), jnp.float32) if k > 1 else None
        return Worlds(
            env_state=env_state,
            obs=obs,
            previous_obs=obs,
            last_action=jnp.zeros((n,), jnp.int32),
            history=history,
            reset=jnp.ones((n,), bool),
            carry=self.initial_carry(n),
            episode_return=jnp.zeros((n,), jnp.float32),
            episode=jnp.zeros((n,), jnp.int32),
        )

    def init(self, key: jax.Array) -> RunnerState:
        key, key_params, key_reset = jax.random.split(key, 3)
        reset = jax.vmap(self.env.reset, in_axes=(0, None))
        obs, env_state = reset(jax.random.split(key_reset, self.config.num_envs), self.env_params)
        worlds = self._initial_worlds(env_state, obs)
        net_obs = self.layout.with_previous_step(obs, obs, worlds.last_action, worlds.reset)
        frames = frames_with_history(worlds.history, net_obs)
        params, target_params = self.init_params(key_params, frames[None, :1])
        zero = jnp.zeros((), jnp.int32)
        return RunnerState(
            params=params,
            target_params=target_params,
            opt_state=self.optimizer.init(params),
            worlds=worlds,
            buffer=self.buffer.init(self._example_step()),
            key=key,
            update=zero,
            gradient_step=zero,
            env_steps=zero,
        )

    def _world_step(self, worlds: Worlds, keys: jax.Array, action: jax.Array, env_params):
        """Every world steps with the environment's own auto-reset; returns the new environment
        state and observation, reward, done, `info` and the `Step` to store."""
        obs, env_state, reward, terminated, truncated, info = jax.vmap(self.env.step, in_axes=(0, 0, 0, None))(
            keys, worlds.env_state, action, env_params
        )
        done = terminated | truncated
        step = Step(
            obs=worlds.obs.astype(jnp.int16),
            reset=worlds.reset,
            action=action.astype(jnp.int8),
            reward=reward,
            done=done,
        )
        return env_state, obs, reward, done, info, step, worlds

    def _acting_frames(self, worlds: Worlds) -> tuple[jax.Array, jax.Array]:
        """`(net_obs (B, O'), frames (B, k, O'))`: the network input of every world's next action."""
        net_obs = self.layout.with_previous_step(worlds.obs, worlds.previous_obs, worlds.last_action, worlds.reset)
        return net_obs, frames_with_history(worlds.history, net_obs)

    def _env_step(self, params, worlds: Worlds, cache, key: jax.Array, env_steps: jax.Array, env_params):
        """One exploring step in every world; `cache`: the acting network's design cache."""
        n = self.config.num_envs
        keys = jax.random.split(key, self.acting_keys + 1)  # to act with, and the last to step the worlds
        net_obs, frames = self._acting_frames(worlds)
        carry, action, cache = self.act(params, worlds, frames, keys[:-1], env_steps, cache)
        env_state, obs, reward, done, info, step, worlds = self._world_step(
            worlds, jax.random.split(keys[-1], n), action, env_params
        )

        history = worlds.history
        if self.frame_stack > 1:
            history = jnp.concatenate([history[:, 1:], net_obs[:, None]], axis=1)
            history = jnp.where(done[:, None, None], 0.0, history)
        episode_return = worlds.episode_return + reward
        stats = {
            "episodes": done.sum(),
            "iou_sum": jnp.where(done, info["final_iou"], 0.0).sum(),
            "return_sum": jnp.where(done, episode_return, 0.0).sum(),
        }
        worlds = worlds.replace(
            env_state=env_state,
            obs=obs,
            previous_obs=worlds.obs,
            last_action=action.astype(jnp.int32),
            history=history,
            reset=done,
            carry=carry,
            episode_return=jnp.where(done, 0.0, episode_return),
            episode=worlds.episode + done.astype(jnp.int32),
        )
        return worlds, step, stats, cache

    def _rollout(self, state: RunnerState, env_params):
        def body(carry, _):
            worlds, cache, key, env_steps = carry
            key, key_step = jax.random.split(key)
            worlds, step, stats, cache = self._env_step(state.params, worlds, cache, key_step, env_steps, env_params)
            return (worlds, cache, key, env_steps + self.config.num_envs), (step, stats)

        # The design features of each world are kept from step to step (a dynamic task's design
        # is constant for an episode) and encoded again where a world's design changes; each
        # rollout starts from its first step's, encoded in one pass (`first_design_cache`: acting
        # with an empty cache, the action unused), as the parameters changed since the last.
        _, frames = self._acting_frames(state.worlds)
        keys = jax.random.split(state.key, self.acting_keys)
        cache = self.act(state.params, state.worlds, frames, keys, state.env_steps, {})[2]
        (worlds, _, key, env_steps), (steps, stats) = jax.lax.scan(
            body, (state.worlds, cache, state.key, state.env_steps), None, length=self.config.rollout_steps
        )
        state = state.replace(worlds=worlds, key=key, env_steps=env_steps)
        return state, steps, jax.tree.map(jnp.sum, stats)

    def sample(self, state: RunnerState, key: jax.Array) -> tuple[Step, jax.Array, jax.Array, jax.Array]:
        """A training batch, time-major: `(steps (L, S), float observations, rewards, loss mask)`."""
        batch = self.buffer.sample(state.buffer, key).experience
        batch = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), batch)
        return batch, batch.obs.astype(jnp.float32), batch.reward, jnp.ones_like(batch.reward)

    def network_inputs(self, obs: jax.Array, actions: jax.Array, resets: jax.Array) -> jax.Array:
        """What the network reads along a replayed window `(L, S, O)`: each observation with the
        previous step (window and action) taken from the row before it. The first row has none
        and reads as an episode start; `loss` drops it (`ReplayConfig.context` counts it)."""
        previous_obs = jnp.concatenate([obs[:1], obs[:-1]], axis=0)
        last_action = jnp.concatenate([actions[:1], actions[:-1]], axis=0).astype(jnp.int32)
        first = jnp.zeros_like(resets).at[0].set(True)
        return self.layout.with_previous_step(obs, previous_obs, last_action, resets | first)

    def gradient_step(self, state: RunnerState) -> tuple[RunnerState, dict]:
        key, key_sample = jax.random.split(state.key)
        batch, obs, rewards, mask = self.sample(state, key_sample)
        (_, info), grads = jax.value_and_grad(self.loss, has_aux=True)(
            state.params, state.target_params, batch, obs, rewards, mask
        )
        return self.apply_gradients(state.replace(key=key), grads), info

    def apply_gradients(self, state: RunnerState, grads) -> RunnerState:
        """One optimiser step, then the target parameters after it (`update_target`)."""
        updates, opt_state = self.optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        gradient_step = state.gradient_step + 1
        target_params = self.update_target(params, state.target_params, gradient_step)
        return state.replace(
            params=params, target_params=target_params, opt_state=opt_state, gradient_step=gradient_step
        )

    def update(self, state: RunnerState, env_params) -> tuple[RunnerState, dict[str, jax.Array]]:
        cfg = self.config
        state, steps, stats = self._rollout(state, env_params)
        buffer = self.buffer.add(state.buffer, jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), steps))
        state = state.replace(buffer=buffer)

        def learn(state):
            state, info = jax.lax.scan(lambda s, _: self.gradient_step(s), state, None, length=cfg.gradient_steps)
            return state, jax.tree.map(jnp.mean, info)

        def wait(state):  # nothing learned yet: the learning metrics read 0
            shapes = jax.eval_shape(learn, state)[1]
            return state, jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)

        ready = self.buffer.can_sample(buffer) & (state.env_steps >= cfg.learning_starts)
        state, info = jax.lax.cond(ready, learn, wait, state)
        filled = jnp.where(buffer.is_full, self.per_world, buffer.current_index) / self.per_world
        metrics = {
            **info,
            **stats,
            **self.acting_metrics(state.env_steps),
            "buffer_fill": filled,
            "gradient_steps": state.gradient_step,
        }
        return state.replace(update=state.update + 1), metrics

    def train_chunk(self, state: RunnerState, env_params, num_updates: int) -> tuple[RunnerState, dict]:
        """`num_updates` updates; metrics stacked along a leading axis of that length."""
        return jax.lax.scan(lambda s, _: self.update(s, env_params), state, None, length=num_updates)

    # --- acting ------------------------------------------------------------------------------------

    def policy(self, params) -> Policy:
        """The greedy policy for one environment (vmap it for a batch)."""
        k, layout, scores = self.frame_stack, self.layout, self.action_scores
        initial_carry = self.initial_carry

        def init(key, design):
            history = jnp.zeros((k - 1, layout.obs_size), jnp.float32) if k > 1 else None
            return {"carry": initial_carry(1)[0], "history": history, **layout.episode_start_memory()}

        def act(params, policy_state, obs, key):
            frames = frames_with_history(policy_state["history"], layout.acting_inputs(obs, policy_state))
            carry, s = scores(
                params, policy_state["carry"][None], frames[None, None], policy_state["reset"][None, None]
            )
            history = frames[1:] if k > 1 else None
            action = jnp.argmax(s[0, 0]).astype(jnp.int32)
            return action, {"carry": carry[0], "history": history, **layout.remember(obs, action)}

        return Policy(init, act, params, self.config.algorithm)
