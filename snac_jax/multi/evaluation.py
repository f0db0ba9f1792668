"""The evaluation protocol (SPEC §8) run by a team of robots in one world (SPEC §13).

The team's form of `snac_jax.evaluation.evaluate_task`: the same episodes per design, test
designs and key per environment task, in `snac_jax.multi.make(env_task, num_robots)`, so the IoU
and the episode length of a team compare with the single robot's and across team sizes. One
world, one design, one brick budget and one step limit hold for the whole team.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.evaluation import (
    EPISODES_PER_TEST_DESIGN,
    STATIC_EPISODES,
    TUNING_EVAL_SEED,
    TaskResult,
    check_protocol_args,
    environment_tasks,
    protocol_episodes,
)
from snac_jax.memory import require, tree_bytes
from snac_jax.multi.env import MultiSNACEnv, make
from snac_jax.multi.episodes import MultiPolicy, run_episode

TeamLike = MultiPolicy | Callable[[MultiSNACEnv], MultiPolicy]
"""A `MultiPolicy` used as is for every environment task, or a builder `team(env) -> MultiPolicy`
called once per environment task."""


@dataclasses.dataclass
class TeamResult:
    """The protocol's numbers of a team (`result`), with how many robots and how many of its
    episodes the env ended (brick budget spent or a robot stuck) rather than the step limit:
    whether a team finishes, beside how long it takes (`result.mean_length`)."""

    result: TaskResult
    robots: int
    max_steps: int
    finished_fraction: float  # episodes that ended terminated (on any step, the last one included), not truncated

    def to_json(self) -> dict[str, Any]:
        return {
            **self.result.to_json(),
            "robots": self.robots,
            "max_steps": self.max_steps,
            "finished_fraction": self.finished_fraction,
        }


@partial(jax.jit, static_argnames=("env", "init", "act"))
def _team_episodes(env, init, act, policy_params, env_params, keys, design_indices):
    # `init` and `act` are static, as in `snac_jax.evaluation`: new weights do not recompile.
    team = MultiPolicy(init, act, policy_params)
    return jax.vmap(lambda key, index: run_episode(env, team, key, index, env_params))(keys, design_indices)


def evaluate_team_task(
    task: str,
    team: TeamLike,
    num_robots: int,
    *,
    static_episodes: int = STATIC_EPISODES,
    episodes_per_test_design: int = EPISODES_PER_TEST_DESIGN,
    seed: int = TUNING_EVAL_SEED,
    **overrides: Any,
) -> TeamResult:
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
        setup = protocol_episodes(env_task, params, seed, static_episodes, episodes_per_test_design)
        params, names = setup.params, setup.names

        def one_episode(k):  # what one episode holds: its observations, world and policy state
            obs, state = env.reset_to_design(k, 0, params)
            return obs, state, policy.init(k, state.world.design)

        one = jax.eval_shape(one_episode, jax.random.key(0))
        require(
            f"{setup.num_episodes:,} team episodes at once",
            4 * setup.num_episodes * tree_bytes(one),
            "evaluate fewer episodes",
        )
        design_indices, keys = setup.design_indices, setup.keys
        episodes = jax.device_get(
            _team_episodes(env, policy.init, policy.act, policy.params, params, keys, jnp.asarray(design_indices))
        )
        outcomes.append(episodes)
        limits.append(int(params.max_steps_in_episode))
        for index, name in enumerate(names):
            strata[name] = np.asarray(episodes.iou[design_indices == index], np.float64)
    everything = jax.tree.map(lambda *xs: np.concatenate(xs), *outcomes)
    result = TaskResult.from_episodes(
        task=task,
        strata=strata,
        lengths=everything.length,
        bricks_used=everything.bricks_used,
        returns=everything.team_return,
        seed=seed,
        wall_s=time.perf_counter() - start,
    )
    finished = float(np.mean(np.asarray(everything.terminated)))
    return TeamResult(result=result, robots=num_robots, max_steps=max(limits), finished_fraction=finished)
