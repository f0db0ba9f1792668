"""The one episode loop: a world stepped from a reset to its own end, never auto-reset.

The evaluator (final outcomes of many episodes), `record_episode` (every state of one episode)
and `replay` (given actions and strides) all run episodes this way. They differ only in how an
action is chosen and what they keep, so those two things are arguments and everything else is
decided here once:

- an episode ends on the step where the env terminates it (`transition`: out of bricks, stuck)
  or truncates it (`env.is_truncated`: the step limit);
- once ended, an episode does not change: later steps of a scan (or of other, longer episodes in
  the same vmapped loop) leave its state, observation, return and agent state as they were;
- the env draws the stride from a key exactly as `env.step_env` does, or a given stride is
  applied as `env.step_with_stride` (replays).

Both loops are pure and traceable (jit and vmap them from the caller, which knows what is static);
keys are threaded explicitly by the caller's `decide`, through the agent state or the scanned
inputs, so a caller keeps its own key schedule and its numbers.

    decide(episode, x) -> (Move, agent)

`episode` is the `Episode` before the step (its `obs` is what a policy may read; `state` is
there for tests and oracles), `x` the step's scanned input (None in `run_to_end`), `agent` the
updated agent state. `run_to_end` returns only the final episode and stops the loop as soon as
the episode (under vmap: every episode) has ended; `scan_episode` runs a fixed number of steps
and returns what `record` keeps of each.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from snac_jax.state import EnvParams, EnvState


@struct.dataclass
class Episode:
    """An episode between steps: what the loops carry."""

    obs: jax.Array  # observation of `state`
    state: EnvState
    agent: Any  # what `decide` keeps between steps: a policy's state, its key
    episode_return: jax.Array  # float32, sum of the rewards so far
    done: jax.Array  # bool: terminated or truncated; the episode no longer changes


def start(obs: jax.Array, state: EnvState, agent: Any) -> Episode:
    """An episode at its reset: `(obs, state)` from `env.reset` or `env.reset_to_design`."""
    return Episode(obs, state, agent, jnp.zeros((), jnp.float32), jnp.asarray(False))


class Move(NamedTuple):
    """One step's action and the source of its stride: exactly one of `key` and `stride`.

    With `key` the env draws the stride (`env.step_env`), as in any live episode; with `stride`
    the given stride is applied (`env.step_with_stride`), as in a replay.
    """

    action: jax.Array
    key: jax.Array | None = None
    stride: jax.Array | None = None


class Step(NamedTuple):
    """One step of `scan_episode`, as `record` sees it.

    A step after the end (`live` False) is not taken: `obs` and `state` are the episode's final
    ones, `reward` is 0, both flags are False; `action` and `stride` are what `decide` chose.
    """

    live: jax.Array  # bool: the episode had not ended before this step
    action: jax.Array
    stride: jax.Array  # int32, the stride drawn or given
    obs: jax.Array  # after the step
    state: EnvState  # after the step
    reward: jax.Array
    terminated: jax.Array  # the env ended the episode on this step (out of bricks, stuck)
    truncated: jax.Array  # the step limit ended it on this step


Decide = Callable[[Episode, Any], tuple[Move, Any]]


def _advance(env, params: EnvParams, decide: Decide, episode: Episode, x) -> tuple[Episode, Step]:
    """One step of `episode`, whether or not it has ended (the callers mask)."""
    move, agent = decide(episode, x)
    if (move.key is None) == (move.stride is None):
        raise ValueError("a Move takes exactly one of key (the env draws the stride) and stride (given)")
    if move.key is not None:
        obs, state, reward, terminated, info = env.step_env(move.key, episode.state, move.action, params)
    else:
        obs, state, reward, terminated, info = env.step_with_stride(episode.state, move.action, move.stride, params)
    truncated = env.is_truncated(state, params)
    stepped = Episode(
        obs=obs, state=state, agent=agent, episode_return=episode.episode_return + reward, done=terminated | truncated
    )
    return stepped, Step(
        live=~episode.done,
        action=move.action,
        stride=info["stride"],
        obs=obs,
        state=state,
        reward=reward,
        terminated=terminated,
        truncated=truncated,
    )


def run_to_end(env, params: EnvParams, decide: Decide, episode: Episode) -> Episode:
    """Step `episode` until it ends; the final episode (`state.time` steps were taken).

    A `lax.while_loop` on `done`: its length is the episode's own, and the step limit bounds it.
    Under `vmap` the loop runs until the last episode ends and JAX leaves the ended ones as they
    were, so a batch of episodes costs its longest one, not the step limit. `decide` gets
    `x=None`.
    """
    return jax.lax.while_loop(lambda e: ~e.done, lambda e: _advance(env, params, decide, e, None)[0], episode)


def scan_episode(
    env,
    params: EnvParams,
    decide: Decide,
    episode: Episode,
    *,
    num_steps: int | None = None,
    xs: Any = None,
    record: Callable[[Step], Any] = lambda step: step,
) -> tuple[Episode, Any]:
    """Step `episode` `num_steps` times (or once per leading entry of `xs`, handed to `decide`);
    the final episode and `record(step)` of every step, stacked.

    A `lax.scan`, because per-step outputs need a static length; steps after the end leave the
    episode unchanged (see `Step`), so the final episode is the one at its end, and cutting the
    records where `live` turns False gives exactly the episode's steps. To keep only the final
    episode, `run_to_end` stops earlier.
    """

    def body(episode: Episode, x):
        stepped, step = _advance(env, params, decide, episode, x)
        ended = episode.done
        episode = jax.tree.map(lambda old, new: jnp.where(ended, old, new), episode, stepped)
        step = step._replace(
            obs=episode.obs,
            state=episode.state,
            reward=jnp.where(ended, jnp.zeros_like(step.reward), step.reward),
            terminated=step.terminated & ~ended,
            truncated=step.truncated & ~ended,
        )
        return episode, record(step)

    return jax.lax.scan(body, episode, xs, length=num_steps)
