"""Several robots in one world (SPEC §13): one robot is the single-robot env, the collision and
shared-cell rules on hand-written steps, every robot's observation against a NumPy team engine
written from the spec, the JaxMARL dict API, compile-once, vmap, the handcrafted split, the
picture, and the refusal of a bad robot count."""

from __future__ import annotations

import subprocess
import sys
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.numpy_engine import MOVES, NumpyEnv
from snac_jax import TASKS, make, multi, tasks
from snac_jax.multi.episodes import stack
from snac_jax.replay import env_for_trace
from tests.conftest import golden_traces

ROOT = Path(__file__).parents[1]

SHORT = 40  # a step limit that ends (and auto-resets) several episodes in a short run


# --- one robot is the single-robot env -----------------------------------------------------------


@partial(jax.jit, static_argnames=("single", "team", "num_steps"))
def _both(key, single, params, team, num_steps):
    """The single env and the one-robot team, vmapped over 4 worlds, same keys and actions."""
    keys = jax.random.split(key, 4)
    obs_s, state_s = jax.vmap(single.reset, in_axes=(0, None))(keys, params)
    obs_m, state_m = jax.vmap(team.reset, in_axes=(0, None))(keys, params)

    def body(carry, key):
        state_s, state_m = carry
        key_action, key_step = jax.random.split(key)
        actions = jax.random.randint(key_action, (4,), 0, single.num_actions)
        step_keys = jax.random.split(key_step, 4)
        out_s = jax.vmap(single.step, in_axes=(0, 0, 0, None))(step_keys, state_s, actions, params)
        out_m = jax.vmap(team.step, in_axes=(0, 0, 0, None))(step_keys, state_m, {"agent_0": actions}, params)
        return (out_s[1], out_m[1]), (out_s, out_m)

    _, (out_s, out_m) = jax.lax.scan(body, (state_s, state_m), jax.random.split(key, num_steps))
    return (obs_s, state_s), (obs_m, state_m), out_s, out_m


def _small(task: str) -> dict:
    """A small bank for 2d-dynamic-dense (resets draw different designs; the other tests here use
    the same bank, built once); a pinned test design for the other dynamic tasks, whose bank
    generator would cost more to compile than the test itself."""
    return {"design_bank_size": 8} if task == "2d-dynamic-dense" else ({"test_design": 3} if "dynamic" in task else {})


FAMILIES = (
    "1d-static-sin",
    "1d-dynamic",
    "2d-static-dense",
    "2d-dynamic-dense",
    "3d-static-sparse",
    "3d-dynamic-dense",
)
"""One task of each dimension, static and dynamic, in the default run; every task with `-m slow`."""


@pytest.mark.slow
@pytest.mark.parametrize("task", [t if t in FAMILIES else pytest.param(t, marks=pytest.mark.slow) for t in TASKS])
def test_one_robot_equals_the_single_robot_env(task):
    overrides = {"max_steps": SHORT, **_small(task)}
    single, params = make(task, **overrides)
    team = multi.make(task, num_robots=1, **overrides)
    both = jax.device_get(_both(jax.random.key(3), single, params, team, 3 * SHORT))  # sliced in NumPy below
    (obs_s, state_s), (obs_m, state_m), out_s, out_m = both
    np.testing.assert_array_equal(obs_m["agent_0"], obs_s)
    np.testing.assert_array_equal(state_m.world.position[:, 0], state_s.position)
    obs, state, reward, terminated, truncated, info = out_s
    obs_t, state_t, rewards_t, dones_t, infos_t = out_m
    np.testing.assert_array_equal(obs_t["agent_0"], obs)
    np.testing.assert_array_equal(rewards_t["agent_0"], reward)
    np.testing.assert_array_equal(dones_t["agent_0"], terminated | truncated)
    np.testing.assert_array_equal(dones_t["__all__"], terminated | truncated)
    np.testing.assert_array_equal(infos_t["terminated"], terminated)
    np.testing.assert_array_equal(infos_t["truncated"], truncated)
    np.testing.assert_array_equal(infos_t["final_iou"], info["final_iou"])
    np.testing.assert_array_equal(infos_t["strides"][..., 0], info["stride"])
    np.testing.assert_array_equal(infos_t["final_observation"]["agent_0"], info["final_observation"])
    np.testing.assert_array_equal(state_t.world.grid, state.grid)
    np.testing.assert_array_equal(state_t.world.position[..., 0, :], state.position)
    assert np.any(truncated), "the run should cross the step limit"


def _replay_one(trace):
    single, params = env_for_trace(trace)
    team = multi.MultiSNACEnv(single, 1, params)
    assert team == multi.make(single.config.task_id, num_robots=1)  # the same compiled step
    out = multi.replay(team, np.asarray(trace["actions"])[:, None], np.asarray(trace["strides"])[:, None], params)
    expected = np.asarray(trace["observations"], dtype=np.float32)
    np.testing.assert_array_equal(out["observations"][:, 0, : expected.shape[1]], expected)
    np.testing.assert_array_equal(out["rewards"], np.asarray(trace["rewards"], dtype=np.float32))
    np.testing.assert_array_equal(out["terminated"] | out["truncated"], np.asarray(trace["dones"]))
    np.testing.assert_array_equal(out["final_grid"], np.asarray(trace["final_grid"]))
    assert out["final_iou"] == np.float32(trace["final_iou"])


def _ending(dim: int, how: str) -> dict:
    """The first golden trace of a dimension that ends by `how` ("budget", "stuck", "limit")."""
    for trace in golden_traces():
        if int(trace["dim"]) != dim or "dynamic" in trace["variant"]:
            continue
        steps, limit = len(trace["actions"]), int(trace["max_steps"])
        ends_by = "limit" if steps == limit else ("budget" if dim < 3 else "stuck")
        if ends_by == how:
            return trace
    raise AssertionError(f"no {dim}D golden trace ends by {how}")


@pytest.mark.parametrize("dim, how", [(1, "budget"), (2, "budget"), (3, "stuck")])
def test_golden_traces_replay_through_one_robot(dim, how):
    _replay_one(_ending(dim, how))


@pytest.mark.slow
def test_every_golden_trace_replays_through_one_robot():
    for trace in golden_traces():
        _replay_one(trace)


# --- the rules of several robots, on hand-written steps ------------------------------------------


def _placed(team, positions, **world):
    """A fresh state of `team` with the robots at `positions` and `world` fields replaced."""
    _, state = team.reset(jax.random.key(0))
    return state.replace(world=state.world.replace(position=jnp.asarray(positions, jnp.int32), **world))


@partial(jax.jit, static_argnums=0)
def _stepped(team, state, actions, strides):
    agents = team.agents
    return team.step_with_strides(state, dict(zip(agents, actions)), dict(zip(agents, strides)))


def _step(team, state, actions, strides):
    """`team.step_with_strides` with one action and stride per robot, jitted: one program per team
    configuration, not one per operation."""
    return _stepped(team, state, jnp.asarray(actions, jnp.int32), jnp.asarray(strides, jnp.int32))


@partial(jax.jit, static_argnums=0)
def _observed(team, state):
    """`team.get_obs(state)`, jitted: one program per team configuration, not one per operation."""
    return team.get_obs(state)


LEFT, RIGHT, DOWN, UP, DROP_2D = 0, 1, 2, 3, 4
DROP_LEFT, DROP_RIGHT, DROP_DOWN = 4, 5, 6  # neighbour drops (3D)


def _positions(state):
    return np.asarray(state.positions).tolist()


def test_two_robots_moving_into_one_cell_the_first_in_order_gets_it():
    team = multi.make("2d-static-dense", num_robots=2)
    _, after, *_ = _step(team, _placed(team, [[5, 5], [5, 7]]), [RIGHT, LEFT], [1, 1])
    assert _positions(after) == [[5, 6], [5, 7]]
    # In the other order of indices, robot 0 still moves first.
    _, after, *_ = _step(team, _placed(team, [[5, 7], [5, 5]]), [LEFT, RIGHT], [1, 1])
    assert _positions(after) == [[5, 6], [5, 5]]


def test_robots_never_pass_through_each_other():
    team = multi.make("2d-static-dense", num_robots=2)
    _, after, *_ = _step(team, _placed(team, [[5, 5], [5, 6]]), [RIGHT, LEFT], [3, 3])
    assert _positions(after) == [[5, 5], [5, 6]]
    _, after, *_ = _step(team, _placed(team, [[5, 5], [5, 8]]), [RIGHT, LEFT], [3, 3])
    assert _positions(after) == [[5, 7], [5, 8]]  # the earlier advances up to the other
    # A long move stops before the robot in its way, whatever its stride.
    _, after, *_ = _step(team, _placed(team, [[5, 0], [5, 2]]), [RIGHT, DROP_2D], [3, 1])
    assert _positions(after) == [[5, 1], [5, 2]]
    # A robot that moves first frees nothing for an earlier one: robot 0 is blocked, robot 1 moves.
    _, after, *_ = _step(team, _placed(team, [[5, 5], [5, 6]]), [RIGHT, RIGHT], [1, 1])
    assert _positions(after) == [[5, 5], [5, 7]]
    # ...but a robot later in the order moves into a cell an earlier one left.
    _, after, *_ = _step(team, _placed(team, [[5, 6], [5, 5]]), [RIGHT, RIGHT], [1, 1])
    assert _positions(after) == [[5, 7], [5, 6]]


def test_a_drop_onto_another_robot_does_nothing():
    team = multi.make("3d-static-dense", num_robots=2)
    state = _placed(team, [[5, 5], [5, 6]])
    _, after, rewards, dones, infos = _step(team, state, [DROP_RIGHT, DROP_LEFT], [1, 1])
    np.testing.assert_array_equal(after.world.grid, state.world.grid)
    assert int(after.world.bricks_used) == 0 and int(after.world.time) == 1
    np.testing.assert_array_equal(infos["robot_rewards"], [0.0, 0.0])
    assert not bool(dones["__all__"])
    # The same drops beside an empty cell land: the robot, not the cell, refused them.
    _, after, *_ = _step(team, _placed(team, [[5, 5], [5, 8]]), [DROP_RIGHT, DROP_LEFT], [1, 1])
    assert int(after.world.bricks_used) == 2


def test_team_reward_is_the_sum_given_to_every_robot():
    team = multi.make("2d-static-dense", num_robots=2)  # binary reward: +5 for a brick on the design
    _, after, rewards, _, infos = _step(team, _placed(team, [[8, 8], [0, 0]]), [DROP_2D, DROP_2D], [1, 1])
    np.testing.assert_array_equal(infos["robot_rewards"], [5.0, 0.0])  # (0, 0) is off the disk
    assert float(rewards["agent_0"]) == float(rewards["agent_1"]) == 5.0
    assert int(after.world.bricks_used) == 2 and int(after.world.time) == 1


def test_the_shared_budget_ends_the_episode_and_later_robots_do_not_act():
    team = multi.make("2d-static-dense", num_robots=2)
    state = _placed(team, [[8, 8], [9, 9]])
    state = state.replace(world=state.world.replace(bricks_used=state.world.max_bricks - 1))
    _, after, rewards, dones, infos = _step(team, state, [DROP_2D, DROP_2D], [1, 1])
    assert bool(dones["__all__"]) and bool(infos["terminated"]) and not bool(infos["truncated"])
    assert int(after.world.bricks_used) == int(state.world.max_bricks)
    pr, pc = team.config.pad
    assert int(after.world.grid[8 + pr, 8 + pc]) == 1 and int(after.world.grid[9 + pr, 9 + pc]) == 0
    np.testing.assert_array_equal(infos["robot_rewards"], [0.0, 0.0])  # the last brick earns 0 (SPEC §5)


def test_another_robot_blocks_but_never_makes_a_robot_stuck():
    team = multi.make("3d-static-dense", num_robots=2)
    pr, pc = team.config.pad
    state = _placed(team, [[0, 0], [0, 1]])
    grid = state.world.grid.at[1 + pr, 0 + pc].set(1)  # a brick below robot 0; walls left and above
    state = state.replace(world=state.world.replace(grid=grid))
    _, after, _, dones, _ = _step(team, state, [RIGHT, DROP_DOWN], [1, 1])
    assert not bool(dones["__all__"]) and _positions(after)[0] == [0, 0]
    # Now robot 0 is walled in by bricks and padding: stuck before its action, the episode ends,
    # and robot 1, after it in the order, does not act.
    grid = grid.at[0 + pr, 1 + pc].set(1)
    state = _placed(team, [[0, 0], [5, 5]], grid=grid)
    _, after, _, dones, infos = _step(team, state, [RIGHT, DROP_RIGHT], [1, 1])
    assert bool(dones["__all__"]) and bool(infos["terminated"])
    assert int(after.world.bricks_used) == 0 and _positions(after)[1] == [5, 5]


def test_each_window_shows_the_other_robots_as_minus_three():
    team = multi.make("2d-static-dense", num_robots=3, landmarks=2)
    state = _placed(team, [[5, 5], [5, 7], [7, 4]])
    state = state.replace(
        world=state.world.replace(landmarks=jnp.zeros_like(state.world.landmarks).at[5 + 3, 7 + 3].set(True))
    )
    obs = _observed(team, state)
    windows = {a: np.asarray(obs[a])[:49].reshape(7, 7) for a in team.agents}
    assert windows["agent_0"][3, 5] == -3 and windows["agent_0"][5, 2] == -3 and windows["agent_0"][3, 3] == 0
    assert windows["agent_0"][3, 5] == -3  # robot 1 stands on a landmark: others see the robot
    assert windows["agent_1"][3, 1] == -3 and windows["agent_1"][3, 3] == -2  # its own cell shows as before
    assert windows["agent_2"][1, 4] == -3 and windows["agent_2"][1, 6] == -3
    assert multi.ROBOT_VALUE == -3.0
    assert sum(int(np.sum(w == -3)) for w in windows.values()) == 6


# --- every robot's observation against a NumPy team engine --------------------------------------


class NumpyTeam:
    """SPEC §13 written out in Python on the plain NumPy engine (`bench/numpy_engine.py`): robots
    act in order, a move goes cell by cell and stops at the plan's edge, before another robot, and
    (obstacle rule) before a brick; a drop onto another robot does nothing; after the robot that
    ends the episode nobody acts; N_s counts team steps; windows show other robots as -3."""

    def __init__(self, task, num_robots, **overrides):
        self.env = NumpyEnv(task, **overrides)
        self.num_robots = num_robots
        self.blocked_moves = 0

    def reset(self, design, landmarks):
        env = self.env
        env.reset(design=design, landmarks=landmarks)
        rows, cols = (1, 30) if env.dim == 1 else (20, 20)
        self.positions = [(0, 0), (rows - 1, cols - 1), (0, cols - 1), (rows - 1, 0)][: self.num_robots]

    def _inside(self, r, c):
        return (r == 0 and 0 <= c < 30) if self.env.dim == 1 else (0 <= r < 20 and 0 <= c < 20)

    def _cell(self, r, c):
        ws = self.env.ws
        return self.env.grid[c + ws] if self.env.dim == 1 else self.env.grid[r + ws, c + ws]

    def step(self, actions, strides):
        env, time = self.env, self.env.time
        rewards, terminated = [0.0] * self.num_robots, False
        for i, (action, stride) in enumerate(zip(actions, strides)):
            if terminated:
                break
            r, c = self.positions[i]
            others = {p for j, p in enumerate(self.positions) if j != i}
            env.row, env.col = r, c
            stuck = env.obstacles and all(env.neighbours_blocked())
            is_move = action < (2 if env.dim == 1 else 4)
            if is_move:
                dr, dc = MOVES[action]
                for _ in range(stride):
                    nr, nc = r + dr, c + dc
                    if not self._inside(nr, nc) or (env.obstacles and self._cell(nr, nc) != 0):
                        break
                    if (nr, nc) in others:
                        self.blocked_moves += 1
                        break
                    r, c = nr, nc
                self.positions[i] = (r, c)
                terminated = stuck
                continue
            neighbour = env.dim == 3 or env.obstacles
            dr, dc = MOVES[action - 4] if neighbour else (0, 0)
            if (r + dr, c + dc) in others:
                terminated = stuck
                continue
            _, rewards[i], terminated, _, _ = env.step(action, stride=stride)
        env.time = time + 1
        return self.observations(), rewards, terminated, env.time >= env.max_steps

    def observations(self):
        env, ws, size = self.env, self.env.ws, 2 * self.env.ws + 1
        out = []
        for i, (r, c) in enumerate(self.positions):
            env.row, env.col = r, c
            obs = env.observation()
            window = obs[: size * size if env.dim > 1 else size].reshape((size, size) if env.dim > 1 else (1, size))
            for j, (rj, cj) in enumerate(self.positions):
                a, b = (0, cj + ws - c) if env.dim == 1 else (rj + ws - r, cj + ws - c)
                if j != i and 0 <= a < window.shape[0] and 0 <= b < window.shape[1]:
                    window[a, b] = -3
            out.append(obs)
        return np.stack(out)


@partial(jax.jit, static_argnames=("team", "num_steps"))
def _team_episodes(key, team, actions, positions, num_steps):
    """Random episodes from a reset with the robots moved to `positions`, then auto-reset."""
    _, state = team.reset(jax.random.key(1))
    state = state.replace(world=state.world.replace(position=positions))

    def body(state, inputs):
        step_key, acts = inputs
        obs, state, rewards, dones, infos = team.step(step_key, state, dict(zip(team.agents, acts)))
        marks = state.world.landmarks if state.world.landmarks is not None else jnp.zeros((), bool)
        return state, (
            stack(team, obs),
            infos["robot_rewards"],
            rewards["agent_0"],
            infos["terminated"],
            infos["truncated"],
            infos["strides"],
            stack(team, infos["final_observation"]),
            state.world.design,
            marks,
        )

    return state, jax.lax.scan(body, state, (jax.random.split(key, num_steps), actions))[1]


TEAM_CASES = [
    ("2d-static-dense", 4, {}),
    ("3d-static-sparse", 4, {}),
    ("1d-static-step", 2, {}),
    ("2d-dynamic-dense", 3, {"landmarks": 6, "gps": True, "design_bank_size": 8}),
    pytest.param("2d-static-sparse", 2, {"obstacles": True}, marks=pytest.mark.slow),
]


@pytest.mark.slow
@pytest.mark.parametrize(
    "task, num_robots, overrides",
    TEAM_CASES,
    ids=[
        "2d-static-dense-4",
        "3d-static-sparse-4",
        "1d-static-step-2",
        "2d-dynamic-dense-3",
        "2d-static-sparse-obstacles-2",
    ],
)
def test_every_robot_observes_as_the_numpy_team_engine(task, num_robots, overrides):
    """Random actions, each robot drifting toward the others so that they meet and block each
    other, a step limit that auto-resets several episodes; each JAX reset's design and landmarks
    go to the NumPy engine, the JAX env's strides are applied in both."""
    num_steps, max_steps = 300, 100
    team = multi.make(task, num_robots=num_robots, max_steps=max_steps, **overrides)
    numpy_overrides = {k: v for k, v in overrides.items() if k != "design_bank_size"}
    engine = NumpyTeam(task, num_robots, max_steps=max_steps, **numpy_overrides)
    rng = np.random.default_rng(0)
    actions = rng.integers(0, team.num_actions, (num_steps, num_robots))
    toward = (
        np.asarray([[1, 2], [0, 3], [0, 2], [1, 3]])[:num_robots] if team.config.dim > 1 else np.asarray([[1], [0]])
    )
    pull = rng.random((num_steps, num_robots)) < 0.5  # each robot drifts toward the others
    actions = np.where(
        pull, toward[np.arange(num_robots), rng.integers(0, toward.shape[1], (num_steps, num_robots))], actions
    )
    # The first episode starts with the robots in a 2x2 block, each in the corner of the block
    # that its start is in the plan, so that they soon meet; the later ones start from the corners.
    cluster = [(9, 9), (10, 10), (9, 10), (10, 9)][:num_robots] if team.config.dim > 1 else [(0, 13), (0, 16)]
    first, (obs, robot_rewards, team_reward, terminated, truncated, strides, final_obs, designs, marks) = (
        jax.device_get(  # indexed step by step below: in NumPy, not a dispatch per index
            _team_episodes(
                jax.random.key(7), team, jnp.asarray(actions, jnp.int32), jnp.asarray(cluster, jnp.int32), num_steps
            )
        )
    )
    _, start = team.reset(jax.random.key(1))
    plan = lambda mask: None if mask.ndim == 0 else np.asarray(mask)[3:-3, 3:-3]
    engine.reset(
        np.asarray(start.world.design),
        plan(start.world.landmarks if start.world.landmarks is not None else jnp.zeros(())),
    )
    engine.positions = list(cluster)
    ends = 0
    for t in range(num_steps):
        where = f"{task} step {t}"
        got_obs, got_rewards, got_terminated, got_truncated = engine.step(actions[t], np.asarray(strides[t]))
        np.testing.assert_array_equal(np.asarray(final_obs[t]), got_obs, err_msg=where)
        np.testing.assert_array_equal(np.asarray(robot_rewards[t]), got_rewards, err_msg=where)
        assert float(team_reward[t]) == sum(got_rewards), where
        assert (bool(terminated[t]), bool(truncated[t])) == (got_terminated, got_truncated), where
        if got_terminated or got_truncated:
            ends += 1
            engine.reset(np.asarray(designs[t]), plan(marks[t]))
        np.testing.assert_array_equal(np.asarray(obs[t]), engine.observations(), err_msg=where)
    assert ends >= 2, ends
    # The robots met and blocked each other (with the obstacle rule their own bricks soon keep
    # them apart; the hand-written tests above cover that case).
    assert engine.blocked_moves > 0 or team.config.obstacles


# --- the API -------------------------------------------------------------------------------------


@pytest.mark.slow
def test_dict_keys_dones_all_and_spaces():
    team = multi.make("3d-static-dense", num_robots=4)
    assert team.agents == ["agent_0", "agent_1", "agent_2", "agent_3"] and team.num_agents == 4
    obs, state = team.reset(jax.random.key(0))
    obs, state, rewards, dones, infos = team.step(jax.random.key(1), state, {a: 0 for a in team.agents})
    assert set(obs) == set(rewards) == set(team.agents) and set(dones) == {*team.agents, "__all__"}
    assert infos["strides"].shape == infos["robot_rewards"].shape == (4,)
    assert set(team.get_avail_actions(state)) == set(team.agents)
    assert all(bool(np.all(v)) and v.shape == (8,) for v in team.get_avail_actions(state).values())
    for agent in team.agents:
        assert team.action_space(agent).n == 8
        space = team.observation_space(agent)
        assert bool(space.contains(obs[agent])) and float(space.low[0]) == -3.0 and float(space.low[24]) == 0.0
    single, params = make("3d-static-dense")
    one = multi.make("3d-static-dense")
    np.testing.assert_array_equal(one.observation_space("agent_0").low, single.observation_space(params).low)
    with pytest.raises(ValueError, match=r"unknown agent 'agent_4'; agents: agent_0, agent_1, agent_2, agent_3"):
        team.observation_space("agent_4")
    with pytest.raises(
        ValueError, match=r"actions must be a dict keyed by \['agent_0', 'agent_1', 'agent_2', 'agent_3'\]"
    ):
        team.step(jax.random.key(1), state, {"agent_0": 0})
    with pytest.raises(ValueError, match=r"actions\['agent_1'\] must be one int in 0..7, got a traced float32"):
        team.step(jax.random.key(1), state, {"agent_0": 0, "agent_1": 2.0, "agent_2": 0, "agent_3": 0})
    # Known values are checked where the step is not compiled (as `SNACEnv.step_with_stride`).
    with pytest.raises(ValueError, match=r"actions\['agent_1'\] must be in 0..7, got 8"):
        team.step_env(jax.random.key(1), state, {"agent_0": 0, "agent_1": 8, "agent_2": 0, "agent_3": 0})


def test_step_auto_resets_every_robot_on_all():
    team = multi.make("2d-static-dense", num_robots=2, max_steps=2)
    obs0, state = team.reset(jax.random.key(0))
    acts = {"agent_0": 1, "agent_1": 0}
    _, state, _, dones, _ = team.step(jax.random.key(1), state, acts)
    assert not bool(dones["__all__"])
    obs, state, _, dones, infos = team.step(jax.random.key(2), state, acts)
    assert bool(dones["__all__"]) and bool(infos["truncated"])
    assert int(state.world.time) == 0 and _positions(state) == [[0, 0], [19, 19]]
    for agent in team.agents:
        np.testing.assert_array_equal(obs[agent], obs0[agent])
        assert not np.array_equal(infos["final_observation"][agent], obs0[agent])


def test_step_compiles_once_per_configuration():
    """Equal configurations share one compiled step, and each env's own default params are used
    (they are arguments of the compiled step, not constants of whichever env compiled it)."""
    first = multi.make("2d-static-sparse", num_robots=2, gps=True, max_steps=3)
    second = multi.make("2d-static-sparse", num_robots=2, gps=True, max_steps=1)
    assert first == second and hash(first) == hash(second) and first != multi.make("2d-static-sparse", num_robots=3)
    _, state = first.reset(jax.random.key(0))
    before = multi.MultiSNACEnv._step._cache_size()
    for i, env in enumerate((first, second, first)):
        _, _, _, dones, _ = env.step(jax.random.key(i), state, {"agent_0": i % 5, "agent_1": jnp.asarray(3)})
        assert bool(dones["__all__"]) == (env is second)
    assert multi.MultiSNACEnv._step._cache_size() - before == 1


def test_spaces_are_built_inside_jit_with_several_robots():
    """JaxMARL's baselines ask for the spaces inside their jitted `train`; the team's lower bounds
    (other robots showing as ROBOT_VALUE) are the same there as outside."""
    team = multi.make("2d-static-dense", num_robots=2)
    outside = team.observation_space("agent_1")

    @jax.jit
    def spaces_inside():
        space = team.observation_space("agent_1")
        return space.low, space.high, jnp.zeros(space.shape), team.action_space("agent_0").n

    low, high, zeros, n = spaces_inside()
    np.testing.assert_array_equal(low, outside.low)
    np.testing.assert_array_equal(high, outside.high)
    assert zeros.shape == outside.shape and int(n) == team.num_actions
    assert float(low.min()) == multi.ROBOT_VALUE


@pytest.mark.slow
def test_actions_of_shape_one_are_one_action():
    """A baseline's per-agent action of shape (1,) steps as the same action of shape ()."""
    team = multi.make("2d-static-dense", num_robots=2)
    _, state = team.reset(jax.random.key(0))
    key = jax.random.key(1)
    scalar = team.step(key, state, {"agent_0": jnp.int32(4), "agent_1": jnp.int32(2)})
    vector = team.step(key, state, {"agent_0": jnp.array([4], jnp.int32), "agent_1": jnp.array([2], jnp.int32)})
    for got, expected in zip(jax.tree.leaves(vector), jax.tree.leaves(scalar)):
        np.testing.assert_array_equal(got, expected)
    with pytest.raises(ValueError, match=r"actions\['agent_0'\] must be one int in 0..4, got a traced int32\[2\]"):
        team.step(key, state, {"agent_0": jnp.array([4, 4]), "agent_1": 2})


def test_step_takes_jaxmarls_reset_state_and_params_by_keyword_or_position():
    """JaxMARL's `step(key, state, actions, reset_state)`: an ended episode continues from
    `reset_state`. Params go by keyword, or (gymnax's order) as the fourth argument."""
    team = multi.make("2d-static-dense", num_robots=2, max_steps=1)
    _, state = team.reset(jax.random.key(0))
    _, chosen = team.reset(jax.random.key(7))
    chosen = chosen.replace(world=chosen.world.replace(position=jnp.array([[3, 4], [5, 6]])))
    acts = {"agent_0": 1, "agent_1": 0}
    obs, reset, _, dones, _ = team.step(jax.random.key(1), state, acts, chosen)
    assert bool(dones["__all__"]) and _positions(reset) == [[3, 4], [5, 6]]
    for agent, expected in _observed(team, chosen).items():
        np.testing.assert_array_equal(obs[agent], expected)
    longer = multi.make("2d-static-dense", num_robots=2, max_steps=5).default_params
    by_keyword = team.step(jax.random.key(1), state, acts, params=longer)
    by_position = team.step(jax.random.key(1), state, acts, longer)
    assert not bool(by_keyword[3]["__all__"])
    for got, expected in zip(jax.tree.leaves(by_position), jax.tree.leaves(by_keyword)):
        np.testing.assert_array_equal(got, expected)
    with pytest.raises(ValueError, match="step got params twice"):
        team.step(jax.random.key(1), state, acts, longer, params=longer)
    with pytest.raises(ValueError, match="reset_state must be a MultiState or None, got dict"):
        team.step(jax.random.key(1), state, acts, {"agent_0": 0})


@pytest.mark.slow
def test_import_snac_jax_reaches_multi_without_importing_it_first():
    """`snac_jax.multi.make` after a bare `import snac_jax`, which itself imports neither JAX nor
    the multi-robot package (they load on first use)."""
    code = (
        "import sys, snac_jax\n"
        "assert 'jax' not in sys.modules and 'snac_jax.multi' not in sys.modules\n"
        "assert 'multi' in dir(snac_jax)\n"
        "env = snac_jax.multi.make('2d-static-dense', num_robots=2)\n"
        "print(type(env).__name__, env.agents)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "MultiSNACEnv ['agent_0', 'agent_1']"


@pytest.mark.slow
def test_vmap_over_worlds_equals_each_world_alone():
    team = multi.make("2d-dynamic-dense", num_robots=2, design_bank_size=8)
    keys = jax.random.split(jax.random.key(0), 2048)
    obs, states = jax.jit(jax.vmap(team.reset))(keys)
    actions = {a: jax.random.randint(jax.random.key(i), (2048,), 0, 5) for i, a in enumerate(team.agents)}
    out = jax.jit(jax.vmap(team.step))(keys, states, actions)
    pick_world = jax.jit(lambda tree, world: jax.tree.map(lambda x: x[world], tree))  # not a program per leaf
    for world in (0, 1234):
        pick = lambda tree: pick_world(tree, world)
        alone = team.step(keys[world], pick(states), pick(actions))
        for got, expected in zip(jax.tree.leaves(pick(out)), jax.tree.leaves(alone)):
            np.testing.assert_array_equal(got, expected)
    assert len({np.asarray(d).tobytes() for d in states.world.design[:64]}) > 1  # designs differ per world


@pytest.mark.parametrize("bad", [0, -1, 2.5, True, np.bool_(False), "2", 5, None])
def test_a_bad_robot_count_is_refused_in_one_line_before_anything_is_built(bad, monkeypatch):
    monkeypatch.setattr(tasks, "make", lambda *a, **k: pytest.fail("built before num_robots was checked"))
    with pytest.raises(ValueError) as caught:
        multi.make("2d-dynamic-dense", num_robots=bad)
    message = str(caught.value)
    assert "\n" not in message and message.startswith("num_robots must be an int in 1..4 for 2d-dynamic-dense")
    assert repr(bad) in message
    with pytest.raises(
        ValueError, match=r"num_robots must be an int in 1..2 for 1d-dynamic \(one per end of the row\), got 3"
    ):
        multi.make("1d-dynamic", num_robots=3)


# --- the handcrafted split -----------------------------------------------------------------------


def test_plan_shares_are_the_spec_table():
    from snac_jax.policies.split import plan_shares

    config_2d = multi.make("2d-static-dense").config
    rows, cols = np.indices((20, 20))
    two = plan_shares(config_2d, 2)
    np.testing.assert_array_equal(two[0], rows + cols <= 19)
    three = plan_shares(config_2d, 3)
    np.testing.assert_array_equal(three[2], (rows <= 9) & (cols >= 10))
    np.testing.assert_array_equal(three[0], (rows + cols <= 19) & ~three[2])
    four = plan_shares(config_2d, 4)
    for robot, (r, c) in enumerate([(0, 0), (10, 10), (0, 10), (10, 0)]):
        assert four[robot, r : r + 10, c : c + 10].all() and four[robot].sum() == 100
    one_d = plan_shares(multi.make("1d-static-sin").config, 2)
    np.testing.assert_array_equal(one_d[0, 0], np.arange(30) <= 14)
    for shares in (two, three, four, one_d):
        np.testing.assert_array_equal(shares.sum(axis=0), 1)  # disjoint, and they cover the plan


@pytest.mark.slow
def test_each_robot_builds_its_share_of_a_hand_written_design():
    """Two design cells, one in each robot's share, no stride noise: each robot walks to its own
    cell and builds it; neither builds the other's (each was given only its share)."""
    from snac_jax.policies.split import handcrafted_split

    design = np.zeros((1, 20, 20), np.int16)
    design[0, 2, 3] = design[0, 17, 16] = 1
    team = multi.make("2d-static-dense", num_robots=2, max_steps=60, stride_probs=(1, 0, 0))
    params = tasks.make_params(design, 2, stride_probs=(1, 0, 0), max_steps=60)
    policy = handcrafted_split(team)
    again = handcrafted_split(multi.make("2d-static-dense", num_robots=2))
    assert (policy.init, policy.act) == (again.init, again.act)  # compiled once per configuration
    np.testing.assert_array_equal(policy.params, [1, 0, 0])  # the robots' stride distribution: the env's
    np.testing.assert_allclose(again.params, [1 / 3] * 3)
    episode = jax.jit(lambda k: multi.run_episode(team, policy, k, 0, params))(jax.random.key(0))
    assert float(episode.iou) == 1.0 and int(episode.bricks_used) == 2 and int(episode.length) == 60
    states = jax.jit(policy.init)(jax.random.key(0), jnp.asarray(design[0]))  # one program, not one per op
    own = np.asarray(states.design)[:, 3:-3, 3:-3]
    assert own[0, 2, 3] == 1 and own[0, 17, 16] == 0 and own[1, 17, 16] == 1 and own[1, 2, 3] == 0
    np.testing.assert_array_equal(states.estimate, [[0, 0], [19, 19]])


def test_a_robot_of_the_team_localises_past_another_robot_in_view():
    """Robot 0 moves one cell right while robot 1, in its window, moves down: the cells showing
    robot 1 differ between the two windows. The team's localiser leaves them out and finds the one
    cell; the single robot's (SPEC §11), which compares them, finds no stride and keeps its
    estimate, one cell behind."""
    from snac_jax.policies.handcrafted import handcrafted_policy

    team = multi.make("2d-static-dense", num_robots=2)
    grid = np.zeros((26, 26), np.int16)
    grid[:3], grid[-3:], grid[:, :3], grid[:, -3:] = -1, -1, -1, -1
    for r, c in [(8, 7), (12, 10), (9, 12), (11, 6)]:  # a few bricks: one stride matches
        grid[r + 3, c + 3] = 1
    before = _placed(team, [[10, 8], [10, 11]], grid=jnp.asarray(grid))
    obs_before = np.asarray(stack(team, _observed(team, before)))
    after = _step(team, before, [RIGHT, DOWN], [1, 1])[1]
    np.testing.assert_array_equal(after.positions, [[10, 9], [11, 11]])
    obs_after = np.asarray(stack(team, _observed(team, after)))
    window_before = obs_before[0, :49].reshape(7, 7)
    assert float(window_before[3, 6]) == multi.ROBOT_VALUE and float(obs_after[0, 4 * 7 + 5]) == multi.ROBOT_VALUE

    def estimate(policy):
        @jax.jit  # one program per policy, not one per operation
        def act(design, window, obs):
            state = policy.init(jax.random.key(0), design).replace(
                estimate=jnp.asarray([10, 8], jnp.int32), last_action=jnp.asarray(RIGHT, jnp.int32), last_window=window
            )
            return policy.act(policy.params, state, obs, jax.random.key(1))[1].estimate

        return tuple(np.asarray(act(before.world.design, window_before, obs_after[0])))

    assert estimate(handcrafted_policy(team.single, team=True)) == (10, 9)
    assert estimate(handcrafted_policy(team.single)) == (10, 8)
    assert handcrafted_policy(team.single, team=True) is not handcrafted_policy(team.single)


@pytest.mark.parametrize(
    "probs, expected", [((1, 0, 0), 1), ((1 / 3, 1 / 3, 1 / 3), 2), ((0.5, 0.5, 0), 1), ((0.2, 0.2, 0.6), 3)]
)
def test_the_odometry_stride_is_the_median_stride(probs, expected):
    from snac_jax.policies.handcrafted import odometry_stride

    assert int(odometry_stride(jnp.asarray(probs, jnp.float32))) == expected


@pytest.mark.parametrize("probs, team_counts", [((1 / 3, 1 / 3, 1 / 3), 2), ((1, 0, 0), 1)])
def test_a_robot_of_the_team_counts_the_median_stride_across_a_featureless_stretch(probs, team_counts):
    """Robot 0 moves right across empty ground, no wall or brick in view: every stride explains
    its new window. The single robot counts one cell (SPEC §11); a robot of the team the median
    of the env's strides, so with strides 1-3 equally likely it does not fall behind by a cell
    on two moves in three."""
    from snac_jax.policies.handcrafted import handcrafted_policy

    team = multi.make("2d-dynamic-dense", num_robots=2, stride_probs=probs, test_design=0)
    grid = np.zeros((26, 26), np.int16)
    grid[:3], grid[-3:], grid[:, :3], grid[:, -3:] = -1, -1, -1, -1
    before = _placed(team, [[16, 8], [19, 19]], grid=jnp.asarray(grid))
    after = _step(team, before, [RIGHT, UP], [3, 1])[1]
    window_before, obs_after = (
        np.asarray(stack(team, _observed(team, before)))[0, :49].reshape(7, 7),
        np.asarray(stack(team, _observed(team, after)))[0],
    )
    assert np.all(window_before == 0) and np.all(obs_after[:49] == 0)

    def estimate(policy):
        @jax.jit  # one program per policy, not one per operation
        def act(design, window, obs):
            state = policy.init(jax.random.key(0), design).replace(
                estimate=jnp.asarray([16, 8], jnp.int32), last_action=jnp.asarray(RIGHT, jnp.int32), last_window=window
            )
            return policy.act(policy.params, state, obs, jax.random.key(1))[1].estimate

        return tuple(np.asarray(act(before.world.design, window_before, obs_after)))

    assert estimate(handcrafted_policy(team.single, team=True)) == (16, 8 + team_counts)
    assert estimate(handcrafted_policy(team.single)) == (16, 9)


@pytest.mark.slow
def test_one_robot_of_the_split_is_the_single_robot_policy_unchanged():
    """What one robot of the split scores is a reference row (bench/results/multi.md): these are
    its episodes as main scored them before the team's localiser changed (IoU, length)."""
    from snac_jax.policies.team import team_policy

    pinned = {
        "2d-static-dense": ([0.93464, 0.89744, 0.97333], [461, 447, 474]),
        "2d-dynamic-dense": ([0.91398, 0.95604, 0.87368], [274, 287, 283]),
    }
    for task, (ious, lengths) in pinned.items():
        env = multi.make(task, num_robots=1, **({"test_design": 4} if "dynamic" in task else {}))
        policy = team_policy("handcrafted", env)
        assert policy.params is None
        out = jax.jit(jax.vmap(lambda k: multi.run_episode(env, policy, k)))(jax.random.split(jax.random.key(11), 3))
        np.testing.assert_allclose(np.asarray(out.iou), ious, atol=1e-5)
        np.testing.assert_array_equal(np.asarray(out.length), lengths)


# --- whole episodes: the recording and the protocol's finish ------------------------------------


@pytest.mark.slow
def test_a_recorded_episode_is_the_episode_run_episode_scores():
    """`record_team_episode` and `run_episode` share one step and one key schedule: from the same
    key on a static task (one design, so `reset` and `reset_to_design(0)` agree) the random team,
    which draws its actions and strides from the keys, takes the same steps to the same end."""
    from snac_jax.multi.episodes import record_team_episode
    from snac_jax.policies.team import team_policy

    env = multi.make("2d-static-dense", num_robots=2, max_steps=SHORT)
    params, team = env.default_params, team_policy("random", env)
    run = jax.jit(lambda k: multi.run_episode(env, team, k, 0, params))
    for seed in range(3):
        key = jax.random.key(seed)
        recorded, scored = record_team_episode(env, params, team, key), run(key)
        assert recorded.length == int(scored.length) and recorded.terminated == bool(scored.terminated)
        assert recorded.final_iou == float(scored.iou)
        assert int(recorded.state_at(-1).world.bricks_used) == int(scored.bricks_used)
        np.testing.assert_allclose(recorded.rewards.sum(), float(scored.team_return), rtol=1e-6)
        assert (
            recorded.actions.shape == (recorded.length, 2) and int(recorded.state_at(-1).world.time) == recorded.length
        )


_ALWAYS_DROP = multi.MultiPolicy(
    init=lambda key, design: jnp.zeros(()),
    act=lambda params, state, obs, key: (jnp.full(obs.shape[0], 2, jnp.int32), state),
    name="always-drop",
)
"""Every robot drops a brick every step (action 2 in 1D), each onto its own column."""


@pytest.mark.parametrize("max_steps, finished", [(301, 1.0), (300, 1.0), (299, 0.0)])
def test_finished_episodes_are_the_terminated_ones_the_last_step_included(max_steps, finished):
    """1d-static-sin's budget is 600 bricks; two robots always dropping spend two a step, so the
    budget runs out on step 300. With a limit of 300 the episode terminates on its last allowed
    step (terminated and truncated at once) and counts as finished, as with a limit of 301; with
    299 the limit truncates it, 598 bricks spent, and it counts as unfinished."""
    assert int(multi.make("1d-static-sin", num_robots=2).default_params.design_max_bricks[0]) == 600
    team = multi.evaluate_team_task("1d-static-sin", _ALWAYS_DROP, 2, static_episodes=2, max_steps=max_steps)
    length = min(max_steps, 300)
    assert team.finished_fraction == finished and team.max_steps == max_steps
    assert team.result.mean_length == length and team.result.mean_bricks_used == 2 * length
    assert team.to_json()["finished_fraction"] == finished


# --- the picture ---------------------------------------------------------------------------------


@pytest.mark.parametrize("task, num_robots", [("1d-static-sin", 2), ("2d-static-dense", 4), ("3d-static-sparse", 3)])
def test_each_robot_is_drawn_in_its_colour(task, num_robots):
    from snac_jax.rendering import ROBOT, ROBOT_COLOURS, render, world_layout

    team = multi.make(task, num_robots=num_robots)
    state = _placed(team, multi.start_positions(team.config, num_robots))
    frame = team.render(state, caption=False)
    single_frame = render(team.single, state.world.replace(position=state.positions[0]), caption=False)
    assert frame.shape == single_frame.shape and ROBOT_COLOURS[0] == ROBOT
    layout = world_layout(team.single, caption_lines=0)
    (pr, pc) = team.config.pad
    for robot, (r, c) in enumerate(np.asarray(state.positions)):
        centre = layout.robot_center(c + pc) if team.config.dim == 1 else layout.cell_center(r + pr, c + pc)
        assert tuple(frame[centre]) == ROBOT_COLOURS[robot], robot
    assert len(set(ROBOT_COLOURS)) == 4


# --- the throughput bench ------------------------------------------------------------------------


@pytest.mark.slow
def test_multi_throughput_bench_writes_its_table_under_out(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "bench" / "multi_throughput.py"
    done = subprocess.run(
        [
            sys.executable,
            str(script),
            "--quick",
            "--tasks",
            "1d-static-sin",
            "--robots",
            "1",
            "2",
            "4",
            "--out",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    rows = json.loads((tmp_path / "multi_throughput.json").read_text())["rows"]
    assert [r["env"] for r in rows] == ["single", "multi N=1", "multi N=2"]  # 1D holds two robots
    assert all(r["robot_steps_per_s"] == r["env_steps_per_s"] * r["num_robots"] for r in rows)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["multi_throughput.json", "multi_throughput.md"]
