"""`pqn-belief --brick-map` (agents/research/belief_map.py): the map's pieces by hand, the mapping filter
tracking real episodes when told the cells moved, the bricks' evidence making a vague move
reading sharper than the row and column filters alone, the learner wired to it, and the Q head
reading the map's unbuilt design (`todo_compass`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.research.belief_filter import filter_step, move_belief
from agents.research.belief_map import (
    WINDOW_NOISE,
    add_drop,
    brick_log_likelihood,
    drop_table,
    drop_target,
    mapping_filter_step,
    move_joint,
    remaining_compass,
    shifted,
)
from agents.research.drqn_aux import move_directions
from agents.research.pqn_belief import MappingBeliefQNetwork
from agents.training.registry import build_algorithm, make_config
from snac_jax.tasks import make
from tests.test_belief import TINY, random_episode_steps


def test_shifted_moves_a_grid_and_drops_what_leaves_the_plan():
    grid = jnp.zeros((1, 3, 3)).at[0, 1, 0].set(1.0)
    np.testing.assert_array_equal(shifted(grid, 0, 1)[0], np.eye(3)[[1]].T @ np.eye(3)[[1]])  # to (1, 1)
    np.testing.assert_array_equal(shifted(grid, 1, 0)[0, 2, 0], 1.0)  # to (2, 0)
    assert float(shifted(grid, 0, -1).sum()) == 0.0  # off the plan's left edge


def test_a_drop_lands_under_the_belief_on_its_target_and_a_move_drops_nothing():
    belief = jnp.zeros((1, 2, 3)).at[0, 0, 0].set(0.25).at[0, 1, 2].set(0.75)
    drops = ((0, 0, -1), (0, 0, 1), (1, 0, 0), (1, 0, 1))  # two moves, a drop on the own cell, one to the right
    none = len(drops)
    onehot = lambda a: jax.nn.one_hot(jnp.array([a]), none + 1)
    np.testing.assert_allclose(drop_target(belief, onehot(2), drops), belief)
    right = drop_target(belief, onehot(3), drops)[0]
    np.testing.assert_allclose(right, [[0, 0.25, 0], [0, 0, 0]])  # the 0.75 at the right edge drops off the plan
    assert (
        float(drop_target(belief, onehot(0), drops).sum()) == 0
        and float(drop_target(belief, onehot(none), drops).sum()) == 0
    )


def test_the_map_after_a_drop_by_hand():
    mean, var = jnp.array([0.5, 1.0]), jnp.array([0.25, 0.2])
    m, v = add_drop(mean, var, jnp.array([0.8, 0.5]), capped=True)  # 0/1 grid: the chance of a brick
    np.testing.assert_allclose(m, [0.8, 1.0])
    np.testing.assert_allclose(v, [0.16, 0.0])
    m, v = add_drop(mean, var, jnp.array([0.5, 0.5]), capped=False)  # counts: a Bernoulli(0.5) brick added
    np.testing.assert_allclose(m, [1.0, 1.5])
    np.testing.assert_allclose(v, [0.5, 0.45])


def test_drops_under_one_spread_belief_do_not_make_its_cells_certain():
    """Ten drops while the belief stays spread over four cells: the ten bricks went to one of them,
    so on the 0/1 grid each cell holds a brick with chance 1/4, not 1 - (3/4)^10."""
    belief = jnp.zeros((1, 2, 2)) + 0.25
    mean = var = jnp.zeros((1, 2, 2))
    for _ in range(10):
        mean, var = add_drop(mean, var, belief, capped=True)
    np.testing.assert_allclose(mean, 0.25)


def test_the_bricks_likelihood_by_hand():
    """A 3x3 plan with one sure brick at (0, 2), a 3x3 window showing a brick right of the robot.
    At (0, 1) the window matches the map: 0. At (1, 1) it shows a brick at (1, 2), where the map
    has none, and none at (0, 2), where it has one: two cells off by one, 2 / (2 * noise) each.
    Window cells showing padding or a landmark count nothing."""
    mean = jnp.zeros((1, 3, 3)).at[0, 0, 2].set(1.0)
    window = jnp.zeros((1, 3, 3)).at[0, 1, 2].set(1.0)
    window_at_top = window.at[0, 0, :].set(-1.0)  # what the robot at row 0 sees: padding above
    log_l = brick_log_likelihood(window_at_top, mean, jnp.zeros_like(mean))[0]
    assert float(log_l[0, 1]) == pytest.approx(0.0)
    log_l = brick_log_likelihood(window, mean, jnp.zeros_like(mean))[0]
    assert float(log_l[1, 1]) == pytest.approx(-2 / (2 * WINDOW_NOISE))
    landmark = window.at[0, 0, 2].set(-2.0)  # a landmark where the map's brick would show: no evidence there
    assert float(brick_log_likelihood(landmark, mean, jnp.zeros_like(mean))[0, 1, 1]) == pytest.approx(
        -1 / (2 * WINDOW_NOISE)
    )


@pytest.mark.parametrize("sign", [(0, 1), (0, -1), (1, 0), (-1, 0), (0, 0)])
def test_a_joint_move_moves_every_line_as_the_axis_filter_moves_one(sign):
    belief = jax.nn.softmax(jax.random.normal(jax.random.key(0), (4, 5 * 6))).reshape(4, 5, 6)
    p_cells = jax.nn.softmax(jax.random.normal(jax.random.key(1), (4, 4)))
    signs = jnp.tile(jnp.array([sign], jnp.float32), (4, 1))
    axis = 1 if sign[1] else 0
    lines = jnp.moveaxis(belief, 1 + (1 - axis), 1)  # (4, k, n): the lines along the moving axis
    expected = jax.vmap(lambda b, p, s: jax.vmap(lambda line: move_belief(line, p, s))(b))(
        lines, p_cells, signs[:, axis]
    )
    np.testing.assert_allclose(move_joint(belief, p_cells, signs), jnp.moveaxis(expected, 1, 1 + (1 - axis)), atol=1e-6)


def test_a_joint_move_by_hand():
    belief = jnp.zeros((1, 3, 4)).at[0, 1, 1].set(1.0)
    moved = move_joint(belief, jnp.array([[0.0, 0.5, 0.5, 0.0]]), jnp.array([[0.0, 1.0]]))[0]  # right by 1 or 2
    np.testing.assert_allclose(moved[1], [0, 0, 0.5, 0.5])
    moved = move_joint(belief, jnp.array([[0.0, 0.0, 0.0, 1.0]]), jnp.array([[-1.0, 0.0]]))[
        0
    ]  # up by 3: stops at row 0
    assert float(moved[0, 1]) == pytest.approx(1.0)


@pytest.mark.parametrize(
    "task, capped",
    [("2d-dynamic-sparse", True), ("3d-static-dense", False), ("3d-static-dense", True), ("1d-dynamic", False)],
)
def test_the_mapping_filter_tracks_real_episodes_when_told_the_cells_moved(task, capped):
    """Told the true cells moved, the joint belief is the robot's position at every step: the drops
    and moves of random episodes, auto-resets included, with the map of heights or, `capped`, of
    whether each cell holds a brick."""
    env, params = make(task, max_steps=40)
    moves = jnp.asarray(np.concatenate([move_directions(env.config), [(0, 0)]]), jnp.float32)
    drops, (rows, cols), worlds = drop_table(env.config), env.config.plan_shape, 16
    state = (jnp.zeros((worlds, rows, cols)),) * 3
    step = jax.jit(lambda s, *a: mapping_filter_step(s, *a, drops=drops, capped=capped))
    for t, (obs, _, reset, last_action, cells, position) in enumerate(random_episode_steps(env, params, worlds, 90)):
        window = env.observation_layout.window_cells(obs)
        state = step(
            state,
            reset,
            jax.nn.one_hot(cells, 4),
            moves[last_action],
            jax.nn.one_hot(last_action, env.num_actions + 1),
            window,
        )
        peak = state[0].reshape(worlds, -1).argmax(-1)
        np.testing.assert_array_equal(peak, position[:, 0] * cols + position[:, 1], err_msg=f"step {t}")
        assert float(state[0].reshape(worlds, -1).max(-1).min()) > 0.99


def test_the_bricks_make_a_vague_move_reading_sharper():
    """With a move reading that puts only half its mass on the true cells, the row and column
    filters can only use the plan's edges; the mapping filter also uses the bricks the robot laid.
    Over random episodes (a fifth of the actions drops) on a 2D plan, its belief holds the true position
    with a higher mean log-probability."""
    env, params = make("2d-dynamic-sparse", max_steps=60)
    moves = jnp.asarray(np.concatenate([move_directions(env.config), [(0, 0)]]), jnp.float32)
    drops, (rows, cols), worlds = drop_table(env.config), env.config.plan_shape, 32
    joint = (jnp.zeros((worlds, rows, cols)),) * 3
    rows_cols = (jnp.zeros((worlds, rows)), jnp.zeros((worlds, cols)))
    step_map = jax.jit(lambda s, *a: mapping_filter_step(s, *a, drops=drops, capped=True))
    step_axes = jax.jit(filter_step)
    log_p_map, log_p_axes = [], []
    for obs, _, reset, last_action, cells, position in random_episode_steps(env, params, worlds, 180):
        vague = 0.5 * jax.nn.one_hot(cells, 4) + 0.5 / 4
        window = env.observation_layout.window_cells(obs)
        joint = step_map(
            joint, reset, vague, moves[last_action], jax.nn.one_hot(last_action, env.num_actions + 1), window
        )
        rows_cols = step_axes(rows_cols, reset, vague, moves[last_action], window == -1)
        index = jnp.arange(worlds)
        log_p_map.append(jnp.log(joint[0][index, position[:, 0], position[:, 1]] + 1e-12))
        log_p_axes.append(jnp.log(rows_cols[0][index, position[:, 0]] * rows_cols[1][index, position[:, 1]] + 1e-12))
    gain = float(jnp.mean(jnp.stack(log_p_map)) - jnp.mean(jnp.stack(log_p_axes)))
    assert gain > 0.1, gain


def test_the_learner_trains_with_the_map_finite_and_compiled_once():
    config = make_config("pqn-belief", "3d-static-dense", **TINY, brick_map=True, max_steps=6)
    agent = build_algorithm(config)
    assert isinstance(agent.network, MappingBeliefQNetwork) and not agent.network.capped  # heights in 3D
    rows, cols = agent.env.config.plan_shape
    assert agent.network.carry_size == config.rnn_size + 3 * rows * cols
    traces, update = [], agent.update
    agent.update = lambda state, env_params: (traces.append(1), update(state, env_params))[1]
    chunk = jax.jit(lambda s, p: agent.train_chunk(s, p, 2))
    state = jax.jit(agent.init)(jax.random.key(0))
    for _ in range(2):
        state, metrics = chunk(state, agent.env_params)
        assert np.all(np.isfinite(metrics["loss"])) and np.all(np.isfinite(metrics["belief_nll"]))
    assert len(traces) == 1 and chunk._cache_size() == 1


def test_a_capped_map_reads_a_stack_as_one_brick():
    """`capped` (2D, or 3D with brick_occupancy): the window's count at a cell is read as whether
    it holds a brick, as the map keeps it, so a stack of three scores as one brick would; with
    heights it is three bricks where the map expects one."""
    config = make("3d-static-dense")[0].config
    drops, none = drop_table(config), jax.nn.one_hot(config.num_actions, config.num_actions + 1)[None]
    belief = jnp.full((1, 5, 5), 1 / 25)
    mean = jnp.zeros((1, 5, 5)).at[0, 2, 3].set(1.0)  # one sure brick, right of the plan's centre
    window = jnp.zeros((1, 3, 3))

    def corrected(count, capped):
        state = (belief, mean, jnp.zeros_like(mean))
        return mapping_filter_step(
            state,
            jnp.array([False]),
            jax.nn.one_hot(jnp.array([0]), 4),
            jnp.zeros((1, 2)),
            none,
            window.at[0, 1, 2].set(count),
            drops,
            capped,
        )[0][0]

    np.testing.assert_array_equal(corrected(3.0, True), corrected(1.0, True))
    assert int(corrected(3.0, True).argmax()) == 2 * 5 + 2  # the brick right of the robot: the centre
    assert not np.allclose(corrected(3.0, False), corrected(1.0, False))


def test_brick_occupancy_caps_the_3d_map_and_is_refused_elsewhere():
    agent = build_algorithm(make_config("pqn-belief", "3d-static-dense", **TINY, brick_map=True, brick_occupancy=True))
    assert isinstance(agent.network, MappingBeliefQNetwork) and agent.network.capped
    with pytest.raises(
        ValueError, match="brick_occupancy needs brick_map=True on a 3D task, got brick_map=False on 3d"
    ):
        make_config("pqn-belief", "3d-static-dense", brick_occupancy=True)
    with pytest.raises(ValueError, match="brick_occupancy needs brick_map=True on a 3D task, got brick_map=True on 2d"):
        make_config("pqn-belief", "2d-dynamic-sparse", brick_map=True, brick_occupancy=True)


def test_the_map_needs_the_filter():
    with pytest.raises(ValueError, match="brick_map needs belief_filter=True"):
        make_config("pqn-belief", "2d-static-sparse", brick_map=True, belief_filter=False, position_coef=5e-3)


def test_the_remaining_compass_by_hand():
    """A 3x3 solid design (9 bricks), the map sure of (0, 0) and (0, 1) and half sure of (2, 2):
    unbuilt per row 1, 3, 2.5 and per column 2, 2, 2.5. The robot is sure of row 1 and split between columns 0 and 1: above 1,
    below 2.5, left 0.5 * 0 + 0.5 * 2, right 0.5 * 4.5 + 0.5 * 2.5, all 6.5, each over 9."""
    design = jnp.ones((3, 3))
    built = jnp.zeros((3, 3)).at[0, 0].set(1.0).at[0, 1].set(1.0).at[2, 2].set(0.5)
    compass = remaining_compass(jnp.array([0.0, 1.0, 0.0]), jnp.array([0.5, 0.5, 0.0]), design, built)
    np.testing.assert_allclose(compass, np.array([1.0, 2.5, 1.0, 3.5, 6.5]) / 9, rtol=1e-6)
    off_design = remaining_compass(jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0]), jnp.eye(2), jnp.ones((2, 2)))
    np.testing.assert_array_equal(off_design, np.zeros(5))  # a brick where the design has none owes nothing


@pytest.mark.parametrize("brick_map", [False, True])
def test_the_compass_reaches_the_q_head(brick_map):
    """The same observation and belief, the map of drops empty or full (the filter's own, or the
    mapping filter's at evidence weight 0, so the map does not move the belief): the Q values
    differ with `todo_compass` and not without it."""
    task = "2d-static-dense"
    mapping = dict(brick_map=True, brick_evidence=0.0) if brick_map else {}

    def q_values(compass: bool):
        agent = build_algorithm(make_config("pqn-belief", task, **TINY, **mapping, todo_compass=compass))
        policy = agent.policy(None)
        obs, _ = agent.env.reset(jax.random.key(0), agent.env_params)
        start = policy.init(None, None)
        net_obs = agent.layout.acting_inputs(obs, start)[None, None]
        carry, reset = start["carry"][None], jnp.array([[False]])
        params = agent.network.init(jax.random.key(1), carry, net_obs, reset)
        rows, cols = agent.env.config.plan_shape
        map_at = agent.network.rnn_size + (rows * cols if brick_map else rows + cols)  # after the belief
        if compass and not brick_map:  # the filter's carry grows by the map
            assert agent.network.carry_size == map_at + rows * cols
        full = carry.at[:, map_at : map_at + rows * cols].set(1.0)
        return [agent.network.apply(params, c, net_obs, reset)[1] for c in (carry, full)]

    empty, full = q_values(True)
    assert not np.allclose(empty, full)
    if brick_map:  # without the compass the filter keeps no map; the mapping filter's, unread at weight 0
        empty, full = q_values(False)
        np.testing.assert_allclose(empty, full, rtol=1e-6)


def test_the_filter_maps_a_drop_under_its_belief():
    """One drop on the robot's own cell with the compass on: the map the filter carries after it is
    `add_drop` of the belief's product (the robot sure of the corner, so a sure brick there)."""
    agent = build_algorithm(make_config("pqn-belief", "2d-static-dense", **TINY, todo_compass=True))
    network, env = agent.network, agent.env
    rows, cols = env.config.plan_shape
    policy = agent.policy(None)
    drop = [a for a, (is_drop, d_row, d_col) in enumerate(drop_table(env.config)) if is_drop and not d_row | d_col][0]
    obs, env_state = env.reset(jax.random.key(0), agent.env_params)
    start = policy.init(None, None)
    params = network.init(
        jax.random.key(1),
        start["carry"][None],
        agent.layout.acting_inputs(obs, start)[None, None],
        start["reset"][None, None],
    )
    _, state = policy.act(params, start, obs, jax.random.key(2))  # the episode's first step: the belief at the corner
    state = {**state, **agent.layout.remember(obs, jnp.asarray(drop))}  # as if it had chosen the drop
    obs, env_state, *_ = env.step(jax.random.key(3), env_state, drop, agent.env_params)
    _, state = policy.act(params, state, obs, jax.random.key(4))
    built = state["carry"][network.rnn_size + rows + cols :].reshape(rows, cols)
    assert float(built[0, 0]) == 1.0 and float(built.sum()) == 1.0


def test_the_compass_needs_the_filter():
    with pytest.raises(
        ValueError, match="^todo_compass needs belief_filter=True: it maps the drops under the filter's belief$"
    ):
        make_config("pqn-belief", "2d-static-dense", todo_compass=True, belief_filter=False, position_coef=5e-3)
