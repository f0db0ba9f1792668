"""The policy interface every agent shares: the evaluator runs any `Policy` without knowing its kind.

A policy is three pure functions of one environment's view (vmap them for a batch):

- `init(key, design) -> policy_state`: at the start of each episode. `design` is the episode's
  design (plan-shaped); the handcrafted policy reads it (it knows the design, as in the paper),
  learned policies ignore it (dynamic tasks show the design in the observation).
- `act(params, policy_state, obs, key) -> (action, policy_state)`: one greedy or sampled action.
  `params` is the policy's pytree of parameters (network weights; `None` for handcrafted), passed
  as an argument rather than closed over so jit does not bake weights into the program.

A recurrent policy keeps its hidden state in `policy_state`; a stateless one returns its input.
`act` returns the policy state with the structure, shapes and dtypes it was given (episode loops
carry it); the loops call it through `call_act`, which checks that while tracing.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp


class Policy(NamedTuple):
    init: Callable[[jax.Array, jax.Array], Any]
    act: Callable[[Any, Any, jax.Array, jax.Array], tuple[jax.Array, Any]]
    params: Any = None
    name: str = "policy"


def _avals(tree: Any) -> str:
    """A pytree's leaves as `dtype[shape]`, in the tree's own form: `(float32[8], int32[])`."""
    shown = jax.tree.map(lambda x: f"{jnp.result_type(x)}{list(jnp.shape(x))}", tree)
    return str(shown).replace("'", "")


def call_act(act: Callable, params: Any, policy_state: Any, obs: jax.Array, key: jax.Array) -> tuple[jax.Array, Any]:
    """`act(params, policy_state, obs, key)`, its contract checked: the action as a JAX array
    (one integer, shape ()) and the new policy state, with the structure, shapes and dtypes of
    the one given.

    Why: an episode loop carries the policy state through `lax.while_loop`/`lax.scan`, so a bare
    action or a memory that changed form fails deep inside JAX without naming `act`. Shapes and
    dtypes are static: the check runs once while tracing and costs nothing per step."""
    out = act(params, policy_state, obs, key)
    if not (isinstance(out, (tuple, list)) and len(out) == 2):
        got = (
            f"a bare {_avals(out)} value"
            if hasattr(out, "dtype") or isinstance(out, (int, float))
            else (f"a {type(out).__name__}" + (f" of {len(out)}" if isinstance(out, (tuple, list)) else ""))
        )
        raise ValueError(f"policy.act must return (action, policy_state), got {got}")
    action, new_state = out
    action = jnp.asarray(action)
    if action.shape != () or not jnp.issubdtype(action.dtype, jnp.integer):
        raise ValueError(
            f"policy.act must return one integer action (shape ()), got {action.dtype}{list(action.shape)}"
        )
    expected, got = _avals(policy_state), _avals(new_state)
    if jax.tree.structure(policy_state) != jax.tree.structure(new_state) or expected != got:
        raise ValueError(f"policy.act must return a policy_state like the one it was given, {expected}, got {got}")
    return action, new_state


def uniform_random_policy(num_actions: int) -> Policy:
    """Uniformly random actions; the floor every agent should beat."""

    def init(key, design):
        return jnp.zeros((), jnp.int32)

    def act(params, state, obs, key):
        return jax.random.randint(key, (), 0, num_actions), state

    return Policy(init=init, act=act, params=None, name="random")
