"""DQN, DRQN and DRQN + hindsight relabelling, acting and learning in one jitted loop.

`DQN(config)` serves the three algorithms (`agents.config.DQNConfig`, `DRQNConfig`,
`DRQNHERConfig`); its methods are pure and plug into the shared driver (`agents.driver`):

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

Hindsight (drqn-her, paper: "the transitions ... relabeled with D replaced by the grid at the
terminal step; both stored"): each step also records where its brick landed and the cell's
height (`drop_record`), and when a world's episode ends its final grid goes into a small ring per
world (`FinalGrids`). A sampled window read as the relabelled copy (a `hindsight_fraction` of
each batch) gets its rewards recomputed against its episode's final grid with the environment's
own `snac_jax.transition.drop_reward`, and on dynamic tasks the design part of its observations
replaced by that grid. Steps of an episode that has not ended yet have no relabelled copy yet and
are left out of that window's loss. Keeping one grid per episode instead of a second copy of
every step makes the relabelled copy nearly free in memory.
"""

from __future__ import annotations

import math
from typing import Any

import flashbax as fbx
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from agents.config import DQNConfig
from agents.networks import ObsLayout, ObservationEncoder, ScannedRNN, mlp_head
from snac_jax.config import EnvConfig
from snac_jax.policy import Policy
from snac_jax.transition import drop_reward

# --- network ---------------------------------------------------------------------------------------


class QNetwork(nn.Module):
    """Q-values from a stack of observations, with an optional LSTM core and a dueling head.

    Time-major like every network of `agents.networks`: `carry (B, C)`, `frames (T, B, k, O)` (the
    last k observations, oldest first, zeros before the episode start), `resets (T, B)`.
    """

    layout: ObsLayout
    num_actions: int
    hidden_size: int = 128
    lstm_size: int = 0  # 0: feed-forward
    dueling: bool = True

    @property
    def carry_size(self) -> int:
        return 2 * self.lstm_size if self.lstm_size else 1

    def initial_carry(self, batch: int) -> jax.Array:
        return jnp.zeros((batch, self.carry_size), jnp.float32)

    @nn.compact
    def __call__(self, carry: jax.Array, frames: jax.Array, resets: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = ObservationEncoder(self.layout, self.hidden_size)(frames)  # (T, B, k, H)
        if frames.shape[-2] > 1:
            x = nn.relu(nn.Dense(self.hidden_size)(x.reshape(x.shape[:-2] + (-1,))))
        else:
            x = x[..., 0, :]
        if self.lstm_size:
            carry, x = ScannedRNN(self.lstm_size, "lstm")(carry, (x, resets))
        if self.dueling:
            value = mlp_head(x, self.hidden_size, 1, 1.0)
            advantage = mlp_head(x, self.hidden_size, self.num_actions, 1.0)
            return carry, value + advantage - advantage.mean(axis=-1, keepdims=True)
        return carry, mlp_head(x, self.hidden_size, self.num_actions, 1.0)


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
    # Hindsight only (None otherwise):
    world: jax.Array | None = None  # int32, the world (buffer row) the step came from
    episode: jax.Array | None = None  # int32, that world's episode counter
    drop_cell: jax.Array | None = None  # int32, flat plan cell a rewarded brick landed on, -1 if none
    drop_height: jax.Array | None = None  # int16, the height that brick brought its cell to
    stride: jax.Array | None = None  # int8, the stride drawn (lets a relabelled episode be replayed)


@struct.dataclass
class FinalGrids:
    """Per world, the final plan-area grids of its last `M` episodes (a ring indexed by episode
    counter modulo M); `episode` says which episode a slot holds (-1: none yet)."""

    grids: jax.Array  # int16 (B, M, *plan_shape)
    episode: jax.Array  # int32 (B, M)


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
    final_grids: FinalGrids | None  # hindsight only


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


# --- pure pieces the tests check one by one --------------------------------------------------------


def plan_area(config: EnvConfig, grid: jax.Array) -> jax.Array:
    """The design-area part of a padded grid."""
    (pr, pc), (h, w) = config.pad, config.plan_shape
    return jax.lax.dynamic_slice(grid, (pr, pc), (h, w))


def drop_record(config: EnvConfig, grid_before: jax.Array, grid_after: jax.Array, terminated: jax.Array):
    """`(flat plan cell, height)` of the brick this step was rewarded for, cell -1 if none.

    Read from the grid change rather than re-deriving the action rule: a rewarded drop is one
    that changed a cell and did not end the episode (the ending drop scores 0, SPEC §5). In 2D a
    brick on a filled cell changes nothing and scores 0 against any binary design, as it would
    in the relabelled episode, so it needs no record either.
    """
    changed = (plan_area(config, grid_after) != plan_area(config, grid_before)).reshape(-1)
    cell = jnp.argmax(changed)
    height = plan_area(config, grid_after).reshape(-1)[cell]
    rewarded = changed.any() & ~terminated
    return jnp.where(rewarded, cell, -1).astype(jnp.int32), height.astype(jnp.int16)


def hindsight_rewards(config: EnvConfig, drop_cell: jax.Array, drop_height: jax.Array, design: jax.Array) -> jax.Array:
    """Rewards of recorded drops against another design (`design (..., *plan_shape)` with the
    leading shape of `drop_cell`), through the environment's one reward function."""
    flat = design.reshape(drop_cell.shape + (-1,)).astype(jnp.int32)
    wanted = jnp.take_along_axis(flat, jnp.maximum(drop_cell, 0)[..., None], axis=-1)[..., 0]
    reward = drop_reward(config, drop_height.astype(jnp.int32), wanted)
    return jnp.where(drop_cell >= 0, reward, 0.0).astype(jnp.float32)


def n_step_targets(rewards: jax.Array, dones: jax.Array, values: jax.Array, gamma: float, n: int, length: int) -> jax.Array:
    """n-step return targets for the first `length` steps of time-major `(length + n, ...)` arrays.

    `values[t]` is the bootstrap value of the observation at t; `dones[t]` means the episode ended
    at step t, so neither later rewards nor a bootstrap value count past it.
    """
    target = jnp.zeros_like(rewards[:length])
    alive = jnp.ones_like(rewards[:length])
    for i in range(n):
        target = target + (gamma**i) * alive * rewards[i : i + length]
        alive = alive * (1.0 - dones[i : i + length].astype(rewards.dtype))
    return target + (gamma**n) * alive * values[n : n + length]


def stack_frames(obs: jax.Array, resets: jax.Array, k: int) -> jax.Array:
    """`(T, B, O)` observations -> `(T - k + 1, B, k, O)` stacks of the last k, oldest first;
    a frame from before the episode of the newest one (a reset in between) is zeros, as when acting."""
    t = obs.shape[0] - k + 1
    frames = []
    for j in range(k):
        frame = obs[j : j + t]
        # Frame j of output i is obs[i + j]; it belongs to the newest frame's episode unless a
        # reset lies in (i + j, i + k - 1].
        later_reset = jnp.zeros_like(resets[:t])
        for m in range(j + 1, k):
            later_reset = later_reset | resets[m : m + t]
        frames.append(jnp.where(later_reset[..., None], 0.0, frame))
    return jnp.stack(frames, axis=2)


def _frames(history: jax.Array | None, obs: jax.Array) -> jax.Array:
    """`(..., k, O)`: the stored earlier frames (if any) followed by `obs (..., O)`."""
    obs = obs[..., None, :].astype(jnp.float32)
    return obs if history is None else jnp.concatenate([history, obs], axis=-2)


def _select(mask: jax.Array, on_true: Any, on_false: Any) -> Any:
    """Per-world choice between two pytrees with a leading world axis."""
    return jax.tree.map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - mask.ndim)), a, b), on_true, on_false
    )


# --- the algorithm -----------------------------------------------------------------------------------


class DQN:
    """Static pieces of a DQN / DRQN / DRQN+HER run; see the module docstring."""

    def __init__(self, config: DQNConfig):
        config.validate()
        self.config = config
        self.env, self.env_params = config.make_env()
        self.layout = ObsLayout.from_env(self.env, self.env_params, previous_step=config.previous_step)
        self.network = QNetwork(
            layout=self.layout,
            num_actions=self.env.num_actions,
            hidden_size=config.hidden_size,
            lstm_size=config.lstm_size if config.uses_lstm else 0,
            dueling=config.dueling,
        )
        self.burn_in = config.burn_in if config.uses_lstm else 0
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
        # An episode lasts at least min(brick budget, step limit) steps (3D can end sooner when
        # stuck; a ring slot overwritten too early only drops that episode's relabelled copy).
        shortest = max(1, min(int(np.min(np.asarray(self.env_params.design_max_bricks))),
                              int(self.env_params.max_steps_in_episode)))
        self.ring_size = self.per_world // shortest + 2 if config.hindsight else 0
        high = self.env.observation_space(self.env_params).high
        if np.max(high) >= np.iinfo(np.int16).max:
            raise ValueError(f"observations reach {np.max(high)}, beyond the int16 the replay stores them in")
        self.memory_bytes = self._memory_bytes()
        limit = config.max_buffer_mb * 2**20
        if sum(self.memory_bytes.values()) > limit:
            raise ValueError(
                f"replay memory {sum(self.memory_bytes.values()) / 2**20:.1f} MiB per seed exceeds max_buffer_mb "
                f"({config.max_buffer_mb}); lower buffer_size or raise max_buffer_mb"
            )

    def _example_step(self) -> Step:
        obs_size = self.layout.env_obs_size
        step = Step(
            obs=jnp.zeros((obs_size,), jnp.int16),
            reset=jnp.zeros((), bool),
            action=jnp.zeros((), jnp.int8),
            reward=jnp.zeros((), jnp.float32),
            done=jnp.zeros((), bool),
        )
        if self.config.hindsight:
            step = step.replace(
                world=jnp.zeros((), jnp.int32),
                episode=jnp.zeros((), jnp.int32),
                drop_cell=jnp.zeros((), jnp.int32),
                drop_height=jnp.zeros((), jnp.int16),
                stride=jnp.zeros((), jnp.int8),
            )
        return step

    def _memory_bytes(self) -> dict[str, int]:
        """Bytes per seed of the replay buffer and of the hindsight ring of final grids."""
        buffer = jax.eval_shape(self.buffer.init, self._example_step())
        sizes = {"buffer": sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(buffer))}
        if self.config.hindsight:
            plan = math.prod(self.env.config.plan_shape)
            sizes["final_grids"] = self.config.num_envs * self.ring_size * (plan * 2 + 4)
        return sizes

    def describe_memory(self) -> str:
        parts = ", ".join(f"{name} {size / 2**20:.1f} MiB" for name, size in self.memory_bytes.items())
        return (f"replay on device: {self.per_world} steps x {self.config.num_envs} worlds per seed; {parts} "
                f"(limit {self.config.max_buffer_mb:g} MiB)")

    # --- pure functions ----------------------------------------------------------------------------

    def init(self, key: jax.Array) -> RunnerState:
        cfg, n = self.config, self.config.num_envs
        key, key_params, key_reset = jax.random.split(key, 3)
        obs, env_state = jax.vmap(self.env.reset, in_axes=(0, None))(jax.random.split(key_reset, n), self.env_params)
        history = jnp.zeros((n, cfg.frame_stack - 1, self.layout.obs_size), jnp.float32) if cfg.frame_stack > 1 else None
        carry = self.network.initial_carry(n)
        no_action, resets = jnp.zeros((n,), jnp.int32), jnp.ones((n,), bool)
        frames = _frames(history, self.layout.with_previous_step(obs, obs, no_action, resets))
        params = self.network.init(key_params, carry[:1], frames[None, :1], jnp.ones((1, 1), bool))
        final_grids = None
        if cfg.hindsight:
            final_grids = FinalGrids(
                grids=jnp.zeros((n, self.ring_size) + self.env.config.plan_shape, jnp.int16),
                episode=jnp.full((n, self.ring_size), -1, jnp.int32),
            )
        worlds = Worlds(
            env_state, obs, obs, no_action, history, resets, carry, jnp.zeros((n,), jnp.float32),
            jnp.zeros((n,), jnp.int32), final_grids,
        )
        zero = jnp.zeros((), jnp.int32)
        return RunnerState(
            params, params, self.optimizer.init(params), worlds, self.buffer.init(self._example_step()),
            key, zero, zero, zero,
        )

    def _env_step(self, params, worlds: Worlds, key: jax.Array, env_steps: jax.Array, env_params):
        """One epsilon-greedy step in every world, with the auto-reset done here so that the
        episode's final grid is at hand for hindsight."""
        n, env, cfg = self.config.num_envs, self.env, self.config
        key_explore, key_random, key_step = jax.random.split(key, 3)
        net_obs = self.layout.with_previous_step(worlds.obs, worlds.previous_obs, worlds.last_action, worlds.reset)
        frames = _frames(worlds.history, net_obs)
        carry, q = self.network.apply(params, worlds.carry, frames[None], worlds.reset[None])
        explore = jax.random.uniform(key_explore, (n,)) < self.epsilon(env_steps)
        action = jnp.where(explore, jax.random.randint(key_random, (n,), 0, env.num_actions), jnp.argmax(q[0], -1))

        keys = jax.random.split(key_step, n)
        obs_stepped, stepped, reward, terminated, info = jax.vmap(env.step_env, in_axes=(0, 0, 0, None))(
            keys, worlds.env_state, action, env_params
        )
        done = terminated | jax.vmap(env.is_truncated, in_axes=(0, None))(stepped, env_params)
        obs_reset, state_reset = jax.vmap(env.reset_env, in_axes=(0, None))(keys, env_params)
        env_state = _select(done, state_reset, stepped)
        obs = jnp.where(done[:, None], obs_reset, obs_stepped)

        step = Step(worlds.obs.astype(jnp.int16), worlds.reset, action.astype(jnp.int8), reward, done)
        final_grids = worlds.final_grids
        if cfg.hindsight:
            drop_cell, drop_height = jax.vmap(lambda b, a, t: drop_record(env.config, b, a, t))(
                worlds.env_state.grid, stepped.grid, terminated
            )
            step = step.replace(
                world=jnp.arange(n, dtype=jnp.int32), episode=worlds.episode, drop_cell=drop_cell,
                drop_height=drop_height, stride=info["stride"].astype(jnp.int8),
            )
            rows, slot = jnp.arange(n), worlds.episode % self.ring_size
            final = jax.vmap(lambda g: plan_area(env.config, g))(stepped.grid).astype(jnp.int16)
            final_grids = FinalGrids(
                grids=final_grids.grids.at[rows, slot].set(
                    jnp.where(done[:, None, None], final, final_grids.grids[rows, slot])),
                episode=final_grids.episode.at[rows, slot].set(
                    jnp.where(done, worlds.episode, final_grids.episode[rows, slot])),
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
        worlds = Worlds(
            env_state, obs, worlds.obs, action.astype(jnp.int32), history, done, carry, jnp.where(done, 0.0, episode_return),
            worlds.episode + done.astype(jnp.int32), final_grids,
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
        """A training batch, time-major: `(steps (L, S), float observations, rewards, loss mask)`.

        With hindsight the first `hindsight_fraction` of the S windows are read as the relabelled
        copy: rewards against the episode's final grid (and, on dynamic tasks, that grid as the
        observed design), their steps masked out where the episode has not ended yet.
        """
        cfg = self.config
        batch = self.buffer.sample(state.buffer, key).experience
        batch = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), batch)
        obs = batch.obs.astype(jnp.float32)
        rewards = batch.reward
        mask = jnp.ones_like(rewards)
        if cfg.hindsight:
            ring = state.worlds.final_grids
            slot = batch.episode % self.ring_size
            grids = ring.grids[batch.world, slot]  # (L, S, *plan_shape)
            ended = ring.episode[batch.world, slot] == batch.episode
            relabelled = (jnp.arange(rewards.shape[1]) < round(cfg.hindsight_fraction * cfg.batch_size))[None, :]
            use = relabelled & ended
            rewards = jnp.where(use, hindsight_rewards(self.env.config, batch.drop_cell, batch.drop_height, grids), rewards)
            mask = jnp.where(relabelled, ended, True).astype(rewards.dtype)
            if self.layout.dynamic:
                start = self.layout.window_size + 2
                design = jnp.where(use[..., None], grids.reshape(grids.shape[:2] + (-1,)), obs[..., start : start + self.layout.design_size])
                obs = obs.at[..., start : start + self.layout.design_size].set(design)
        return batch, obs, rewards, mask

    def network_inputs(self, obs: jax.Array, actions: jax.Array, resets: jax.Array) -> jax.Array:
        """What the network reads along a replayed window `(L, S, O)`: each observation with the
        previous step (window and action) taken from the row before it. The first row has none
        and reads as an episode start; `loss` drops it (`DQNConfig.context` counts it)."""
        previous_obs = jnp.concatenate([obs[:1], obs[:-1]], axis=0)
        last_action = jnp.concatenate([actions[:1], actions[:-1]], axis=0).astype(jnp.int32)
        first = jnp.zeros_like(resets).at[0].set(True)
        return self.layout.with_previous_step(obs, previous_obs, last_action, resets | first)

    def sequence_q(self, params, frames: jax.Array, resets: jax.Array) -> jax.Array:
        """Q-values `(T - burn_in, S, A)` of a sampled window from a zero LSTM state; the burn-in
        only warms the state (its carry is cut from the gradient)."""
        carry = self.network.initial_carry(frames.shape[1])
        if self.burn_in:
            carry, _ = self.network.apply(params, carry, frames[: self.burn_in], resets[: self.burn_in])
            carry = jax.lax.stop_gradient(carry)
        _, q = self.network.apply(params, carry, frames[self.burn_in :], resets[self.burn_in :])
        return q

    def loss(self, params, target_params, batch: Step, obs, rewards, mask):
        cfg = self.config
        k, length, c = cfg.frame_stack, cfg.sequence_length, cfg.context
        p = int(cfg.previous_step)  # the first row only lends its window and action to the second
        inputs = self.network_inputs(obs, batch.action, batch.reset)[p:]
        frames = stack_frames(inputs, batch.reset[p:], k)
        resets = batch.reset[p + k - 1 :]
        q = self.sequence_q(params, frames, resets)  # (length + n, S, A), index 0 = batch index c
        q_target = jax.lax.stop_gradient(self.sequence_q(target_params, frames, resets))
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
        return loss, {"loss": loss, "q_mean": (q_taken * weights).sum() / jnp.maximum(weights.sum(), 1.0)}

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

        def wait(state):
            return state, {"loss": jnp.zeros(()), "q_mean": jnp.zeros(())}

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
            frames = _frames(policy_state["history"], layout.acting_inputs(obs, policy_state))
            carry, q = network.apply(params, policy_state["carry"][None], frames[None, None], policy_state["reset"][None, None])
            history = frames[1:] if k > 1 else None
            action = jnp.argmax(q[0, 0]).astype(jnp.int32)
            return action, {"carry": carry[0], "history": history, **layout.remember(obs, action)}

        return Policy(init, act, params, self.config.algorithm)


def make_train(config: DQNConfig):
    """The whole run as a pure function of a key: `jax.jit(jax.vmap(make_train(c)))(keys)`."""
    agent = DQN(config)

    def train(key: jax.Array) -> tuple[RunnerState, dict[str, jax.Array]]:
        return agent.train_chunk(agent.init(key), agent.env_params, agent.config.num_updates)

    return train
