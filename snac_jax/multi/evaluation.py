"""The evaluation protocol (SPEC §8) run by a team of robots in one world (SPEC §13).

The team's form of `snac_jax.evaluation.evaluate_task`: the same episodes per design, test
designs and key per environment task, in `snac_jax.multi.make(env_task, num_robots)`, so the IoU
and the episode length of a team compare with the single robot's and across team sizes. One
world, one design, one brick budget and one step limit hold for the whole team.
"""

from __future__ import annotations

import dataclasses
import time
from functools import partial
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.evaluation import (
    EPISODES_PER_TEST_DESIGN,
    STATIC_EPISODES,
    TUNING_EVAL_SEED,
    TaskResult,
    _task_key,
    check_protocol_args,
    environment_tasks,
    test_design_params,
)
from snac_jax.memory import require, tree_bytes
from snac_jax.multi.env import MultiSNACEnv, make
from snac_jax.multi.episodes import MultiPolicy, run_episode
from snac_jax.tasks import task_spec, test_design_names

TeamLike = MultiPolicy | Callable[[MultiSNACEnv], MultiPolicy]
"""A `MultiPolicy` used as is for every environment task, or a builder `team(env) -> MultiPolicy`
called once per environment task."""


@dataclasses.dataclass
class TeamResult:
    """The protocol's numbers of a team (`result`), with how many robots and how many of its
    episodes ended before the step limit (brick budget spent or a robot stuck): whether a team
    finishes, beside how long it takes (`result.mean_length`)."""

    result: TaskResult
    robots: int
    max_steps: int
    finished_fraction: float  # episodes with length < max_steps

    def to_json(self) -> dict[str, Any]:
        return {**self.result.to_json(), "robots": self.robots, "max_steps": self.max_steps,
                "finished_fraction": self.finished_fraction}


@partial(jax.jit, static_argnames=("env", "init", "act"))
def _team_episodes(env, init, act, policy_params, env_params, keys, design_indices):
    # `init` and `act` are static, as in `snac_jax.evaluation`: new weights do not recompile.
    team = MultiPolicy(init, act, policy_params)
    return jax.vmap(lambda key, index: run_episode(env, team, key, index, env_params))(keys, design_indices)


def evaluate_team_task(task: str, team: TeamLike, num_robots: int, *, static_episodes: int = STATIC_EPISODES,
                       episodes_per_test_design: int = EPISODES_PER_TEST_DESIGN, seed: int = TUNING_EVAL_SEED,
                       **overrides: Any) -> TeamResult:
    """SPEC §8's protocol run by a team of `num_robots` in `snac_jax.multi.make(env_task,
    num_robots, **overrides)`: the same episodes per design, test designs and key per environment
    task (`fold_in(key(seed), crc32(env task))`) as `snac_jax.evaluation.evaluate_task`, so with
    one robot and a policy that uses no randomness the episodes are the single robot's. The
    episodes run on one device."""
    check_protocol_args(static_episodes, episodes_per_test_design, seed, overrides)
    start, strata, outcomes, limits = time.perf_counter(), {}, [], []
    for env_task in environment_tasks(task):
        env = make(env_task, num_robots=num_robots, **overrides)
        params = env.default_params
        policy = team if isinstance(team, MultiPolicy) else team(env)
        if not isinstance(policy, MultiPolicy):
            raise ValueError(f"a team needs a snac_jax.multi.MultiPolicy, got {type(policy).__name__}")
        if task_spec(env_task).dynamic:
            params, names = test_design_params(env_task, params), test_design_names(env_task)
            design_indices = np.repeat(np.arange(len(names)), episodes_per_test_design).astype(np.int32)
        else:
            names, design_indices = [env_task], np.zeros(static_episodes, np.int32)

        def one_episode(k):  # what one episode holds: its observations, world and policy state
            obs, state = env.reset_to_design(k, 0, params)
            return obs, state, policy.init(k, state.world.design)

        one = jax.eval_shape(one_episode, jax.random.key(0))
        require(f"{design_indices.size:,} team episodes at once", 4 * design_indices.size * tree_bytes(one),
                "evaluate fewer episodes")
        keys = jax.random.split(_task_key(seed, env_task), design_indices.size)
        episodes = jax.device_get(_team_episodes(env, policy.init, policy.act, policy.params, params, keys,
                                                 jnp.asarray(design_indices)))
        outcomes.append(episodes)
        limits.append(np.full(design_indices.size, int(params.max_steps_in_episode)))
        for index, name in enumerate(names):
            strata[name] = np.asarray(episodes.iou[design_indices == index], np.float64)
    everything = jax.tree.map(lambda *xs: np.concatenate(xs), *outcomes)
    limits = np.concatenate(limits)
    result = TaskResult.from_episodes(task=task, strata=strata, lengths=everything.length,
                                      bricks_used=everything.bricks_used, returns=everything.team_return,
                                      seed=seed, wall_s=time.perf_counter() - start)
    finished = float(np.mean(np.asarray(everything.length) < limits))
    return TeamResult(result=result, robots=num_robots, max_steps=int(limits.max()), finished_fraction=finished)
