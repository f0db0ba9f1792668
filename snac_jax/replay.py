"""Replaying recorded episodes (SPEC §10): actions with their recorded strides."""

from __future__ import annotations

import gzip
import json
import os
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax import episodes, metrics
from snac_jax.env import SNACEnv
from snac_jax.state import EnvParams
from snac_jax.tasks import make

GOLDEN_TRACES_ENV_VAR = "SNAC_GOLDEN_TRACES"


def load_traces(path: str | os.PathLike) -> list[dict]:
    """A golden-trace file: a gzip'd (or plain) JSON list of episodes."""
    path = Path(path)
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt") as f:
        return json.load(f)


def env_for_trace(trace: dict) -> tuple[SNACEnv, EnvParams]:
    """The environment a trace was recorded in: `variant` is a task id or `<task>-testN`."""
    variant = trace["variant"]
    if "-test" in variant:
        task_id, index = variant.rsplit("-test", 1)
        return make(task_id, test_design=int(index), max_steps=int(trace["max_steps"]))
    return make(variant, max_steps=int(trace["max_steps"]))


REPLAY_CHUNK = 512


@partial(jax.jit, static_argnums=0)
def _replay_scan(env: SNACEnv, params: EnvParams, actions: jax.Array, strides: jax.Array):
    obs0, state0 = env.reset(jax.random.key(0), params)

    def decide(episode: episodes.Episode, action_stride):
        action, stride = action_stride
        return episodes.Move(action, stride=stride), episode.agent

    def record(step: episodes.Step):
        return step.obs, step.reward, step.terminated, step.truncated, metrics.iou(step.state), step.state.grid

    first = episodes.start(obs0, state0, None)
    _, outputs = episodes.scan_episode(env, params, decide, first, xs=(actions, strides), record=record)
    return obs0, outputs


def replay(env: SNACEnv, params: EnvParams, actions, strides) -> dict[str, np.ndarray]:
    """Run one episode from reset with the given actions and strides, in one jitted scan.

    Returns observations (T+1, obs) with the reset observation first, rewards, terminated and
    truncated flags (T,), the design-area grid after the last action and its IoU. Actions after
    the episode's end are not taken (see `snac_jax.episodes.Step`). Inputs are padded to a
    multiple of `REPLAY_CHUNK` steps so one configuration compiles a few times at most; the
    padding steps are cut off.
    """
    steps = len(actions)
    padded = -(-max(steps, 1) // REPLAY_CHUNK) * REPLAY_CHUNK
    pad = lambda x: jnp.asarray(np.pad(np.asarray(x, np.int32), (0, padded - steps), constant_values=1))
    obs0, (obs, rewards, terminated, truncated, ious, grids) = _replay_scan(env, params, pad(actions), pad(strides))
    (pr, pc), (h, w) = env.config.pad, env.config.plan_shape
    grid = np.asarray(grids[steps - 1])[pr : pr + h, pc : pc + w]
    return {
        "observations": np.concatenate([np.asarray(obs0)[None], np.asarray(obs[:steps])]),
        "rewards": np.asarray(rewards[:steps]),
        "terminated": np.asarray(terminated[:steps]),
        "truncated": np.asarray(truncated[:steps]),
        "final_grid": grid[0] if env.config.dim == 1 else grid,
        "final_iou": float(ious[steps - 1]),
    }
