"""The handcrafted baseline for a team (SPEC §13): the plan split among the robots, each robot
running the single-robot handcrafted policy (SPEC §11) on its share of the design.

    env = snac_jax.multi.make("2d-static-dense", num_robots=2)
    team = handcrafted_split(env)
    episode = jax.jit(lambda k: snac_jax.multi.run_episode(env, team, k))(key)   # .iou, .length

Why a split: the handcrafted robot builds every design cell it sees that lacks bricks, so robots
given the whole design would crowd the same cells; given disjoint shares, each builds its own and
the team's work adds up. The share of a cell is the robot whose start is nearest, so each robot
starts inside its share, with walls in view that fix its position estimate. In a team its
localiser leaves out the cells where it sees another robot (`handcrafted_policy(team=True)`),
which moved or built there between two views, and counts the median stride after a move that
every stride explains (the team's `params`: the env's stride distribution); one robot is the
single-robot policy itself.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.config import EnvConfig
from snac_jax.multi import MultiPolicy, MultiSNACEnv, start_positions
from snac_jax.policies.handcrafted import VARIANTS_1D, handcrafted_policy


def plan_shares(config: EnvConfig, num_robots: int) -> np.ndarray:
    """bool (num_robots, *plan_shape): each plan cell belongs to the robot whose start is nearest
    in Manhattan distance, the lower index on a tie (SPEC §13's table)."""
    starts = start_positions(config, num_robots)
    rows, cols = np.indices(config.plan_shape)
    distance = np.abs(rows[None] - starts[:, 0, None, None]) + np.abs(cols[None] - starts[:, 1, None, None])
    owner = np.argmin(distance, axis=0)  # argmin takes the first of equal distances
    return owner[None] == np.arange(num_robots)[:, None, None]


@functools.cache
def _split(env: MultiSNACEnv, variant: str) -> MultiPolicy:
    # One MultiPolicy (the same init/act objects) per configuration, so jitted callers that take
    # it as a static argument compile once per configuration.
    # One robot is the single-robot policy itself; in a team each robot's localiser leaves out
    # the cells where it sees another robot.
    single = handcrafted_policy(env.single, variant, team=env.num_agents > 1)
    shares = jnp.asarray(plan_shares(env.config, env.num_agents))
    starts = jnp.asarray(start_positions(env.config, env.num_agents))

    def init(key: jax.Array, design: jax.Array):
        keys = jax.random.split(key, env.num_agents)
        own_designs = jnp.where(shares, design[None], jnp.zeros_like(design)[None])
        states = jax.vmap(single.init)(keys, own_designs)
        return states.replace(estimate=starts)

    def act(params, states, obs: jax.Array, key: jax.Array):
        # `params`: the robots' (one robot: none; a team: the stride distribution, `odometry_stride`)
        keys = jax.random.split(key, env.num_agents)
        return jax.vmap(single.act, in_axes=(None, 0, 0, 0))(params, states, obs, keys)

    return MultiPolicy(init=init, act=act, params=None, name=f"{single.name}-split")


def handcrafted_split(env: MultiSNACEnv, variant: str = "no-map") -> MultiPolicy:
    """The team's handcrafted baseline for `env` (a `snac_jax.multi.MultiSNACEnv`); `variant` is
    the 1D variant of `handcrafted_policy` (`"no-map"` or `"map"`)."""
    if not isinstance(env, MultiSNACEnv):
        raise ValueError(f"handcrafted_split takes a snac_jax.multi env, got {type(env).__name__}")
    if variant not in VARIANTS_1D:
        raise ValueError(f"variant must be one of {VARIANTS_1D}, got {variant!r}")
    # The same init/act per configuration (compiled once); the params, the robots' stride
    # distribution in a team, are the env's own.
    return _split(env, variant)._replace(params=handcrafted_policy(env.single, variant, team=env.num_agents > 1).params)
