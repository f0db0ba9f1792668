"""What a network reads: the environment's observation laid out as the library says
(`snac_jax.observation.ObservationLayout`), optionally followed by the previous step, each part
scaled to about [-1, 1] and cell heights also read as classes.

Observation scaling lives on the learners' side, not in the environment: raw counters reach 1300
and heights 57, and the environment's observation stays the original's.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.env import SNACEnv
from snac_jax.observation import LANDMARK_VALUE, ObservationLayout
from snac_jax.state import EnvParams
from snac_jax.transition import PADDING

_LOWEST_CELL = int(min(LANDMARK_VALUE, PADDING))  # the lowest value a window cell holds


def episode_min_steps(env: SNACEnv, params: EnvParams, robots: int = 1, stuck: bool = True) -> int:
    """A lower bound on the steps of any episode of `env` under `params` (SPEC §4-§5), for one
    robot or a team of `robots` sharing one world (SPEC §13): the step limit; the brick budget,
    since each robot lays at most one counted brick a step; and with the obstacle rule 3, since a
    robot starting in a corner is walled in after two drops and its next action ends the episode
    (a team's other robots start too far away to wall it in sooner). `stuck=False` leaves that
    last term out, for a caller that sizes for the usual episode and tolerates a rare short one."""
    budget = int(np.min(np.asarray(params.design_max_bricks)))
    bound = min(int(params.max_steps_in_episode), -(-budget // robots))
    if stuck and env.config.obstacles:
        bound = min(bound, 3)
    return max(bound, 1)


@dataclasses.dataclass(frozen=True)
class ObsLayout:
    """What a network reads: the environment's observation, laid out as `env` (the library's
    `snac_jax.observation.ObservationLayout`) says, optionally followed by the previous step
    (`with_previous_step`), and how to scale each part to about [-1, 1]."""

    env: ObservationLayout
    height_scale: float  # the tallest design cell (1 in 2D)
    brick_scale: float  # the largest brick budget
    step_scale: float  # the step limit
    # > 0: the learner appends the previous step to the environment's observation: the window
    # before the last action, and that action one-hot in `num_actions + 1` entries.
    num_actions: int = 0
    # The fewest steps an episode lasts, and how many designs one episode shows (2 with a design
    # change, SPEC §15): together they bound how often a dynamic task's design can change along
    # a sequence (`max_design_runs`). 1 and 1 claim nothing, and the design is read at every step.
    episode_min_steps: int = 1
    designs_per_episode: int = 1

    @classmethod
    def from_env(cls, env: SNACEnv, params: EnvParams, previous_step: bool = False, robots: int = 1) -> ObsLayout:
        return cls(
            env=env.observation_layout,
            height_scale=float(max(1, int(np.max(np.asarray(params.designs))))),
            brick_scale=float(max(1, int(np.max(np.asarray(params.design_max_bricks))))),
            step_scale=float(int(params.max_steps_in_episode)),
            num_actions=env.num_actions if previous_step else 0,
            episode_min_steps=episode_min_steps(env, params, robots),
            designs_per_episode=2 if env.config.design_change else 1,
        )

    def max_truncations(self, steps: int) -> int:
        """The most step-limit truncations one world's `steps` consecutive steps hold: the limit,
        `step_scale`, ends an episode at most once every `step_scale` steps."""
        return -(-steps // int(self.step_scale))

    def max_design_runs(self, steps: int) -> int:
        """The most runs of one design a world's observations hold along `steps` consecutive
        steps: episodes last at least `episode_min_steps`, so at most `1 + ceil((steps - 1) /
        episode_min_steps)` of them meet `steps` steps, each showing `designs_per_episode`."""
        episodes = 1 + -(-(steps - 1) // self.episode_min_steps)
        return min(steps, episodes * self.designs_per_episode)

    @property
    def window_shape(self) -> tuple[int, int]:
        return self.env.window_shape

    @property
    def plan_shape(self) -> tuple[int, int]:
        return self.env.plan_shape

    @property
    def dynamic(self) -> bool:
        return self.env.design is not None

    @property
    def window_size(self) -> int:
        return self.env.window_size

    @property
    def design_size(self) -> int:
        return self.env.design_size

    @property
    def env_obs_size(self) -> int:
        return self.env.size

    @property
    def previous_step_size(self) -> int:
        return self.window_size + self.num_actions + 1 if self.num_actions else 0

    @property
    def obs_size(self) -> int:
        """What the network reads: the environment's observation (+ the previous step)."""
        return self.env_obs_size + self.previous_step_size

    def with_previous_step(
        self, obs: jax.Array, previous_obs: jax.Array, last_action: jax.Array, reset: jax.Array
    ) -> jax.Array:
        """Append to `obs (..., env_obs_size)` the window of `previous_obs` and the one-hot of
        `last_action`; where `reset` (an episode's first observation) there is no previous step:
        the window repeats the current one and the action is "none" (index `num_actions`).

        Why: the robot localises by how its window shifted after a move (SPEC §11). A recurrent
        policy that samples its actions cannot tell from its own state which one was drawn, and
        comparing two windows is far easier side by side than through a recurrent state; each of
        the two inputs raised recurrent PPO's score (bench/results/ppo.md).
        """
        if not self.num_actions:
            return obs
        w = self.window_size
        previous_window = jnp.where(reset[..., None], obs[..., :w], previous_obs[..., :w])
        last_action = jnp.where(reset, self.num_actions, last_action)
        action = jax.nn.one_hot(last_action, self.num_actions + 1, dtype=obs.dtype)
        return jnp.concatenate([obs, previous_window.astype(obs.dtype), action], axis=-1)

    def episode_start_memory(self) -> dict[str, jax.Array]:
        """What a `Policy` keeps between steps to build its inputs, at an episode's start (the
        `reset` flag also zeroes a recurrent carry)."""
        return {
            "reset": jnp.ones((), bool),
            "previous_obs": jnp.zeros((self.env_obs_size,), jnp.float32),
            "last_action": jnp.zeros((), jnp.int32),
        }

    def acting_inputs(self, obs: jax.Array, memory: dict[str, jax.Array]) -> jax.Array:
        """The network's input for one observation, given the memory of the steps before it."""
        return self.with_previous_step(obs, memory["previous_obs"], memory["last_action"], memory["reset"])

    def remember(self, obs: jax.Array, action: jax.Array) -> dict[str, jax.Array]:
        """The memory after acting `action` on `obs`: what the next step reads as its previous one."""
        return {
            "reset": jnp.zeros((), bool),
            "previous_obs": obs.astype(jnp.float32),
            "last_action": action.astype(jnp.int32),
        }

    @property
    def num_height_classes(self) -> int:
        """One class per value from the lowest a window cell holds (a landmark, `LANDMARK_VALUE`;
        padding, `PADDING`) through heights 0..tallest, and one for anything taller."""
        return int(self.height_scale) - _LOWEST_CELL + 2

    def height_classes(self, cells: jax.Array) -> jax.Array:
        """One-hot `(..., n, num_height_classes)` of raw cell values.

        Why: the policy must stop dropping exactly when a column reaches its design height
        (+10 at equality, -1 above). A scaled height puts 19 and 20 bricks 0.03 apart; a one-hot
        makes "is it exactly 20?" one weight, and a trained PPO policy without it missed its
        columns by ~4 bricks even at the start cell, whose position it knows.
        """
        index = jnp.clip(cells.astype(jnp.int32) - _LOWEST_CELL, 0, self.num_height_classes - 1)
        return jax.nn.one_hot(index, self.num_height_classes, dtype=jnp.float32)

    def split(self, obs: jax.Array) -> dict[str, jax.Array]:
        """Scaled parts of `obs (..., obs_size)`: window (..., wr, wc), its cells one-hot
        (..., wr * wc, classes), counters (..., 2),
        with the switches design (..., *plan_shape) and position (..., 1 or 2), and with
        `num_actions` the previous window (scaled and one-hot) and the last action."""
        lead, layout = obs.shape[:-1], self.env
        window = obs[..., layout.window]
        parts = {
            "window": window.reshape(lead + self.window_shape) / self.height_scale,
            "window_classes": self.height_classes(window),
            "counters": obs[..., layout.counters] / jnp.array([self.brick_scale, self.step_scale]),
        }
        if layout.design is not None:
            parts["design"] = layout.design_cells(obs[..., : layout.size]) / self.height_scale
        if layout.position is not None:
            parts["position"] = obs[..., layout.position] / max(self.plan_shape)
        w = self.window_size
        if self.num_actions:
            previous_window = obs[..., self.env_obs_size : self.env_obs_size + w]
            parts["previous_window"] = previous_window.reshape(lead + self.window_shape) / self.height_scale
            parts["previous_window_classes"] = self.height_classes(previous_window)
            parts["last_action"] = obs[..., self.env_obs_size + w :]
        return parts
