"""The uniformly random policy as a registry builder (`snac eval --policy random`)."""

from __future__ import annotations

import functools

from snac_jax.env import SNACEnv
from snac_jax.policy import Policy, uniform_random_policy


@functools.cache
def _cached(num_actions: int) -> Policy:
    # The same init/act objects for every call: jitted evaluators compile once per configuration.
    return uniform_random_policy(num_actions)


def random_policy(env: SNACEnv) -> Policy:
    return _cached(env.num_actions)
