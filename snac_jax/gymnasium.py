"""The SNAC tasks as Gymnasium environments: one world (`SNACGymEnv`) or a batch of worlds stepped
in one jitted call (`SNACVectorEnv`).

Importing this module registers every task of `snac_jax.TASKS` as `SNAC/<task id>-v0`::

    import gymnasium as gym
    import snac_jax.gymnasium  # noqa: F401  (registers the ids)

    env = gym.make("SNAC/2d-static-dense-v0", gps=True)            # one world, NumPy in and out
    envs = gym.make_vec("SNAC/2d-static-dense-v0", num_envs=1024)  # SNACVectorEnv

Keyword arguments of `make`/`make_vec` other than `render_mode` (and `num_envs`) are
`snac_jax.make` overrides (`snac_jax.OVERRIDES`). An id builds its own task: a `task_id` naming
another one is refused.

- `SNACGymEnv` does not reset by itself: after `terminated or truncated` call `reset()`, as
  Gymnasium expects (Stable-Baselines3's `DummyVecEnv` does); a step before it raises
  `gymnasium.error.ResetNeeded`.
- `SNACVectorEnv` resets a world on the step its episode ends (`AutoresetMode.SAME_STEP`, as
  `snac_jax`'s jitted `step` does): that step returns the new episode's first observation, and
  `info["final_obs"]` (with the mask `info["_final_obs"]`) and `info["final_info"]` hold the
  ended episode's last observation and step info.

Both hand back NumPy arrays, draw their randomness from a JAX key seeded by `reset(seed=...)`,
and render RGB frames with `render_mode="rgb_array"`. The spaces are the gymnax env's per-entry
bounds (`SNACEnv.observation_space`) as `gymnasium.spaces`. Step info: `iou`, the IoU of the
construction after the step (on an episode's last step, its final IoU), and `stride`, the stride
the step drew.

This module needs Gymnasium (`pip install snac-jax[gymnasium]`); `import snac_jax` does not
import it.
"""

from __future__ import annotations

from functools import partial
from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces as gym_spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from snac_jax import threefry
from snac_jax.batched_step import resolve_reset
from snac_jax.env import SNACEnv
from snac_jax.state import EnvParams, EnvState
from snac_jax.tasks import TASKS, make

NAMESPACE = "SNAC"
VERSION = 0
RENDER_FPS = 10


def env_id(task_id: str) -> str:
    """The Gymnasium id of a task: `SNAC/<task id>-v0`."""
    return f"{NAMESPACE}/{task_id}-v{VERSION}"


def observation_space(env: SNACEnv, params: EnvParams) -> gym_spaces.Box:
    """The gymnax env's per-entry observation bounds as a `gymnasium.spaces.Box` (float32)."""
    space = env.observation_space(params)
    low = np.asarray(space.low, np.float32)
    high = np.asarray(space.high, np.float32)
    return gym_spaces.Box(low=low, high=high, shape=space.shape, dtype=np.float32)


def action_space(env: SNACEnv, params: EnvParams) -> gym_spaces.Discrete:
    return gym_spaces.Discrete(env.action_space(params).n)


def _key_from(rng: np.random.Generator) -> jax.Array:
    """A JAX Threefry key of two words drawn from the Gymnasium generator (`reset(seed=s)` seeds it
    from any non-negative int, through NumPy's `SeedSequence`)."""
    return jax.random.wrap_key_data(rng.integers(0, 2**32, size=2, dtype=np.uint32), impl="threefry2x32")


def _check_registered_task(task_id: str, registered_task_id: str | None) -> None:
    """`ValueError` unless `task_id` is the task of the Gymnasium id the env is made under.

    Why: `make(id, **kwargs)` lays the caller's keywords over the id's registered `task_id`, so
    without this check `make("SNAC/1d-static-sin-v0", task_id="2d-static-dense")` would build a
    2D world that every wrapper, log and `env.spec` names as the 1D task."""
    if registered_task_id is not None and task_id != registered_task_id:
        raise ValueError(
            f"{env_id(registered_task_id)} is the task {registered_task_id}, not task_id={task_id!r}: "
            f"make {env_id(task_id)!r} instead"
        )


def _check_render_mode(metadata: dict[str, Any], render_mode: str | None) -> str | None:
    if render_mode is not None and render_mode not in metadata["render_modes"]:
        raise ValueError(f"render_mode must be None or one of {metadata['render_modes']}, got {render_mode!r}")
    return render_mode


# --- jitted kernels (static on the env: equal configurations share compiled code) -------------------


@partial(jax.jit, static_argnums=0)
def _reset_one(env: SNACEnv, key: jax.Array, params: EnvParams, design_index: jax.Array | None):
    key, reset_key = threefry.split(key, 2)
    if design_index is None:
        obs, state = env.reset(reset_key, params)
    else:
        obs, state = env.reset_to_design(reset_key, params, design_index)
    return key, obs, state


def _pack(obs, reward, terminated, truncated, iou, stride) -> jax.Array:
    """Observation and step results as one float32 array (one transfer to the host): the last
    axis is [obs..., reward, terminated, truncated, iou, stride], all exact in float32."""
    extras = jnp.stack([reward, terminated, truncated, iou, stride], axis=-1).astype(jnp.float32)
    return jnp.concatenate([obs, extras], axis=-1)


def _unpack(packed: np.ndarray, size: int):
    obs = np.array(packed[..., :size])
    reward, terminated, truncated, iou, stride = (packed[..., size + i] for i in range(5))
    return obs, reward, terminated != 0, truncated != 0, iou, stride.astype(np.int32)


@partial(jax.jit, static_argnums=0)
def _step_one(env: SNACEnv, key: jax.Array, state: EnvState, action: jax.Array, params: EnvParams):
    key, step_key = threefry.split(key, 2)
    obs, state, reward, terminated, info = env.step_env(step_key, state, action, params)
    truncated = env.is_truncated(state, params)
    return key, state, _pack(obs, reward, terminated, truncated, info["final_iou"], info["stride"])


@partial(jax.jit, static_argnums=(0, 1))
def _reset_batch(env: SNACEnv, num_envs: int, key: jax.Array, params: EnvParams):
    key, reset_key = threefry.split(key, 2)
    obs, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(reset_key, num_envs), params)
    return key, obs, states


@partial(jax.jit, static_argnums=(0, 5), donate_argnums=2)
def _step_batch(env: SNACEnv, key: jax.Array, states: EnvState, actions: jax.Array, params: EnvParams, reset: str):
    key, step_key = threefry.split(key, 2)
    keys = threefry.split(step_key, actions.shape[0])
    obs, states, reward, terminated, truncated, info = env.step_batch(keys, states, actions, params, reset=reset)
    packed = _pack(obs, reward, terminated, truncated, info["final_iou"], info["stride"])
    return key, states, packed, info["final_observation"]


# --- one world -------------------------------------------------------------------------------------


class SNACGymEnv(gymnasium.Env):
    """One SNAC world as a `gymnasium.Env`: `SNACGymEnv("1d-static-sin", max_steps=100)`.

    `reset(seed=s)` starts a reproducible key chain (later unseeded resets and steps continue
    it); `reset(options={"design_index": i})` starts on `params.designs[i]` (a dynamic task's
    bank, or its pinned test design). The episode ends with `terminated` (out of bricks, or
    stuck in 3D) or `truncated` (the step limit); the env then waits for `reset()`: a step before
    it raises `gymnasium.error.ResetNeeded` and leaves the ended episode as it was.

    `registered_task_id` is the task of the Gymnasium id the env is made under (the registration
    passes it); a `task_id` of another task is refused.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": RENDER_FPS}

    def __init__(
        self, task_id: str, render_mode: str | None = None, registered_task_id: str | None = None, **overrides: Any
    ):
        _check_registered_task(task_id, registered_task_id)
        self.render_mode = _check_render_mode(self.metadata, render_mode)
        self.jax_env, self.env_params = make(task_id, **overrides)
        self.task_id = task_id
        self.observation_space = observation_space(self.jax_env, self.env_params)
        self.action_space = action_space(self.jax_env, self.env_params)
        self._key: jax.Array | None = None
        self._state: EnvState | None = None
        self._ended: str | None = None  # "terminated" or "truncated" once the episode has ended

    @property
    def state(self) -> EnvState | None:
        """The current `EnvState` (JAX arrays), None before the first reset."""
        return self._state

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        options = dict(options or {})
        design_index = options.pop("design_index", None)
        if options:
            raise ValueError(f"unknown reset option(s) {sorted(options)}; the one option is 'design_index'")
        if design_index is not None:
            count = self.env_params.designs.shape[0]
            if not isinstance(design_index, (int, np.integer)) or not 0 <= design_index < count:
                raise ValueError(f"design_index must be an int in 0..{count - 1}, got {design_index!r}")
            design_index = np.int32(design_index)
        if seed is not None or self._key is None:
            self._key = _key_from(self.np_random)
        self._key, obs, self._state = _reset_one(self.jax_env, self._key, self.env_params, design_index)
        self._ended = None
        return np.array(obs), {}

    def step(self, action) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        if self._ended is not None:
            # The step itself would go on past the end (time, bricks and IoU growing): the end is
            # where the episode's numbers belong.
            raise gymnasium.error.ResetNeeded(f"the episode ended ({self._ended}): call reset() before step()")
        if isinstance(action, (bool, np.bool_)) or not self.action_space.contains(action):  # True is no action
            raise ValueError(f"action must be an int in 0..{self.action_space.n - 1}, got {action!r}")
        self._key, self._state, packed = _step_one(
            self.jax_env, self._key, self._state, np.int32(action), self.env_params
        )
        obs, reward, terminated, truncated, iou, stride = _unpack(np.asarray(packed), self.observation_space.shape[0])
        if terminated or truncated:
            self._ended = "terminated" if terminated else "truncated"
        info = {"iou": float(iou), "stride": int(stride)}
        return obs, float(reward), bool(terminated), bool(truncated), info

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() was called without a render_mode; make the env with render_mode='rgb_array'"
            )
            return None
        if self._state is None:
            raise gymnasium.error.ResetNeeded("call reset() before render()")
        return self.jax_env.render(self._state, self.env_params)


# --- a batch of worlds -----------------------------------------------------------------------------


class SNACVectorEnv(VectorEnv):
    """`num_envs` SNAC worlds stepped by one jitted `SNACEnv.step_batch` call per `step`.

    Autoreset is `AutoresetMode.SAME_STEP`: a world whose episode ends this step is reset within
    the same call; its row of the returned observations is the new episode's first observation,
    `info["final_obs"][i]` the ended episode's last one (the mask `info["_final_obs"]` marks
    those worlds) and `info["final_info"]` that step's info. Top-level `iou` and `stride` belong
    to the worlds that go on (masks `_iou`, `_stride`). `reset` is the auto-reset strategy of
    `SNACEnv.step_batch` (`"auto"`: one by one on a CPU, a select on a GPU; the same worlds
    either way).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": RENDER_FPS, "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        task_id: str,
        num_envs: int = 1,
        render_mode: str | None = None,
        registered_task_id: str | None = None,
        reset: str = "auto",
        **overrides: Any,
    ):
        _check_registered_task(task_id, registered_task_id)
        self.reset_strategy = resolve_reset(reset)  # how ended worlds are reset: the backend's own by default
        if not isinstance(num_envs, (int, np.integer)) or isinstance(num_envs, bool) or num_envs < 1:
            raise ValueError(f"num_envs must be an int >= 1, got {num_envs!r}")
        self.render_mode = _check_render_mode(self.metadata, render_mode)
        self.jax_env, self.env_params = make(task_id, **overrides)
        self.task_id = task_id
        self.num_envs = int(num_envs)
        self.single_observation_space = observation_space(self.jax_env, self.env_params)
        self.single_action_space = action_space(self.jax_env, self.env_params)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._key: jax.Array | None = None
        self._states: EnvState | None = None

    @property
    def states(self) -> EnvState | None:
        """The batched `EnvState` (JAX arrays with a leading `num_envs` axis), None before reset.

        `step` donates these buffers to the jitted step: copy what must outlive the next step."""
        return self._states

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Reset every world. `seed` is one int (the worlds get independent keys from it)."""
        if seed is not None and (not isinstance(seed, (int, np.integer)) or isinstance(seed, bool)):
            raise TypeError(f"seed must be an int or None, got {seed!r}")
        if options:
            raise ValueError(f"SNACVectorEnv.reset takes no options, got {sorted(options)}")
        super().reset(seed=seed)
        if seed is not None or self._key is None:
            self._key = _key_from(self.np_random)
        self._key, obs, self._states = _reset_batch(self.jax_env, self.num_envs, self._key, self.env_params)
        return np.array(obs), {}

    def step(self, actions) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        if self._states is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        actions = np.asarray(actions)
        n = self.single_action_space.n
        if actions.shape != (self.num_envs,) or not np.issubdtype(actions.dtype, np.integer):
            raise ValueError(f"actions must be {self.num_envs} ints, got shape {actions.shape} of {actions.dtype}")
        if np.any((actions < 0) | (actions >= n)):
            raise ValueError(f"actions must lie in 0..{n - 1}, got {actions}")
        self._key, self._states, packed, final_obs = _step_batch(
            self.jax_env, self._key, self._states, actions.astype(np.int32), self.env_params, self.reset_strategy
        )
        size = self.single_observation_space.shape[0]
        obs, reward, terminated, truncated, iou, stride = _unpack(np.asarray(packed), size)
        done = terminated | truncated
        going_on = ~done
        info: dict[str, Any] = {
            "iou": np.where(going_on, iou, 0.0).astype(np.float32),
            "_iou": going_on,
            "stride": np.where(going_on, stride, 0).astype(np.int32),
            "_stride": going_on.copy(),
        }
        if done.any():
            ended = np.flatnonzero(done)
            final = np.asarray(final_obs)[ended]
            info["final_obs"] = np.full(self.num_envs, None, dtype=object)
            for row, world in zip(final, ended):
                info["final_obs"][world] = row
            info["_final_obs"] = done
            info["final_info"] = {
                "iou": np.where(done, iou, 0.0).astype(np.float32),
                "_iou": done.copy(),
                "stride": np.where(done, stride, 0).astype(np.int32),
                "_stride": done.copy(),
            }
            info["_final_info"] = done.copy()
        return obs, reward.astype(np.float32), terminated, truncated, info

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One RGB frame per world (every world is drawn on the host: slow for large batches)."""
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() was called without a render_mode; make the env with render_mode='rgb_array'"
            )
            return None
        if self._states is None:
            raise gymnasium.error.ResetNeeded("call reset() before render()")
        states = jax.device_get(self._states)
        return tuple(
            self.jax_env.render(jax.tree.map(lambda leaf, i=i: leaf[i], states), self.env_params)
            for i in range(self.num_envs)
        )


def register_all() -> None:
    """Register `SNAC/<task id>-v0` for every task (done on import; calling it again is harmless)."""
    for task_id in TASKS:
        if env_id(task_id) in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id(task_id),
            entry_point=f"{__name__}:SNACGymEnv",
            vector_entry_point=f"{__name__}:SNACVectorEnv",
            kwargs={"task_id": task_id, "registered_task_id": task_id},
        )


register_all()
