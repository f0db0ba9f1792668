"""`MultiSNACEnv`: several robots building one design in one world (SPEC §13), JaxMARL-shaped.

JaxMARL's `MultiAgentEnv` is the convention of multi-agent RL in JAX: `agents`, `reset(key) ->
(obs, state)`, `step(key, state, actions) -> (obs, state, rewards, dones, infos)` with dicts keyed
by agent and `dones["__all__"]`, auto-reset on `__all__` (or to a given `reset_state`). This
class follows it without importing JaxMARL (an optional extra), so JaxMARL's baselines run on it
unchanged: the spaces can be built inside `jit`, and an agent's action may have shape `()` or
`(1,)`. Their `LogWrapper` needs `replace_info=True`, since `infos` holds per-team values beside
per-robot ones. It adds an optional `params` argument, as gymnax does (`step` takes it by
keyword), so the designs, stride distribution and step limit can be swapped or vmapped without
recompiling. The world is the single-robot env's (`SNACEnv`), whose reset, checks and
transition it reuses; with one robot every output equals the single-robot env's.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from gymnax.environments import spaces

from snac_jax import metrics, tasks
from snac_jax.config import MAX_STRIDE
from snac_jax.env import SNACEnv, check_integer
from snac_jax.multi import rules
from snac_jax.state import EnvParams, EnvState


@struct.dataclass
class MultiState:
    """One world shared by every robot: the single-robot `EnvState` whose `position` is
    (num_robots, 2), each robot's plan cell in robot order."""

    world: EnvState

    @property
    def positions(self) -> jax.Array:
        return self.world.position


def agent_names(num_robots: int) -> list[str]:
    """`["agent_0", ...]`, JaxMARL's names; robot i is `agent_i` and acts i-th in a step."""
    return [f"agent_{i}" for i in range(num_robots)]


def check_num_robots(task_id: str, num_robots: Any) -> int:
    """`num_robots` if it is an int in 1..max_robots for the task's plan, else a one-line
    `ValueError` naming the allowed values (checked before anything is built or traced)."""
    dim = tasks.task_spec(task_id).dim
    high = rules.max_robots(dim)
    ok = isinstance(num_robots, (int, np.integer)) and not isinstance(num_robots, (bool, np.bool_))
    if not ok or not 1 <= num_robots <= high:
        where = "one per end of the row" if dim == 1 else "one per corner of the plan"
        raise ValueError(f"num_robots must be an int in 1..{high} for {task_id} ({where}), got {num_robots!r}")
    return int(num_robots)


def make(task_id: str, num_robots: int = 1, **switches: Any) -> MultiSNACEnv:
    """`env = snac_jax.multi.make("2d-static-dense", num_robots=2, gps=True)`: the task's world
    with `num_robots` robots. `switches` are `snac_jax.make`'s overrides (SPEC §9), checked there;
    the default params are `env.default_params`."""
    num_robots = check_num_robots(task_id, num_robots)
    for name in ("landmark_action", "design_change"):
        if name in switches:
            raise ValueError(f"{name} is a single-robot switch (SPEC §14-15); snac_jax.multi.make does not take it")
    single, params = tasks.make(task_id, **switches)
    return MultiSNACEnv(single, num_robots, params)


class MultiSNACEnv:
    """N robots in one SNAC world. Build it with `snac_jax.multi.make(task, num_robots=N)`.

    Equal configurations and robot counts hash equal, so the jitted `reset` and `step` (static on
    `self`) compile once per configuration, not once per instance.
    """

    def __init__(self, single: SNACEnv, num_robots: int, default_params: EnvParams | None = None):
        self.single = single
        self.config = single.config
        self.num_agents = num_robots
        self.agents = agent_names(num_robots)
        self._default_params = default_params if default_params is not None else single.default_params
        self._starts = rules.start_positions(self.config, num_robots)
        self.observation_spaces = {a: self.observation_space(a) for a in self.agents}
        self.action_spaces = {a: self.action_space(a) for a in self.agents}

    def __hash__(self) -> int:
        return hash((self.config, self.num_agents))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, MultiSNACEnv) and (other.config, other.num_agents) == (self.config, self.num_agents)

    def __repr__(self) -> str:
        return f"MultiSNACEnv({self.config.task_id!r}, num_robots={self.num_agents})"

    @property
    def name(self) -> str:
        return self.config.task_id

    @property
    def default_params(self) -> EnvParams:
        return self._default_params

    @property
    def num_actions(self) -> int:
        return self.config.num_actions

    @property
    def observation_layout(self):
        """Each robot's observation is laid out as the single-robot env's (SPEC §6)."""
        return self.single.observation_layout

    # --- dicts and arrays ----------------------------------------------------------------------

    def _stacked(self, name: str, values: Mapping[str, Any], low: int, high: int) -> jax.Array:
        """int32 (N,) from a dict keyed by agent; the keys and each value checked while tracing.
        A value may be one integer of shape `()` or `(1,)`: JaxMARL's baselines hand each agent
        its sampled action as `(1,)` (their envs reshape it), so both are taken as one action."""
        if not isinstance(values, Mapping) or set(values) != set(self.agents):
            got = sorted(values) if isinstance(values, Mapping) else type(values).__name__
            raise ValueError(f"{name} must be a dict keyed by {self.agents}, got {got}")
        one = {a: jnp.reshape(v, ()) if np.shape(v) == (1,) else v for a, v in values.items()}
        for agent in self.agents:
            check_integer(f"{name}[{agent!r}]", one[agent], low, high)
        return jnp.stack([jnp.asarray(one[a], jnp.int32) for a in self.agents])

    def _by_agent(self, stacked: jax.Array) -> dict[str, jax.Array]:
        return {agent: stacked[i] for i, agent in enumerate(self.agents)}

    # --- reset ---------------------------------------------------------------------------------

    def _place(self, world: EnvState) -> MultiState:
        return MultiState(world=world.replace(position=jnp.asarray(self._starts)))

    def reset(self, key: jax.Array, params: EnvParams | None = None) -> tuple[dict[str, jax.Array], MultiState]:
        """A fresh episode: the single-robot env's reset with the same key (the design, the
        landmarks), the robots at their starts (SPEC §13)."""
        return self._reset(key, self.default_params if params is None else params)

    # `reset` and `step` hand the default params to the jitted functions as arguments: the
    # compiled code is shared by every env of equal configuration (static `self`), so params
    # baked in as constants would be those of whichever env compiled first.
    @partial(jax.jit, static_argnames=("self",))
    def _reset(self, key: jax.Array, params: EnvParams) -> tuple[dict[str, jax.Array], MultiState]:
        state = self._reset_state(key, params)
        return self.get_obs(state), state

    def _reset_state(self, key: jax.Array, params: EnvParams) -> MultiState:
        return self._place(self.single.reset_env(key, params)[1])

    def reset_to_design(
        self, key: jax.Array, design_index: jax.Array, params: EnvParams | None = None
    ) -> tuple[dict[str, jax.Array], MultiState]:
        """A fresh episode on `params.designs[design_index]` (an evaluation pins test designs so)."""
        params = self.default_params if params is None else params
        state = self._place(self.single.reset_to_design(key, params, design_index)[1])
        return self.get_obs(state), state

    # --- step ----------------------------------------------------------------------------------

    def step_with_strides(
        self, state: MultiState, actions: Mapping[str, Any], strides: Mapping[str, Any], params: EnvParams | None = None
    ) -> tuple[dict[str, jax.Array], MultiState, dict[str, jax.Array], dict[str, jax.Array], dict[str, Any]]:
        """One step with the given strides, without auto-reset (replays and tests use it).
        Returns `step`'s five outputs for the state the step reached."""
        params = self.default_params if params is None else params
        self._check(state, params)
        acts = self._stacked("actions", actions, 0, self.num_actions - 1)
        return self._outputs(state, acts, self._stacked("strides", strides, 1, MAX_STRIDE), params)

    def step_env(
        self, key: jax.Array, state: MultiState, actions: Mapping[str, Any], params: EnvParams | None = None
    ) -> tuple[dict[str, jax.Array], MultiState, dict[str, jax.Array], dict[str, jax.Array], dict[str, Any]]:
        """One step, strides drawn from `key` (SPEC §13), without auto-reset."""
        params = self.default_params if params is None else params
        self._check(state, params)
        acts = self._stacked("actions", actions, 0, self.num_actions - 1)
        return self._outputs(state, acts, rules.draw_strides(key, params.stride_probs, self.num_agents), params)

    def _check(self, state: MultiState, params: EnvParams) -> None:
        self.single.check_params(params)
        self.single.check_state(state.world)
        if tuple(state.positions.shape) != (self.num_agents, 2):
            raise ValueError(
                f"state holds {tuple(state.positions.shape)} positions, {self!r} needs ({self.num_agents}, 2)"
            )

    def _outputs(self, state: MultiState, actions: jax.Array, strides: jax.Array, params: EnvParams):
        world, robot_rewards, terminated = rules.robot_turns(self.config, state.world, actions, strides)
        truncated = self.single.is_truncated(world, params)
        done = terminated | truncated
        infos = {
            "final_iou": metrics.iou(world),
            "strides": strides,
            "robot_rewards": robot_rewards,
            "terminated": terminated,
            "truncated": truncated,
        }
        stepped = MultiState(world=world)
        return self.get_obs(stepped), stepped, self._team_rewards(robot_rewards), self._dones(done), infos

    def _team_rewards(self, robot_rewards: jax.Array) -> dict[str, jax.Array]:
        """Every robot gets the team's reward: the sum of the robots' drop rewards (SPEC §13)."""
        team = robot_rewards[0] if self.num_agents == 1 else jnp.sum(robot_rewards)
        return {agent: team for agent in self.agents}

    def _dones(self, done: jax.Array) -> dict[str, jax.Array]:
        return {**{agent: done for agent in self.agents}, "__all__": done}

    def step(
        self,
        key: jax.Array,
        state: MultiState,
        actions: Mapping[str, Any],
        reset_state: MultiState | EnvParams | None = None,
        params: EnvParams | None = None,
    ) -> tuple[dict[str, jax.Array], MultiState, dict[str, jax.Array], dict[str, jax.Array], dict[str, Any]]:
        """JaxMARL's auto-resetting step: where `dones["__all__"]`, the returned observations and
        state belong to a fresh episode (reset with this step's key, as the single-robot env), or
        to `reset_state` when one is given, as in JaxMARL's `MultiAgentEnv.step(key, state,
        actions, reset_state=None)`.

        `params` by keyword, else the env's own. The fourth positional argument may also be an
        `EnvParams` (gymnax's `step(key, state, action, params)`): the two types are told apart
        while tracing, so both kinds of caller run unchanged.

        `infos`: `final_iou`, `strides` (N,), `robot_rewards` (N,, each robot's own drop rewards),
        `terminated`, `truncated`, and `final_observation` (the observations before any reset;
        free unless used). `actions` must hold one integer per agent (checked while tracing); their
        values are not checked here, as in `SNACEnv.step` (a check would cost every step; JAX
        clamps an index outside the action table). `step_env` and `step_with_strides` refuse a
        known value outside it.
        """
        if isinstance(reset_state, EnvParams):
            if params is not None:
                raise ValueError("step got params twice: as the fourth argument and as params=")
            reset_state, params = None, reset_state
        if reset_state is not None and not isinstance(reset_state, MultiState):
            raise ValueError(f"reset_state must be a MultiState or None, got {type(reset_state).__name__}")
        return self._step(key, state, actions, reset_state, self.default_params if params is None else params)

    @partial(jax.jit, static_argnames=("self",))
    def _step(
        self,
        key: jax.Array,
        state: MultiState,
        actions: Mapping[str, Any],
        reset_state: MultiState | None,
        params: EnvParams,
    ):
        obs_stepped, stepped, rewards, dones, infos = self.step_env(key, state, actions, params)
        fresh = self._reset_state(key, params) if reset_state is None else reset_state
        state = jax.tree.map(lambda r, s: jnp.where(dones["__all__"], r, s), fresh, stepped)
        return self.get_obs(state), state, rewards, dones, {**infos, "final_observation": obs_stepped}

    # --- views of a state ----------------------------------------------------------------------

    def get_obs(self, state: MultiState, params: EnvParams | None = None) -> dict[str, jax.Array]:
        """Each robot's observation (SPEC §6 and §13), keyed by agent."""
        return self._by_agent(rules.observe_all(self.config, state.world))

    def get_avail_actions(self, state: MultiState) -> dict[str, jax.Array]:
        """Every action is always allowed (a blocked move or drop is a step that does nothing)."""
        return {agent: jnp.ones(self.num_actions, jnp.bool_) for agent in self.agents}

    def is_terminated(self, state: MultiState) -> jax.Array:
        """Out of bricks, or (with obstacles) a robot stuck."""
        stuck = jax.vmap(lambda p: self.single.is_terminated(state.world.replace(position=p), self.default_params))
        return jnp.any(stuck(state.positions))

    def iou(self, state: MultiState) -> jax.Array:
        return metrics.iou(state.world)

    def render(self, state: MultiState, params: EnvParams | None = None, **kwargs) -> np.ndarray:
        """An RGB picture of one state, each robot in its colour; see `snac_jax.rendering.render_robots`."""
        from snac_jax.rendering.robots import render_robots  # rendering stays out of the step's imports

        return render_robots(self, state, params or self.default_params, **kwargs)

    # --- spaces --------------------------------------------------------------------------------

    def _agent(self, agent: str) -> str:
        if agent not in self.agents:
            raise ValueError(f"unknown agent {agent!r}; agents: {', '.join(self.agents)}")
        return agent

    def action_space(self, agent: str) -> spaces.Discrete:
        """The single-robot env's actions, the same for every robot."""
        self._agent(agent)
        return spaces.Discrete(self.num_actions)

    def observation_space(self, agent: str) -> spaces.Box:
        """The single-robot env's space (`SNACEnv.observation_space`), its window cells other than
        the centre reaching down to `ROBOT_VALUE` when other robots can show there."""
        self._agent(agent)
        space = self.single.observation_space(self.default_params)
        if self.num_agents == 1:
            return space
        layout = self.observation_layout
        window_low = np.full(layout.window_shape, rules.ROBOT_VALUE, np.float32)
        low = self.single.observation_low()  # NumPy, concrete under jit (the space's `high` may be traced)
        window_low[self.config.pad] = low[layout.window].reshape(layout.window_shape)[self.config.pad]
        low[layout.window] = window_low.reshape(-1)
        return spaces.Box(jnp.asarray(low), space.high, space.shape, space.dtype)
