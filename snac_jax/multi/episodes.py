"""Whole episodes of several robots: a team policy run to the episode's end, the same episode
kept step by step for a video, and a replay.

All step without auto-reset (`MultiSNACEnv.step_env`, `step_with_strides`) and leave an
ended episode as it was, as the single-robot loops of `snac_jax.episodes` do, so an
evaluation's score is the final IoU of each episode and its length the steps it took.
`run_episode` and `record_team_episode` share one step (`_team_step`) and one key schedule,
so a recorded episode is the episode an evaluation scores from the same key and start.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from snac_jax.config import MAX_STRIDE
from snac_jax.env import check_range
from snac_jax.multi.env import MultiSNACEnv
from snac_jax.recording import Trajectory
from snac_jax.replay import REPLAY_CHUNK
from snac_jax.state import EnvParams


class MultiPolicy(NamedTuple):
    """A team's policy, the multi-robot form of `snac_jax.policy.Policy` (pure, under jit/vmap):

    - `init(key, design) -> policy_state` at each episode start (`design` plan-shaped);
    - `act(params, policy_state, obs, key) -> (actions, policy_state)`, `obs` (N, obs_size) and
      `actions` int (N,) in robot order.

    Arrays rather than dicts, so a policy with shared parameters vmaps over its robots.
    """

    init: Callable[[jax.Array, jax.Array], Any]
    act: Callable[[Any, Any, jax.Array, jax.Array], tuple[jax.Array, Any]]
    params: Any = None
    name: str = "team"


@struct.dataclass
class TeamEpisode:
    """What one finished episode leaves for an evaluation."""

    iou: jax.Array  # float32, the final IoU
    length: jax.Array  # int32, the steps taken (N_s)
    bricks_used: jax.Array  # int32
    team_return: jax.Array  # float32, the sum of the team rewards
    # bool: the env ended it (bricks spent, a robot stuck), on any step including the last allowed one;
    # False: the step limit alone truncated it
    terminated: jax.Array


def stack(env: MultiSNACEnv, by_agent: dict[str, jax.Array]) -> jax.Array:
    """A dict keyed by agent as one array, robot order first."""
    return jnp.stack([by_agent[agent] for agent in env.agents])


def _team_start(env: MultiSNACEnv, policy: MultiPolicy, key: jax.Array, reset: Callable[[jax.Array], Any]):
    """The first carry of `_team_step`: the world from `reset(key)`, the policy's state, the run's key."""
    key_reset, key_init, key_run = jax.random.split(key, 3)
    obs, state = reset(key_reset)
    return stack(env, obs), state, policy.init(key_init, state.world.design), key_run


def _team_step(env: MultiSNACEnv, policy: MultiPolicy, params: EnvParams, carry):
    """One step of the team: the policy acts on the stacked observations, the world steps with
    strides drawn from the carried key. Returns the next carry and `(actions (N,), team reward,
    done, infos)`; the one body of `run_episode` and `record_team_episode`."""
    obs, state, agent, key = carry
    key, key_act, key_step = jax.random.split(key, 3)
    actions, agent = policy.act(policy.params, agent, obs, key_act)
    by_agent = {name: actions[i] for i, name in enumerate(env.agents)}
    obs, state, rewards, dones, infos = env.step_env(key_step, state, by_agent, params)
    return (stack(env, obs), state, agent, key), (actions, rewards[env.agents[0]], dones["__all__"], infos)


def run_episode(
    env: MultiSNACEnv,
    policy: MultiPolicy,
    key: jax.Array,
    design_index: jax.Array | int = 0,
    params: EnvParams | None = None,
) -> TeamEpisode:
    """One episode on `params.designs[design_index]` from its reset to its end (a `while_loop`,
    bounded by the step limit); jit and vmap it from the caller (over keys or design indices)."""
    params = env.default_params if params is None else params
    start = _team_start(env, policy, key, lambda k: env.reset_to_design(k, design_index, params))

    def body(loop):
        carry, total, _, _ = loop
        carry, (_, reward, done, infos) = _team_step(env, policy, params, carry)
        return carry, total + reward, done, infos["terminated"]

    first = (start, jnp.zeros((), jnp.float32), jnp.asarray(False), jnp.asarray(False))
    (_, state, _, _), total, _, terminated = jax.lax.while_loop(lambda loop: ~loop[2], body, first)
    world = state.world
    return TeamEpisode(
        iou=env.iou(state), length=world.time, bricks_used=world.bricks_used, team_return=total, terminated=terminated
    )


@partial(jax.jit, static_argnames=("env", "init", "act", "num_steps"))
def _record_scan(key, env: MultiSNACEnv, params: EnvParams, init, act, policy_params, num_steps: int):
    # `init` and `act` static, as in `snac_jax.recording`: one compilation per configuration.
    policy = MultiPolicy(init, act, policy_params)
    start = _team_start(env, policy, key, lambda k: env.reset(k, params))

    def body(loop, _):
        carry, ended = loop
        stepped, (actions, reward, done, infos) = _team_step(env, policy, params, carry)
        keep = lambda old, new: jax.tree.map(lambda o, n: jnp.where(ended, o, n), old, new)
        carry = (*keep(carry[:3], stepped[:3]), stepped[3])  # after the end, only the unused key moves
        return (carry, ended | done), (carry[1], actions, infos["strides"], reward, infos["terminated"], ~ended)

    ((_, final, _, _), _), (states, actions, strides, rewards, terminated, live) = jax.lax.scan(
        body, (start, jnp.asarray(False)), None, length=num_steps
    )
    states = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), start[1], states)
    return states, actions, strides, rewards, terminated, live, env.iou(final)


def record_team_episode(env: MultiSNACEnv, params: EnvParams, policy: MultiPolicy, key: jax.Array) -> Trajectory:
    """One episode of a team from `env.reset`, kept step by step, as `snac_jax.recording.record_episode`
    keeps a single robot's: a `Trajectory` whose states are `MultiState`s and whose actions and
    strides are (length, N). One scan over the whole step limit, jitted once per configuration
    (env, policy functions, step limit); an ended episode stays as it was."""
    states, actions, strides, rewards, terminated, live, final_iou = jax.device_get(
        _record_scan(key, env, params, policy.init, policy.act, policy.params, int(params.max_steps_in_episode))
    )
    length = int(np.sum(live))  # the step limit ends every episode within the scan
    return Trajectory(
        states=jax.tree.map(lambda x: np.asarray(x[: length + 1]), states),
        actions=np.asarray(actions[:length]),
        strides=np.asarray(strides[:length]),
        rewards=np.asarray(rewards[:length]),
        final_iou=float(final_iou),
        terminated=bool(terminated[length - 1]),
    )


@partial(jax.jit, static_argnums=0)
def _replay_scan(env: MultiSNACEnv, params: EnvParams, design_index, actions: jax.Array, strides: jax.Array):
    obs, state = env.reset_to_design(jax.random.key(0), design_index, params)

    def body(carry, inputs):
        state, ended = carry
        acts, strs = inputs
        by = lambda x: {name: x[i] for i, name in enumerate(env.agents)}
        obs, stepped, rewards, dones, infos = env.step_with_strides(state, by(acts), by(strs), params)
        state = jax.tree.map(lambda old, new: jnp.where(ended, old, new), state, stepped)
        live = ~ended
        record = (
            stack(env, env.get_obs(state)),
            jnp.where(live, rewards[env.agents[0]], 0.0),
            infos["terminated"] & live,
            infos["truncated"] & live,
        )
        return (state, ended | dones["__all__"]), record

    (state, _), records = jax.lax.scan(body, (state, jnp.asarray(False)), (actions, strides))
    return stack(env, obs), state, records


def replay(
    env: MultiSNACEnv, actions, strides, params: EnvParams | None = None, design_index: int = 0
) -> dict[str, Any]:
    """One episode from `reset_to_design` with the given actions and strides, both int (T, N).

    Returns the observations (T+1, N, obs_size), the team rewards, terminated and truncated flags
    (T,), the plan after the last step and its IoU. Steps after the episode's end are not taken.
    Inputs are padded to a multiple of `snac_jax.replay.REPLAY_CHUNK` steps, so one
    configuration compiles a few times at most.
    """
    params = env.default_params if params is None else params
    actions, strides = np.asarray(actions), np.asarray(strides)
    steps = len(actions)
    if not steps or actions.shape != (steps, env.num_agents) or strides.shape != actions.shape:
        raise ValueError(
            f"replay needs actions and strides of shape (T, {env.num_agents}), T >= 1, got "
            f"{actions.shape} and {strides.shape}"
        )
    check_range("actions", actions, 0, env.num_actions - 1)
    check_range("strides", strides, 1, MAX_STRIDE)
    padded = -(-steps // REPLAY_CHUNK) * REPLAY_CHUNK
    pad = lambda x: jnp.asarray(np.pad(np.asarray(x, np.int32), ((0, padded - steps), (0, 0)), constant_values=1))
    obs0, state, (obs, rewards, terminated, truncated) = _replay_scan(
        env, params, design_index, pad(actions), pad(strides)
    )
    (pr, pc), (h, w) = env.config.pad, env.config.plan_shape
    grid = np.asarray(state.world.grid)[pr : pr + h, pc : pc + w]
    return {
        "observations": np.concatenate([np.asarray(obs0)[None], np.asarray(obs[:steps])]),
        "rewards": np.asarray(rewards[:steps]),
        "terminated": np.asarray(terminated[:steps]),
        "truncated": np.asarray(truncated[:steps]),
        "final_grid": grid[0] if env.config.dim == 1 else grid,
        "final_iou": float(env.iou(state)),
        "bricks_used": int(state.world.bricks_used),
    }
