"""The policy interface every agent shares: the evaluator runs any `Policy` without knowing its kind.

A policy is three pure functions of one environment's view (vmap them for a batch):

- `init(key, design) -> policy_state`: at the start of each episode. `design` is the episode's
  design (plan-shaped); the handcrafted policy reads it (it knows the design, as in the paper),
  learned policies ignore it (dynamic tasks show the design in the observation).
- `act(params, policy_state, obs, key) -> (action, policy_state)`: one greedy or sampled action.
  `params` is the policy's pytree of parameters (network weights; `None` for handcrafted), passed
  as an argument rather than closed over so jit does not bake weights into the program.

A recurrent policy keeps its hidden state in `policy_state`; a stateless one returns its input.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp


class Policy(NamedTuple):
    init: Callable[[jax.Array, jax.Array], Any]
    act: Callable[[Any, Any, jax.Array, jax.Array], tuple[jax.Array, Any]]
    params: Any = None
    name: str = "policy"


def uniform_random_policy(num_actions: int) -> Policy:
    """Uniformly random actions; the floor every agent should beat."""

    def init(key, design):
        return jnp.zeros((), jnp.int32)

    def act(params, state, obs, key):
        return jax.random.randint(key, (), 0, num_actions), state

    return Policy(init=init, act=act, params=None, name="random")
