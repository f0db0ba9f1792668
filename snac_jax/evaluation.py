"""The evaluation protocol (SPEC §8): every agent in the project is scored by `evaluate_task`.

- Static task: `static_episodes` (default `STATIC_EPISODES`, the paper's) episodes on its
  design. The paper's `1d-static` is the three shapes, that many episodes each: mean of the
  three means, minimum over all of them.
- Dynamic task: its ten fixed test designs x `episodes_per_test_design` (default
  `EPISODES_PER_TEST_DESIGN`, the paper's) episodes.
- Every episode runs to its own end (brick budget, stuck, or the step limit), never auto-reset;
  the policy acts as given (a learned agent passes its greedy policy).

One environment task is one jitted, vmapped call (`run_episodes`): all its episodes advance
together in the loop of `snac_jax.episodes.run_to_end` until the last one ends. The call is
compiled once per (environment configuration, policy functions, episode count): `policy.init`
and `policy.act` are static arguments, so build them once per configuration (a new closure
recompiles), while `policy.params` is an ordinary argument, so new weights do not recompile.

The reported interval is a 95% normal confidence interval of the mean. Designs (or shapes) are
fixed strata with equal weight, so the standard error is the stratified one,
sqrt(sum_d s_d^2 / n_d) / D, which for a single design is the usual s / sqrt(n).
"""

from __future__ import annotations

import dataclasses
import math
import time
import zlib
from collections.abc import Callable
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from snac_jax import design_change, designs, devices, episodes, memory, metrics
from snac_jax.env import SNACEnv, check_range
from snac_jax.paper import PAPER_GROUPS, PAPER_TASKS
from snac_jax.policy import Policy, call_act
from snac_jax.state import EnvParams
from snac_jax.tasks import MAX_SEED, TASKS, make, make_params, task_spec, test_design_names

STATIC_EPISODES = 500
"""Episodes per static task in the protocol (SPEC §8): the one place the count is stated."""
EPISODES_PER_TEST_DESIGN = 200
"""Episodes per test design of a dynamic task in the protocol (SPEC §8)."""
Z_95 = 1.959963984540054

TUNING_EVAL_SEED = 0
"""The evaluation key of everyday scoring (`snac eval`, `snac train`): the runs that chose the
tuned settings were scored with it, so their numbers carry the selection's optimism."""
REPORT_EVAL_SEED = 1_000_003
"""The evaluation key reserved for reported results (`snac table`): no setting was chosen by
looking at scores under it, so the episodes it draws are new to every tuning decision."""

PolicyLike = Policy | Callable[[SNACEnv], Policy]
"""A `Policy` used as is for every environment task, or a builder `builder(env) -> Policy`
called once per environment task (a learned agent loads the checkpoint of that task)."""


def environment_tasks(task: str) -> tuple[str, ...]:
    """The environment tasks behind a task name: the three shapes for `1d-static`."""
    if task in PAPER_GROUPS:
        return PAPER_GROUPS[task]
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; allowed: {', '.join(PAPER_TASKS)}, {', '.join(TASKS)}")
    return (task,)


# --- one environment task: the jitted, vmapped episodes -------------------------------------------


@struct.dataclass
class Episodes:
    """Per-episode outcomes of one `run_episodes` call (leading axis: episodes)."""

    iou: jax.Array  # float32, final IoU
    length: jax.Array  # int32, steps taken
    bricks_used: jax.Array  # int32
    episode_return: jax.Array  # float32, sum of rewards
    design_index: jax.Array  # int32, index into the params' designs
    invalid_actions: jax.Array  # int32, actions outside 0..num_actions-1 (the env would clamp them)


def protocol_start(env, env_params: EnvParams, init, key: jax.Array, design_index, extra) -> episodes.Episode:
    """Episode `key`'s start as the protocol runs it: the reset, the fixed schedule of design changes
    (SPEC §15), the policy's `init`, each from its own part of the key; the agent is
    `(key, policy_state, extra)` for `protocol_decide`. Anything that must replay the protocol's
    episodes exactly (a tally on the way, a recording) starts them here."""
    key_reset, key_init, key_run = jax.random.split(key, 3)
    obs, state = env.reset_to_design(key_reset, env_params, design_index)
    if env.config.design_change is not None:
        state = design_change.schedule(env.config, env_params, state, design_index)
    return episodes.start(obs, state, (key_run, init(key_init, state.design), extra))


def protocol_decide(act, policy_params, watch):
    """The protocol's `decide` for `episodes.run_to_end` / `scan_episode`: each step splits the
    episode's key into the policy's and the step's; `watch(episode, action, extra) -> extra` sees
    the episode before the step (the policy state that chose `action`) and keeps what it counts."""

    def decide(episode: episodes.Episode, _):
        key, policy_state, extra = episode.agent
        key, key_act, key_step = jax.random.split(key, 3)
        action, new_policy_state = call_act(act, policy_params, policy_state, episode.obs, key_act)
        return episodes.Move(action, key=key_step), (key, new_policy_state, watch(episode, action, extra))

    return decide


@partial(jax.jit, static_argnames=("env", "init", "act"))
def _run_episodes(env, init, act, policy_params, env_params: EnvParams, keys, design_indices) -> Episodes:
    def count_invalid(episode, action, invalid):
        return invalid + ((action < 0) | (action >= env.num_actions)).astype(jnp.int32)

    decide = protocol_decide(act, policy_params, count_invalid)

    def run(key, design_index):
        first = protocol_start(env, env_params, init, key, design_index, jnp.zeros((), jnp.int32))
        final = episodes.run_to_end(env, env_params, decide, first)
        return Episodes(
            iou=metrics.iou(final.state),
            length=final.state.time,
            bricks_used=final.state.bricks_used,
            episode_return=final.episode_return,
            design_index=design_index,
            invalid_actions=final.agent[2],
        )

    return jax.vmap(run)(keys, design_indices)


@partial(jax.jit, static_argnames=("env", "init", "act", "mesh"))
def _run_episodes_sharded(env, init, act, policy_params, env_params, keys, design_indices, mesh) -> Episodes:
    # Each device runs its own share of the episodes (its own while-loop), so every core works.
    def per_device(keys, design_indices, policy_params, env_params):
        return _run_episodes(env, init, act, policy_params, env_params, keys, design_indices)

    replicated = jax.sharding.PartitionSpec()
    run = jax.shard_map(
        per_device,
        mesh=mesh,
        in_specs=(devices.ENVS, devices.ENVS, replicated, replicated),
        out_specs=devices.ENVS,
        check_vma=False,
    )
    return run(keys, design_indices, policy_params, env_params)


def run_episodes(
    env: SNACEnv, params: EnvParams, policy: Policy, key: jax.Array, design_indices, num_devices: int | None = None
) -> Episodes:
    """One episode per entry of `design_indices` (indices into `params.designs`), each run to
    its end with `policy`, all in one jitted, vmapped call.

    The episodes are split over `num_devices` local devices (default: as many as divide the
    episode count evenly; see `snac_jax.devices`). Every episode has its own key, so the
    outcomes do not depend on the number of devices. Every episode's state lives on the device
    at once: a count whose estimated memory exceeds the device's is refused before anything runs.
    """
    env.check_params(params)
    indices = np.asarray(design_indices)
    if indices.ndim != 1 or not np.issubdtype(indices.dtype, np.integer):
        raise ValueError(f"design_indices must be a 1-D array of ints, got {indices.dtype}{list(indices.shape)}")
    check_range("design_indices", indices, 0, params.designs.shape[0] - 1)
    num_episodes = indices.shape[0]
    require_episode_memory(env, params, policy, num_episodes)
    design_indices = jnp.asarray(indices, jnp.int32)
    keys = _episode_keys(key, num_episodes)
    mesh = devices.env_mesh(num_devices, num_envs=num_episodes)
    if mesh.devices.size == 1:
        return _run_episodes(env, policy.init, policy.act, policy.params, params, keys, design_indices)
    devices.check_divisible(num_episodes, mesh)
    return _run_episodes_sharded(env, policy.init, policy.act, policy.params, params, keys, design_indices, mesh)


def episode_bytes(env: SNACEnv, params: EnvParams, policy: Policy) -> int:
    """An upper bound of the device memory one episode of `run_episodes` holds: its state,
    observation, key and policy state, in the loop's carry, the step's copy and the select."""
    key = jax.random.key(0)
    obs, state = jax.eval_shape(env.reset_to_design, key, params, 0)
    policy_state = jax.eval_shape(policy.init, key, state.design)
    return 4 * memory.tree_bytes((obs, state, policy_state, jax.random.key_data(key)))


def require_episode_memory(env: SNACEnv, params: EnvParams, policy: Policy, num_episodes: int) -> None:
    """`ValueError` with the estimate if `num_episodes` episodes at once would not fit."""
    memory.require(
        f"{num_episodes:,} episodes at once",
        num_episodes * episode_bytes(env, params, policy),
        "evaluate fewer episodes",
    )


def test_design_params(task_id: str, params: EnvParams) -> EnvParams:
    """`params` with its designs replaced by the ten test designs of a dynamic task (the
    stride distribution and step limit of `params` are kept)."""
    stack = np.stack([designs.fixed_design(name) for name in test_design_names(task_id)])
    fresh = make_params(stack, task_spec(task_id).dim)
    return params.replace(
        designs=fresh.designs, design_max_bricks=fresh.design_max_bricks, design_volume=fresh.design_volume
    )


# --- statistics --------------------------------------------------------------------------------


def _stats(values: np.ndarray) -> dict[str, Any]:
    return {
        "mean": float(np.mean(values)),
        "min": float(np.min(values)),
        "std": float(np.std(values, ddof=1)) if values.size > 1 else 0.0,
        "episodes": int(values.size),
    }


def summarize(strata: dict[str, np.ndarray]) -> dict[str, Any]:
    """Mean (of the equal-weight strata means), min, pooled std and the stratified 95% CI of the
    mean, from the final IoUs of each stratum (a design, or a 1D shape)."""
    means = [float(np.mean(v)) for v in strata.values()]
    variances = [float(np.var(v, ddof=1)) / v.size if v.size > 1 else 0.0 for v in strata.values()]
    mean = float(np.mean(means))
    half_width = Z_95 * math.sqrt(sum(variances)) / len(strata)
    pooled = np.concatenate(list(strata.values()))
    return {**_stats(pooled), "mean": mean, "ci95": [mean - half_width, mean + half_width]}


@dataclasses.dataclass
class TaskResult:
    """The protocol's numbers for one task (a paper column or one environment task)."""

    task: str
    mean: float
    min: float
    std: float
    ci95: list[float]
    episodes: int
    mean_length: float
    mean_bricks_used: float
    mean_return: float
    per_design: dict[str, dict[str, Any]]  # per test design (dynamic) or per shape (1d-static)
    seed: int
    wall_s: float  # compile + run, all environment tasks of this task

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_episodes(
        cls, task: str, strata: dict[str, np.ndarray], lengths, bricks_used, returns, seed: int, wall_s: float
    ) -> TaskResult:
        """The protocol's statistics from the final IoUs of each stratum (a design or a 1D
        shape) and the episodes' lengths, bricks and returns."""
        stats = summarize(strata)
        return cls(
            task=task,
            mean=stats["mean"],
            min=stats["min"],
            std=stats["std"],
            ci95=stats["ci95"],
            episodes=stats["episodes"],
            mean_length=float(np.mean(lengths)),
            mean_bricks_used=float(np.mean(bricks_used)),
            mean_return=float(np.mean(returns)),
            per_design={name: _stats(values) for name, values in strata.items()} if len(strata) > 1 else {},
            seed=seed,
            wall_s=wall_s,
        )


def _task_key(seed: int, env_task: str) -> jax.Array:
    # Each environment task has its own stream: a task's numbers do not depend on which other
    # tasks ran before it.
    return jax.random.fold_in(jax.random.key(seed), zlib.crc32(env_task.encode()))


def _episode_keys(key: jax.Array, num_episodes: int) -> jax.Array:
    # Episode i's key depends only on `key` and i, never on how the episodes are split over devices.
    return jax.random.split(key, num_episodes)


@dataclasses.dataclass(frozen=True)
class ProtocolEpisodes:
    """The episodes the protocol runs on one environment task (SPEC §8), before any policy acts.

    The per-episode arrays are built when read, so a caller can refuse a count too large for the
    device (`require_episode_memory` with `num_episodes`) before any of them is allocated."""

    params: Any  # the task's params; a dynamic task's designs replaced by its ten test designs
    names: tuple[str, ...]  # the design behind each design index: the test designs, or the task itself
    episodes_per_design: int
    key: jax.Array  # the task's key: `run_episodes(..., key, design_indices)` draws `keys` from it

    @property
    def num_episodes(self) -> int:
        return len(self.names) * self.episodes_per_design

    @property
    def design_indices(self) -> np.ndarray:
        """int32 (episodes,), design-major: every episode of design 0 first."""
        return np.repeat(np.arange(len(self.names), dtype=np.int32), self.episodes_per_design)

    @property
    def keys(self) -> jax.Array:
        """(episodes,): episode i's key, the one `run_episodes` gives it."""
        return _episode_keys(self.key, self.num_episodes)


def protocol_episodes(
    env_task: str,
    params,
    seed: int,
    static_episodes: int = STATIC_EPISODES,
    episodes_per_test_design: int = EPISODES_PER_TEST_DESIGN,
) -> ProtocolEpisodes:
    """The designs and keys of the protocol's episodes on `env_task` with evaluation key `seed`,
    `params` being the task's as `make` built them (the single robot's `EnvParams` or a team's).

    The one statement of which episodes the protocol runs: `evaluate_task` and anything that runs
    the protocol's episodes another way (a team, a tally of what the policy does on the way) draw
    them here, so they see the same episodes with the same keys. `env_task` is an environment task
    (not a paper group such as `1d-static`; `environment_tasks` expands those)."""
    check_protocol_args(static_episodes, episodes_per_test_design, seed, {})
    if task_spec(env_task).dynamic:
        setup = test_design_params(env_task, params), tuple(test_design_names(env_task)), episodes_per_test_design
    else:
        setup = params, (env_task,), static_episodes
    return ProtocolEpisodes(*setup, key=_task_key(seed, env_task))


def check_protocol_args(static_episodes, episodes_per_test_design, seed, overrides) -> None:
    """The protocol's counts, key and overrides, checked before anything is built: one-line
    `ValueError`s naming what is allowed (shared by the single robot's and the team's protocol)."""
    for name, count in (("static_episodes", static_episodes), ("episodes_per_test_design", episodes_per_test_design)):
        if not isinstance(count, (int, np.integer)) or isinstance(count, bool) or count < 1:
            raise ValueError(f"{name} must be an int >= 1, got {count!r}")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed must be an int in 0..{MAX_SEED}, got {seed!r}")
    if "test_design" in overrides:
        raise ValueError(
            "test_design pins one design, but the protocol scores a dynamic task on all ten of its "
            "test designs (a static task has none): leave it out"
        )


def evaluate_task(
    task: str,
    policy: PolicyLike,
    *,
    static_episodes: int = STATIC_EPISODES,
    episodes_per_test_design: int = EPISODES_PER_TEST_DESIGN,
    seed: int = TUNING_EVAL_SEED,
    num_devices: int | None = None,
    **overrides: Any,
) -> TaskResult:
    """Score `policy` on `task` (a paper column such as `1d-static`, or an environment task id)
    with the protocol of SPEC §8. `overrides` go to `snac_jax.make` (e.g. `gps=True`); a
    dynamic task's test designs replace its training designs (so `test_design`, which would
    pin one, is refused). `num_devices`: see `run_episodes` (the numbers do not depend on it).

    A policy that takes an action outside the task's actions (the env would clamp it to a valid
    one: a policy built for another task) is refused with a `ValueError`, not scored."""
    env_tasks = environment_tasks(task)
    check_protocol_args(static_episodes, episodes_per_test_design, seed, overrides)
    start = time.perf_counter()
    strata: dict[str, np.ndarray] = {}
    outcomes: list[Episodes] = []
    for env_task in env_tasks:
        env, params = make(env_task, **overrides)
        episode_policy = policy if isinstance(policy, Policy) else policy(env)
        if not isinstance(episode_policy, Policy):
            raise ValueError(f"expected a Policy or a builder returning one, got {type(episode_policy).__name__}")
        setup = protocol_episodes(env_task, params, seed, static_episodes, episodes_per_test_design)
        require_episode_memory(env, setup.params, episode_policy, setup.num_episodes)
        result = jax.device_get(
            run_episodes(env, setup.params, episode_policy, setup.key, setup.design_indices, num_devices)
        )
        invalid = np.asarray(result.invalid_actions)
        if invalid.any():
            raise ValueError(
                f"policy {episode_policy.name!r} took {int(invalid.sum()):,} action(s) outside 0..{env.num_actions - 1} "
                f"in {int(np.count_nonzero(invalid))} of {invalid.size} episodes of {env_task}; the environment would "
                f"clamp them to valid ones, so they are not scored (a policy for a task with another action count?)"
            )
        outcomes.append(result)
        for index, name in enumerate(setup.names):
            strata[name] = np.asarray(result.iou[result.design_index == index], np.float64)
    wall_s = time.perf_counter() - start

    everything = jax.tree.map(lambda *xs: np.concatenate(xs), *outcomes)
    return TaskResult.from_episodes(
        task=task,
        strata=strata,
        lengths=everything.length,
        bricks_used=everything.bricks_used,
        returns=everything.episode_return,
        seed=seed,
        wall_s=wall_s,
    )
