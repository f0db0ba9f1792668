"""DQN acting and learning in one jitted loop, with replay on device. DRQN (`agents.drqn`) and
DRQN + hindsight (`agents.hindsight`) extend the `DQN` class here through its hooks.

`DQN(config)`'s methods are pure and plug into the shared driver (`agents.driver`):

- `init(key) -> RunnerState` for one seed;
- `update(state, env_params)`: every world acts epsilon-greedily for `rollout_steps` steps, the
  steps are appended to the replay buffer, then `gradient_steps` gradient steps are taken on
  sampled sequences (once the buffer holds `learning_starts` steps);
- `train_chunk(state, env_params, n)`: `n` updates in a `lax.scan`;
- `policy(params)`: the greedy `snac_jax.policy.Policy` the evaluator runs.

Replay is a flashbax trajectory buffer on device: one row per world, time along the row, each
entry a `Step`. A sample is `batch_size` windows of `sample_length` consecutive steps of one world
(`DQNConfig.sample_length`): first the context (the frame stack's earlier frames, then the
recurrent burn-in, which only warms the LSTM state: its output carry is cut from the gradient),
then `sequence_length` steps that get a loss, then `n_step` steps to bootstrap from. A window can
cross episode boundaries: `reset` (this observation starts an episode) zeroes the LSTM state and
the frame stack there, and `done` (the episode ended at this step) cuts the n-step return.
Reaching the step limit is an end like any other: the step counter N_s is in the observation, so
the limit is part of the observed state and nothing lies beyond it to bootstrap from.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import flashbax as fbx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from agents.config import TrainConfig, option
from agents.networks import ObsLayout, QNetwork, frames_with_history, stack_frames
from agents.targets import n_step_targets
from snac_jax.policy import Policy


@dataclasses.dataclass(frozen=True)
class DQNConfig(TrainConfig):
    """DQN with double Q-learning, a dueling head, n-step returns and an optional stack of the
    last `frame_stack` observations."""

    algorithm: ClassVar[str] = "dqn"
    paper_method: ClassVar[str] = "dqn"

    rollout_steps: int = option(8, "steps per world between learning phases", low=1)
    gradient_steps: int = option(1, "gradient steps per learning phase", low=1)
    batch_size: int = option(256, "sampled sequences per gradient step", low=1)
    sequence_length: int = option(1, "steps per sampled sequence that get a loss", low=1)
    buffer_size: int = option(500_000, "replay capacity in env steps, over all worlds of a seed", low=1)
    max_buffer_mb: float = option(2048.0, "the config is refused when the replay memory would exceed this",
                                  low=0, low_open=True)
    learning_rate: float = option(3e-4, "Adam step size", low=0, low_open=True)
    gamma: float = option(0.99, "discount", low=0, high=1)
    n_step: int = option(3, "steps of reward before the bootstrap", low=1)
    huber_delta: float = option(1.0, "Huber loss threshold", low=0, low_open=True)
    max_grad_norm: float = option(10.0, "global gradient norm clip", low=0, low_open=True)
    eps_start: float = option(1.0, "exploration rate at the start", low=0, high=1)
    eps_end: float = option(0.05, "exploration rate after the decay", low=0, high=1)
    exploration_fraction: float = option(0.3, "share of total_steps over which epsilon decays linearly", low=0, high=1)
    learning_starts: int = option(20_000, "env steps per seed before the first gradient step", low=0)
    target_update_interval: int = option(250, "gradient steps between copies into the target network", low=1)
    hidden_size: int = option(128, "width of the encoder and the heads", low=1)
    dueling: bool = option(True, "separate value and advantage heads")
    double_q: bool = option(True, "the online network picks the bootstrap action")
    frame_stack: int = option(1, "observations the network reads at once (the newest and those before it)", low=1)
    reward_scale: float = option(0.1, "rewards are multiplied by this for learning (not for reporting)",
                                 low=0, low_open=True)

    @property
    def context(self) -> int:
        """Steps before the first learning step of a sampled sequence: one whose observation is
        read only as the next step's previous step (with `previous_step`), and the frame stack's
        context (DRQN adds its burn-in)."""
        return int(self.previous_step) + self.frame_stack - 1

    @property
    def sample_length(self) -> int:
        """Steps per sampled sequence: context, learning steps, and n more to bootstrap from."""
        return self.context + self.sequence_length + self.n_step

    def check(self) -> None:
        per_world = self.buffer_size // self.num_envs
        if per_world < self.sample_length + self.rollout_steps:
            raise ValueError(
                f"buffer_size ({self.buffer_size}) holds {per_world} steps per world; it must hold at least "
                f"sample_length + rollout_steps = {self.sample_length + self.rollout_steps} (raise buffer_size or lower num_envs)"
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


# --- the algorithm -----------------------------------------------------------------------------------


class DQN:
    """Static pieces of a DQN run; see the module docstring. Subclasses change the network core
    (`lstm_size`, `burn_in`), what a stored step records (`_example_step`, `_world_step`) and how
    a sampled batch is read (`sample`)."""

    lstm_size = 0  # feed-forward
    burn_in = 0

    def __init__(self, config: DQNConfig):
        config.validate()
        self.config = config
        self.env, self.env_params = config.make_env()
        self.layout = ObsLayout.from_env(self.env, self.env_params, previous_step=config.previous_step)
        self.network = QNetwork(
            layout=self.layout,
            num_actions=self.env.num_actions,
            hidden_size=config.hidden_size,
            lstm_size=self.lstm_size,
            dueling=config.dueling,
        )
        self.per_world = config.buffer_size // config.num_envs
        self.buffer = fbx.make_trajectory_buffer(
            add_batch_size=config.num_envs,
            sample_batch_size=config.batch_size,
            sample_sequence_length=config.sample_length,
            period=1,
            min_length_time_axis=config.sample_length,
            max_length_time_axis=self.per_world,
        )
        self.optimizer = optax.chain(
            optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.learning_rate, eps=1e-5)
        )
        self.epsilon = optax.linear_schedule(
            config.eps_start, config.eps_end, max(1, int(config.exploration_fraction * config.total_steps))
        )
        high = self.env.observation_space(self.env_params).high
        if np.max(high) >= np.iinfo(np.int16).max:
            raise ValueError(f"observations reach {np.max(high)}, beyond the int16 the replay stores them in")
        self.check_memory()

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
        return (f"replay on device: {self.per_world} steps x {self.config.num_envs} worlds per seed; {parts} "
                f"(limit {self.config.max_buffer_mb:g} MiB)")

    # --- pure functions ----------------------------------------------------------------------------

    def _initial_worlds(self, env_state, obs: jax.Array) -> Worlds:
        cfg, n = self.config, self.config.num_envs
        history = jnp.zeros((n, cfg.frame_stack - 1, self.layout.obs_size), jnp.float32) if cfg.frame_stack > 1 else None
        return Worlds(
            env_state=env_state, obs=obs, previous_obs=obs, last_action=jnp.zeros((n,), jnp.int32), history=history,
            reset=jnp.ones((n,), bool), carry=self.network.initial_carry(n),
            episode_return=jnp.zeros((n,), jnp.float32), episode=jnp.zeros((n,), jnp.int32),
        )

    def init(self, key: jax.Array) -> RunnerState:
        key, key_params, key_reset = jax.random.split(key, 3)
        reset = jax.vmap(self.env.reset, in_axes=(0, None))
        obs, env_state = reset(jax.random.split(key_reset, self.config.num_envs), self.env_params)
        worlds = self._initial_worlds(env_state, obs)
        net_obs = self.layout.with_previous_step(obs, obs, worlds.last_action, worlds.reset)
        frames = frames_with_history(worlds.history, net_obs)
        params = self.network.init(key_params, worlds.carry[:1], frames[None, :1], jnp.ones((1, 1), bool))
        zero = jnp.zeros((), jnp.int32)
        return RunnerState(
            params=params, target_params=params, opt_state=self.optimizer.init(params), worlds=worlds,
            buffer=self.buffer.init(self._example_step()), key=key, update=zero, gradient_step=zero, env_steps=zero,
        )

    def _world_step(self, worlds: Worlds, keys: jax.Array, action: jax.Array, env_params):
        """Every world steps with the environment's own auto-reset; returns the new environment
        state and observation, reward, done, `info` and the `Step` to store."""
        obs, env_state, reward, terminated, truncated, info = jax.vmap(self.env.step, in_axes=(0, 0, 0, None))(
            keys, worlds.env_state, action, env_params
        )
        done = terminated | truncated
        step = Step(obs=worlds.obs.astype(jnp.int16), reset=worlds.reset, action=action.astype(jnp.int8),
                    reward=reward, done=done)
        return env_state, obs, reward, done, info, step, worlds

    def _env_step(self, params, worlds: Worlds, key: jax.Array, env_steps: jax.Array, env_params):
        """One epsilon-greedy step in every world."""
        n, cfg = self.config.num_envs, self.config
        key_explore, key_random, key_step = jax.random.split(key, 3)
        net_obs = self.layout.with_previous_step(worlds.obs, worlds.previous_obs, worlds.last_action, worlds.reset)
        frames = frames_with_history(worlds.history, net_obs)
        carry, q = self.network.apply(params, worlds.carry, frames[None], worlds.reset[None])
        explore = jax.random.uniform(key_explore, (n,)) < self.epsilon(env_steps)
        action = jnp.where(explore, jax.random.randint(key_random, (n,), 0, self.env.num_actions), jnp.argmax(q[0], -1))
        env_state, obs, reward, done, info, step, worlds = self._world_step(
            worlds, jax.random.split(key_step, n), action, env_params
        )

        history = worlds.history
        if cfg.frame_stack > 1:
            history = jnp.concatenate([history[:, 1:], net_obs[:, None]], axis=1)
            history = jnp.where(done[:, None, None], 0.0, history)
        episode_return = worlds.episode_return + reward
        stats = {
            "episodes": done.sum(),
            "iou_sum": jnp.where(done, info["final_iou"], 0.0).sum(),
            "return_sum": jnp.where(done, episode_return, 0.0).sum(),
        }
        worlds = worlds.replace(
            env_state=env_state, obs=obs, previous_obs=worlds.obs, last_action=action.astype(jnp.int32),
            history=history, reset=done, carry=carry, episode_return=jnp.where(done, 0.0, episode_return),
            episode=worlds.episode + done.astype(jnp.int32),
        )
        return worlds, step, stats

    def _rollout(self, state: RunnerState, env_params):
        def body(carry, _):
            worlds, key, env_steps = carry
            key, key_step = jax.random.split(key)
            worlds, step, stats = self._env_step(state.params, worlds, key_step, env_steps, env_params)
            return (worlds, key, env_steps + self.config.num_envs), (step, stats)

        (worlds, key, env_steps), (steps, stats) = jax.lax.scan(
            body, (state.worlds, state.key, state.env_steps), None, length=self.config.rollout_steps
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
        and reads as an episode start; `loss` drops it (`DQNConfig.context` counts it)."""
        previous_obs = jnp.concatenate([obs[:1], obs[:-1]], axis=0)
        last_action = jnp.concatenate([actions[:1], actions[:-1]], axis=0).astype(jnp.int32)
        first = jnp.zeros_like(resets).at[0].set(True)
        return self.layout.with_previous_step(obs, previous_obs, last_action, resets | first)

    def sequence_q(self, params, frames: jax.Array, resets: jax.Array) -> tuple[jax.Array, Any]:
        """Q-values `(T - burn_in, S, A)` of a sampled window from a zero LSTM state, and what the
        network sowed along them (auxiliary heads, `agents.auxiliary`); the burn-in only warms the
        state (its carry is cut from the gradient)."""
        carry = self.network.initial_carry(frames.shape[1])
        if self.burn_in:
            carry, _ = self.network.apply(params, carry, frames[: self.burn_in], resets[: self.burn_in])
            carry = jax.lax.stop_gradient(carry)
        (_, q), sown = self.network.apply(params, carry, frames[self.burn_in :], resets[self.burn_in :], mutable="intermediates")
        return q, sown

    def loss(self, params, target_params, batch: Step, obs, rewards, mask):
        cfg = self.config
        k, length, c = cfg.frame_stack, cfg.sequence_length, cfg.context
        p = int(cfg.previous_step)  # the first row only lends its window and action to the second
        inputs = self.network_inputs(obs, batch.action, batch.reset)[p:]
        frames = stack_frames(inputs, batch.reset[p:], k)
        resets = batch.reset[p + k - 1 :]
        q, sown = self.sequence_q(params, frames, resets)  # (length + n, S, A), index 0 = batch index c
        q_target = jax.lax.stop_gradient(self.sequence_q(target_params, frames, resets)[0])
        greedy_from = jax.lax.stop_gradient(q) if cfg.double_q else q_target
        next_action = jnp.argmax(greedy_from, axis=-1)
        values = jnp.take_along_axis(q_target, next_action[..., None], axis=-1)[..., 0]
        targets = n_step_targets(
            rewards[c:] * cfg.reward_scale, batch.done[c:], values, cfg.gamma, cfg.n_step, length
        )
        actions = batch.action[c : c + length].astype(jnp.int32)
        q_taken = jnp.take_along_axis(q[:length], actions[..., None], axis=-1)[..., 0]
        weights = mask[c : c + length]
        errors = optax.huber_loss(q_taken, jax.lax.stop_gradient(targets), delta=cfg.huber_delta)
        loss = (errors * weights).sum() / jnp.maximum(weights.sum(), 1.0)
        info = {"loss": loss, "q_mean": (q_taken * weights).sum() / jnp.maximum(weights.sum(), 1.0)}
        return self.auxiliary_losses(loss, info, sown, batch, weights)

    def auxiliary_losses(self, loss, info, sown, batch: Step, weights) -> tuple[jax.Array, dict]:
        """A hook for losses on what the network sowed (`agents.auxiliary`): none in DQN."""
        return loss, info

    def gradient_step(self, state: RunnerState) -> tuple[RunnerState, dict]:
        key, key_sample = jax.random.split(state.key)
        batch, obs, rewards, mask = self.sample(state, key_sample)
        (_, info), grads = jax.value_and_grad(self.loss, has_aux=True)(
            state.params, state.target_params, batch, obs, rewards, mask
        )
        updates, opt_state = self.optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        gradient_step = state.gradient_step + 1
        target_params = optax.periodic_update(params, state.target_params, gradient_step, self.config.target_update_interval)
        state = state.replace(params=params, target_params=target_params, opt_state=opt_state, key=key,
                              gradient_step=gradient_step)
        return state, info

    def update(self, state: RunnerState, env_params) -> tuple[RunnerState, dict[str, jax.Array]]:
        cfg = self.config
        state, steps, stats = self._rollout(state, env_params)
        buffer = self.buffer.add(state.buffer, jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), steps))
        state = state.replace(buffer=buffer)

        def learn(state):
            state, info = jax.lax.scan(lambda s, _: self.gradient_step(s), state, None, length=cfg.gradient_steps)
            return state, jax.tree.map(jnp.mean, info)

        def wait(state):  # zeros in place of every metric a gradient step reports
            return state, jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), jax.eval_shape(learn, state)[1])

        ready = self.buffer.can_sample(buffer) & (state.env_steps >= cfg.learning_starts)
        state, info = jax.lax.cond(ready, learn, wait, state)
        filled = jnp.where(buffer.is_full, self.per_world, buffer.current_index) / self.per_world
        metrics = {**info, **stats, "epsilon": self.epsilon(state.env_steps), "buffer_fill": filled,
                   "gradient_steps": state.gradient_step}
        return state.replace(update=state.update + 1), metrics

    def train_chunk(self, state: RunnerState, env_params, num_updates: int) -> tuple[RunnerState, dict]:
        """`num_updates` updates; metrics stacked along a leading axis of that length."""
        return jax.lax.scan(lambda s, _: self.update(s, env_params), state, None, length=num_updates)

    # --- acting ------------------------------------------------------------------------------------

    def policy(self, params) -> Policy:
        """The greedy policy for one environment (vmap it for a batch)."""
        network, k, layout = self.network, self.config.frame_stack, self.layout

        def init(key, design):
            history = jnp.zeros((k - 1, layout.obs_size), jnp.float32) if k > 1 else None
            return {"carry": network.initial_carry(1)[0], "history": history, **layout.episode_start_memory()}

        def act(params, policy_state, obs, key):
            frames = frames_with_history(policy_state["history"], layout.acting_inputs(obs, policy_state))
            carry, q = network.apply(params, policy_state["carry"][None], frames[None, None], policy_state["reset"][None, None])
            history = frames[1:] if k > 1 else None
            action = jnp.argmax(q[0, 0]).astype(jnp.int32)
            return action, {"carry": carry[0], "history": history, **layout.remember(obs, action)}

        return Policy(init, act, params, self.config.algorithm)
