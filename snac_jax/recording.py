"""One episode of any `Policy`, kept step by step so that it can be drawn or inspected.

The evaluator only needs final IoUs; a video needs every intermediate state. `record_episode`
runs one world for the whole step limit in a single jitted `lax.scan` (no auto-reset: the
episode's last state is kept), then cuts the stacked states at the step that ended the episode.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from snac_jax.env import SNACEnv
from snac_jax.policy import Policy
from snac_jax.state import EnvParams, EnvState


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """One episode: `states[0]` is the reset state, `states[t]` the state after `actions[t-1]`.

    All leaves are numpy arrays cut to the episode's `length` steps (length + 1 states).
    """

    states: EnvState
    actions: np.ndarray  # (length,) int
    strides: np.ndarray  # (length,) int, the stride drawn at each step
    rewards: np.ndarray  # (length,) float32
    final_iou: float
    terminated: bool  # out of bricks or stuck (False: the step limit truncated it)

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])

    def state_at(self, t: int) -> EnvState:
        return jax.tree.map(lambda x: x[t], self.states)


@partial(jax.jit, static_argnames=("env", "init", "act", "num_steps"))
def _scan_episode(key, env: SNACEnv, params: EnvParams, init, act, policy_params: Any, num_steps: int):
    key_reset, key_policy, key_run = jax.random.split(key, 3)
    obs, state = env.reset(key_reset, params)
    policy_state = init(key_policy, state.design)

    def body(carry, step_key):
        obs, state, policy_state, done = carry
        key_act, key_step = jax.random.split(step_key)
        action, policy_state = act(policy_params, policy_state, obs, key_act)
        # gymnax's step without auto-reset: draws the stride as `env.step` does, keeps the end state.
        obs, next_state, reward, terminated, info = env.step_env(key_step, state, action, params)
        stride = info["stride"]
        truncated = next_state.time >= params.max_steps_in_episode
        out = (next_state, action, stride, reward, terminated, terminated | truncated)
        return (obs, next_state, policy_state, done | terminated | truncated), out

    _, (states, actions, strides, rewards, terminated, ends) = jax.lax.scan(
        body, (obs, state, policy_state, jnp.asarray(False)), jax.random.split(key_run, num_steps)
    )
    states = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), state, states)
    return states, actions, strides, rewards, terminated, ends


def record_episode(env: SNACEnv, params: EnvParams, policy: Policy, key: jax.Array) -> Trajectory:
    """Run `policy` greedily-or-not (as its `act` decides) through one episode from `env.reset`."""
    num_steps = int(params.max_steps_in_episode)
    states, actions, strides, rewards, terminated, ends = jax.device_get(
        _scan_episode(key, env, params, policy.init, policy.act, policy.params, num_steps)
    )
    # The step limit guarantees an end within num_steps steps.
    length = int(np.argmax(ends)) + 1
    states = jax.tree.map(lambda x: np.asarray(x[: length + 1]), states)
    last = jax.tree.map(lambda x: x[length], states)
    return Trajectory(
        states=states,
        actions=np.asarray(actions[:length]),
        strides=np.asarray(strides[:length]),
        rewards=np.asarray(rewards[:length]),
        final_iou=float(last.overlap / max(int(last.union), 1)),
        terminated=bool(terminated[length - 1]),
    )
