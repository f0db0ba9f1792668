"""Several robots building one design together (SPEC §13), as a JaxMARL-shaped environment.

    from snac_jax import multi
    env = multi.make("2d-static-dense", num_robots=2)
    obs, state = env.reset(key)                                    # {"agent_0": ..., "agent_1": ...}
    obs, state, rewards, dones, infos = env.step(key, state, {"agent_0": 4, "agent_1": 0})

Modules: `rules` (the step of N robots and their observations, pure functions of one world),
`env` (`MultiSNACEnv` and `make`), `episodes` (a team policy's interface, one episode to its end,
replaying recorded actions and strides), `evaluation` (SPEC §8's protocol run by a team).
"""

from snac_jax.multi.env import MultiSNACEnv, MultiState, agent_names, check_num_robots, make
from snac_jax.multi.episodes import MultiPolicy, TeamEpisode, replay, run_episode
from snac_jax.multi.evaluation import TeamResult, evaluate_team_task
from snac_jax.multi.rules import ROBOT_VALUE, max_robots, start_positions

__all__ = [
    "ROBOT_VALUE",
    "MultiPolicy",
    "MultiSNACEnv",
    "MultiState",
    "TeamEpisode",
    "TeamResult",
    "agent_names",
    "check_num_robots",
    "evaluate_team_task",
    "make",
    "max_robots",
    "replay",
    "run_episode",
    "start_positions",
]
