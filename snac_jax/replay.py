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
from snac_jax.config import MAX_STRIDE
from snac_jax.env import SNACEnv, check_range
from snac_jax.state import EnvParams
from snac_jax.tasks import make

GOLDEN_TRACES_ENV_VAR = "SNAC_GOLDEN_TRACES"


TRACE_KEYS = (
    "variant",
    "dim",
    "max_steps",
    "max_bricks",
    "design",
    "actions",
    "strides",
    "rewards",
    "dones",
    "observations",
    "final_grid",
    "final_iou",
)


def load_traces(path: str | os.PathLike) -> list[dict]:
    """A golden-trace file: a gzip'd (or plain) JSON list of episodes.

    `ValueError` naming the file unless it holds at least one complete trace: an empty or cut
    file must fail the conformance tests, not leave them nothing to check.
    """
    path = Path(path)
    opener = gzip.open if path.suffix == ".gz" else open
    try:
        with opener(path, "rt") as f:
            traces = json.load(f)
    except (OSError, EOFError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: not a readable golden-trace file ({type(error).__name__}: {error})") from error
    if not isinstance(traces, list) or not traces:
        raise ValueError(
            f"{path}: expected a non-empty JSON list of traces, got {type(traces).__name__} of length "
            f"{len(traces) if isinstance(traces, (list, dict)) else '-'}"
        )
    for number, trace in enumerate(traces):
        missing = [k for k in TRACE_KEYS if not isinstance(trace, dict) or k not in trace]
        steps = len(trace.get("actions", ())) if isinstance(trace, dict) else 0
        lengths = None if missing else {len(trace[k]) for k in ("actions", "strides", "rewards", "dones")}
        if missing or not steps or lengths != {steps} or len(trace["observations"]) != steps + 1:
            why = (
                f"lacks {missing}"
                if missing
                else "its actions, strides, rewards, dones and observations disagree in length"
            )
            raise ValueError(f"{path}: trace {number} is incomplete: {why}")
    return traces


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
        state = step.state
        return step.obs, step.reward, step.terminated, step.truncated, metrics.iou(state), state.grid, state.bricks_used

    first = episodes.start(obs0, state0, None)
    _, outputs = episodes.scan_episode(env, params, decide, first, xs=(actions, strides), record=record)
    return obs0, outputs


def replay(env: SNACEnv, params: EnvParams, actions, strides) -> dict[str, np.ndarray]:
    """Run one episode from reset with the given actions and strides, in one jitted scan.

    Returns observations (T+1, obs) with the reset observation first, rewards, terminated and
    truncated flags (T,), the design-area grid after the last action, its IoU and the bricks
    used. Actions after the episode's end are not taken (see `snac_jax.episodes.Step`). Inputs
    are padded to a multiple of `REPLAY_CHUNK` steps so one configuration compiles a few times
    at most; the padding steps are cut off. Actions outside the task's, strides outside 1..3,
    or no action at all are a `ValueError` (the env would clamp them).
    """
    actions, strides = np.asarray(actions), np.asarray(strides)
    steps = len(actions)
    if actions.shape != (steps,) or strides.shape != (steps,) or not steps:
        raise ValueError(
            f"replay needs one stride per action and at least one action, got {actions.shape[:1]} "
            f"actions and {strides.shape[:1]} strides"
        )
    for name, values in (("actions", actions), ("strides", strides)):
        if not np.issubdtype(values.dtype, np.integer):
            raise ValueError(f"{name} must be integers, got {values.dtype}")
    check_range("actions", actions, 0, env.num_actions - 1)
    check_range("strides", strides, 1, MAX_STRIDE)
    padded = -(-steps // REPLAY_CHUNK) * REPLAY_CHUNK
    pad = lambda x: jnp.asarray(np.pad(np.asarray(x, np.int32), (0, padded - steps), constant_values=1))
    obs0, (obs, rewards, terminated, truncated, ious, grids, bricks) = _replay_scan(
        env, params, pad(actions), pad(strides)
    )
    (pr, pc), (h, w) = env.config.pad, env.config.plan_shape
    grid = np.asarray(grids[steps - 1])[pr : pr + h, pc : pc + w]
    return {
        "observations": np.concatenate([np.asarray(obs0)[None], np.asarray(obs[:steps])]),
        "rewards": np.asarray(rewards[:steps]),
        "terminated": np.asarray(terminated[:steps]),
        "truncated": np.asarray(truncated[:steps]),
        "final_grid": grid[0] if env.config.dim == 1 else grid,
        "final_iou": float(ious[steps - 1]),
        "bricks_used": int(bricks[steps - 1]),
    }
