"""One episode of any `Policy`, kept step by step so that it can be drawn or inspected.

The evaluator only needs final IoUs; a video needs every intermediate state. `record_episode`
runs one world for the whole step limit in a single jitted scan of `snac_jax.episodes` (no
auto-reset: the episode stays at its end), then cuts the stacked states at the step that ended it.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax import episodes, metrics
from snac_jax.env import SNACEnv
from snac_jax.policy import Policy, call_act
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

    def decide(episode: episodes.Episode, step_key):
        key_act, key_step = jax.random.split(step_key)
        action, policy_state = call_act(act, policy_params, episode.agent, episode.obs, key_act)
        return episodes.Move(action, key=key_step), policy_state

    def record(step: episodes.Step):
        return step.state, step.action, step.stride, step.reward, step.terminated, step.live

    first = episodes.start(obs, state, init(key_policy, state.design))
    final, (states, actions, strides, rewards, terminated, live) = episodes.scan_episode(
        env, params, decide, first, xs=jax.random.split(key_run, num_steps), record=record
    )
    states = jax.tree.map(lambda first, rest: jnp.concatenate([first[None], rest]), state, states)
    return states, actions, strides, rewards, terminated, live, metrics.iou(final.state)


def record_episode(env: SNACEnv, params: EnvParams, policy: Policy, key: jax.Array) -> Trajectory:
    """Run `policy` greedily-or-not (as its `act` decides) through one episode from `env.reset`."""
    num_steps = int(params.max_steps_in_episode)
    states, actions, strides, rewards, terminated, live, final_iou = jax.device_get(
        _scan_episode(key, env, params, policy.init, policy.act, policy.params, num_steps)
    )
    # The step limit ends every episode within num_steps steps.
    length = int(np.sum(live))
    return Trajectory(
        states=jax.tree.map(lambda x: np.asarray(x[: length + 1]), states),
        actions=np.asarray(actions[:length]),
        strides=np.asarray(strides[:length]),
        rewards=np.asarray(rewards[:length]),
        final_iou=float(final_iou),
        terminated=bool(terminated[length - 1]),
    )
