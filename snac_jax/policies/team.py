"""Registered policies run as a team of robots in one world (SPEC §13), by name.

    env = snac_jax.multi.make("2d-static-dense", num_robots=2)
    team = team_policy("handcrafted", env)                      # a snac_jax.multi.MultiPolicy

The handcrafted policies run as the split of the plan (`snac_jax.policies.split`), each robot
building its own share; the random policy as N independent random robots. It lives beside the
split because it builds team policies from single-robot ones: `snac_jax.multi` stays free of
any policy (the imports run policies -> multi, never back).
"""

from __future__ import annotations

import functools

import jax

from snac_jax.multi import MultiPolicy, MultiSNACEnv
from snac_jax.policies.random import random_policy
from snac_jax.policies.split import handcrafted_split
from snac_jax.policy import Policy

TEAM_POLICIES = ("handcrafted", "handcrafted-map", "random")
"""Registered policies a team runs: the handcrafted ones as the split of the plan, the random
one as N independent random robots."""


def team_policy(name: str, env: MultiSNACEnv) -> MultiPolicy:
    """The team form of registered policy `name` for `env`; the same `MultiPolicy` for every
    call with one configuration, so jitted callers compile once per configuration."""
    if name not in TEAM_POLICIES:
        raise ValueError(f"a team runs one of: {', '.join(TEAM_POLICIES)}; got {name!r}")
    if name != "random":
        return handcrafted_split(env, "map" if name == "handcrafted-map" else "no-map")
    return _random_team(env)


@functools.cache
def _random_team(env: MultiSNACEnv) -> MultiPolicy:
    return independent_team(random_policy(env.single), env.num_agents)


def independent_team(single: Policy, num_robots: int) -> MultiPolicy:
    """N robots each running `single` on the whole design, with keys of their own."""

    def init(key, design):
        return jax.vmap(single.init, in_axes=(0, None))(jax.random.split(key, num_robots), design)

    def act(params, states, obs, key):
        keys = jax.random.split(key, num_robots)
        return jax.vmap(single.act, in_axes=(None, 0, 0, 0))(params, states, obs, keys)

    return MultiPolicy(init=init, act=act, params=single.params, name=f"{single.name}-x{num_robots}")
