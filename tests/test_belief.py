"""`pqn-belief` (agents/research/pqn_belief.py): the expected design window by hand and against a loop over
positions, the filter's pieces by hand and the whole filter tracking real episodes, each belief
trained by its own loss alone, the design it reads (the observation's or the static task's),
honest acting and the CLI. Tiny runs with every signal, compile-once and resume are
tests/test_privileged.py's, shared with the other learners of privileged signals."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.research.belief_filter import (
    belief_cross_entropy,
    correct_belief,
    expected_design_window,
    filter_step,
    move_belief,
    padding_agrees,
    start_belief,
)
from agents.research.drqn_aux import move_directions
from agents.research.pqn_belief import BeliefQNetwork
from agents.training.registry import build_algorithm, make_config
from snac_jax.tasks import make

TINY = dict(
    total_steps=2 * 16 * 8,
    num_envs=16,
    rollout_steps=8,
    num_minibatches=2,
    update_epochs=1,
    hidden_size=16,
    rnn_size=16,
    stagger_starts=False,  # no random steps before training: a smaller `init` to compile
)


expected_window = jax.jit(expected_design_window, static_argnums=3)
"""`expected_design_window` jitted (the view's shape static): one program a shape, not one per operation."""


def test_expected_window_by_hand_in_1d():
    design = jnp.array([[1.0, 2.0, 3.0, 4.0]])  # one row of four columns; a window of three
    one_row = jnp.ones(1)
    window = expected_window(one_row, jnp.array([1.0, 0.0, 0.0, 0.0]), design, (1, 3), outside=-1.0)
    np.testing.assert_allclose(window, [[-1.0, 1.0, 2.0]])  # off the plan on the left: the padding value
    # Equally unsure of all four columns: padded design -1 1 2 3 4 -1, each window cell the mean
    # of four consecutive entries: (-1+1+2+3)/4, (1+2+3+4)/4, (2+3+4-1)/4.
    window = expected_window(one_row, jnp.full(4, 0.25), design, (1, 3), outside=-1.0)
    np.testing.assert_allclose(window, [[1.25, 2.5, 2.0]])
    # Half on column 1, half on column 3: the mean of the two windows [1 2 3] and [3 4 -1].
    window = expected_window(one_row, jnp.array([0.0, 0.5, 0.0, 0.5]), design, (1, 3), -1.0)
    np.testing.assert_allclose(window, [[2.0, 3.0, 1.0]])


@pytest.mark.slow
def test_expected_window_is_the_belief_weighted_crop_in_2d():
    key_design, key_rows, key_cols = jax.random.split(jax.random.key(0), 3)
    design = jax.random.randint(key_design, (2, 5, 6), 0, 4).astype(jnp.float32)  # a batch of two designs
    row_logits, col_logits = jax.random.normal(key_rows, (2, 5)), jax.random.normal(key_cols, (2, 6))
    p_row, p_col = jax.nn.softmax(row_logits), jax.nn.softmax(col_logits)
    got = expected_window(p_row, p_col, design, (3, 3), outside=-0.5)
    want = np.zeros((2, 3, 3))
    rows, cols = np.asarray(p_row), np.asarray(p_col)  # indexed in NumPy: no program per index
    for b in range(2):
        padded = np.pad(np.asarray(design)[b], 1, constant_values=-0.5)
        for r in range(5):
            for c in range(6):
                want[b] += rows[b, r] * cols[b, c] * padded[r : r + 3, c : c + 3]  # the window at (r, c)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    # A wider view holds the window's expectation at its centre.
    wide = expected_window(p_row, p_col, design, (7, 5), outside=-0.5)
    np.testing.assert_allclose(wide[:, 2:5, 1:4], got, rtol=1e-5, atol=1e-6)


def test_a_move_shifts_the_belief_by_the_cells_and_stops_at_the_ends():
    at_1 = jnp.array([0.0, 1.0, 0.0, 0.0, 0.0])
    one_or_two = jnp.array([0.0, 0.5, 0.5, 0.0])  # P(cells moved = m), m = 0..3
    np.testing.assert_allclose(move_belief(at_1, one_or_two, jnp.array(1.0)), [0, 0, 0.5, 0.5, 0])
    np.testing.assert_allclose(move_belief(at_1, one_or_two, jnp.array(-1.0)), [1, 0, 0, 0, 0])  # 1 - 1 and 1 - 2 -> 0
    np.testing.assert_allclose(move_belief(at_1, jnp.array([0.0, 0, 0, 1]), jnp.array(1.0)), [0, 0, 0, 0, 1])
    np.testing.assert_allclose(move_belief(at_1, one_or_two, jnp.array(0.0)), at_1)  # a drop: no move
    spread = jnp.array([0.5, 0.0, 0.0, 0.5, 0.0])
    np.testing.assert_allclose(
        move_belief(spread, jnp.array([0.5, 0.5, 0, 0]), jnp.array(1.0)), [0.25, 0.25, 0, 0.25, 0.25]
    )


def test_padding_keeps_the_positions_whose_window_reaches_off_the_plan_there():
    # five positions, a window of three: from 0 it reaches one cell off the left edge, from 4 off the right
    np.testing.assert_array_equal(padding_agrees(jnp.array([True, False, False]), 5), [1, 0, 0, 0, 0])
    np.testing.assert_array_equal(padding_agrees(jnp.array([False, False, True]), 5), [0, 0, 0, 0, 1])
    np.testing.assert_array_equal(padding_agrees(jnp.array([False, False, False]), 5), [0, 1, 1, 1, 0])
    # A floor of u = 1e-6 under every position, then weight u where the padding disagrees.
    u = 1e-6
    corrected = correct_belief(jnp.array([0.5, 0.5, 0.0, 0.0, 0.0]), jnp.array([False, True, True, True, False]))
    weights = np.array([(0.5 + u) * u, 0.5 + u, u, u, u * u])
    np.testing.assert_allclose(corrected, weights / weights.sum(), rtol=1e-5)
    # All its mass where the padding says it cannot be: it moves to where it can.
    recovered = correct_belief(jnp.array([1.0, 0.0, 0.0, 0.0, 0.0]), jnp.array([False, True, True, True, False]))
    assert float(recovered[1:4].sum()) > 0.7


def test_filter_step_by_hand():
    step = jax.jit(filter_step)  # one program for the three steps, not one per operation
    rows, cols, window = 4, 6, (3, 3)
    at_start = np.zeros((1,) + window, bool)
    at_start[0, 0, :] = at_start[0, :, 0] = True  # at plan (0, 0) the window's top row and left column are off the plan
    start = (start_belief(rows)[None], start_belief(cols)[None])
    reset = jnp.array([True])
    right = jnp.array([[0.0, 1.0]])
    b_row, b_col = step(start, reset, jnp.array([[0.0, 0.0, 1.0, 0.0]]), right, jnp.asarray(at_start))
    np.testing.assert_allclose(
        b_col[0], start_belief(cols), atol=1e-5
    )  # a reset ignores the move: the episode's first step
    top_row = np.zeros((1,) + window, bool)
    top_row[0, 0, :] = True  # two or three cells right of the corner: only the top row is off the plan
    b_row, b_col = step((b_row, b_col), ~reset, jnp.array([[0.0, 0.0, 0.5, 0.5]]), right, jnp.asarray(top_row))
    np.testing.assert_allclose(b_row[0], [1, 0, 0, 0], atol=1e-5)
    np.testing.assert_allclose(b_col[0], [0, 0, 0.5, 0.5, 0, 0], atol=1e-5)
    # No padding anywhere: rows 0 and 3 would show it above or below, so the row belief leaves them.
    b_row, _ = step(
        (jnp.full((1, rows), 0.25), b_col), ~reset, jnp.array([[1.0, 0, 0, 0]]), right, jnp.zeros((1,) + window, bool)
    )
    np.testing.assert_allclose(b_row[0], [0, 0.5, 0.5, 0], atol=1e-5)


def random_episode_steps(env, params, worlds: int, steps: int):
    """Random actions in `worlds` worlds with auto-reset, one step after another. Yields what a
    filter sees before acting: `(obs, previous_obs, reset, last_action, cells, position)`, the
    cells the last move carried the robot (0 after a reset: the episode's first step) and its
    true plan position. At the start `last_action` is "none" (`num_actions`)."""
    reset_all = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))

    @jax.jit
    def advance(t, state, params):  # one program a step, not one per operation
        action = jax.random.randint(jax.random.key(100 + t), (worlds,), 0, env.num_actions)
        obs, after, _, terminated, truncated, _ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(jax.random.key(t), worlds), state, action, params
        )
        return obs, after, terminated | truncated, action, jnp.abs(after.position - state.position).sum(-1)

    obs, state = reset_all(jax.random.split(jax.random.key(0), worlds), params)
    previous, reset = obs, jnp.ones(worlds, bool)
    last_action, cells = jnp.full(worlds, env.num_actions), jnp.zeros(worlds, jnp.int32)
    for t in range(steps):
        yield obs, previous, reset, last_action, cells, state.position
        previous = obs
        obs, state, reset, last_action, cells = advance(t, state, params)


@pytest.mark.slow
@pytest.mark.parametrize("task", ["1d-static-sin", "2d-dynamic-sparse", "3d-static-dense"])
def test_the_filter_tracks_real_episodes_when_told_the_cells_moved(task):
    """With the true cells moved as its move distribution, the filter's belief is the robot's
    position, step after step, through random episodes: moves clipped at the plan's edge, blocked
    by bricks (3D), drops, and the resets of auto-reset."""
    env, params = make(task, max_steps=40)
    moves = jnp.asarray(np.concatenate([move_directions(env.config), [(0, 0)]]), jnp.float32)
    worlds, (rows, cols) = 16, env.config.plan_shape

    @jax.jit
    def track(belief, obs, reset, last_action, cells):  # one program a step, not one per operation
        padding = env.observation_layout.window_cells(obs) == -1
        belief = filter_step(belief, reset, jax.nn.one_hot(cells, 4), moves[last_action], padding)
        return belief, [jnp.argmax(b, -1) for b in belief], [jnp.min(jnp.max(b, -1)) for b in belief]

    belief, ends = (jnp.zeros((worlds, rows)), jnp.zeros((worlds, cols))), 0
    for t, (obs, _, reset, last_action, cells, position) in enumerate(random_episode_steps(env, params, worlds, 120)):
        belief, (peak_row, peak_col), (sure_row, sure_col) = track(belief, obs, reset, last_action, cells)
        np.testing.assert_array_equal(peak_row, position[:, 0], err_msg=f"row, step {t}")
        np.testing.assert_array_equal(peak_col, position[:, 1], err_msg=f"column, step {t}")
        assert float(sure_row) > 0.99 and float(sure_col) > 0.99
        ends += int(np.sum(reset)) if t else 0
    assert ends >= 2 * worlds  # episodes of at most 40 steps: every world crossed two auto-resets


@pytest.mark.slow
@pytest.mark.parametrize("task", ["2d-static-sparse", "3d-dynamic-dense"])
def test_the_networks_filter_tracks_real_episodes_when_its_move_head_is_right(task):
    """The network's own wiring of the filter (the action's direction from the observation's
    last-action one-hot, the padding read off the window, the carry split into rows and columns),
    given move logits that put all the mass on the true cells moved: its belief's peak is the
    robot's position at every step, through auto-resets, as the acting path computes it."""
    agent = build_algorithm(make_config("pqn-belief", task, **TINY, max_steps=30))
    network, layout, worlds = agent.network, agent.layout, 16

    @jax.jit
    def run_filter(belief, obs, previous, reset, last_action, cells):  # one program a step, not one per operation
        net_obs = layout.with_previous_step(obs, previous, last_action, reset)
        logits = 50.0 * jax.nn.one_hot(cells, 4)[None]
        belief, (b_row, b_col) = network.apply(
            {}, belief, logits, net_obs[None], reset[None], method=BeliefQNetwork.run_filter
        )
        return belief, jnp.argmax(b_row[0], -1), jnp.argmax(b_col[0], -1)

    belief, ends = network.initial_carry(worlds)[:, network.rnn_size :], 0
    episode_steps = random_episode_steps(agent.env, agent.env_params, worlds, 70)
    for t, (obs, previous, reset, last_action, cells, position) in enumerate(episode_steps):
        belief, peak_row, peak_col = run_filter(belief, obs, previous, reset, last_action, cells)
        np.testing.assert_array_equal(peak_row, position[:, 0], err_msg=f"row, step {t}")
        np.testing.assert_array_equal(peak_col, position[:, 1], err_msg=f"column, step {t}")
        ends += int(np.sum(reset)) if t else 0
    assert ends >= 2 * worlds  # episodes of at most 30 steps: every world crossed two auto-resets


def test_belief_cross_entropy_by_hand():
    # Step 1: sure of row 2; the column split between 1 and 5, the robot at (2, 5): -log(1 x 0.5) = ln 2.
    # Step 2: uniform over 4 rows and 6 columns: ln 4 + ln 6. The metric is the mean of the two.
    p_row = jnp.array([[0.0, 0.0, 1.0, 0.0], [0.25, 0.25, 0.25, 0.25]])
    p_col = jnp.array([[0.0, 0.5, 0.0, 0.0, 0.0, 0.5], [1 / 6] * 6])
    position = jnp.array([[2, 5], [3, 0]])
    np.testing.assert_allclose(belief_cross_entropy(p_row, p_col, position), (np.log(2) + np.log(24)) / 2, rtol=1e-6)
    # Rows and columns are not interchangeable: sure of (2, 5), the robot at (2, 5) costs nothing and
    # at (5, 2) the product is 0, floored at 1e-12: 27.6 nats.
    sure = jax.nn.one_hot(jnp.array([2]), 6), jax.nn.one_hot(jnp.array([5]), 6)
    np.testing.assert_allclose(belief_cross_entropy(*sure, jnp.array([[2, 5]])), 0.0, atol=1e-6)
    np.testing.assert_allclose(belief_cross_entropy(*sure, jnp.array([[5, 2]])), -np.log(1e-12), rtol=1e-5)


def test_move_directions_of_each_dimension():
    np.testing.assert_array_equal(move_directions(make("1d-static-sin")[0].config), [(0, -1), (0, 1), (0, 0)])
    np.testing.assert_array_equal(
        move_directions(make("3d-static-dense")[0].config),
        [(0, -1), (0, 1), (1, 0), (-1, 0), (0, 0), (0, 0), (0, 0), (0, 0)],
    )
    # the landmark placement (SPEC §14) moves nobody: one more (0, 0) row, after the table's
    with_placement = move_directions(make("2d-static-sparse", landmark_action=4)[0].config)
    np.testing.assert_array_equal(with_placement, [*move_directions(make("2d-static-sparse")[0].config), (0, 0)])


@pytest.mark.parametrize("task,dynamic", [("1d-dynamic", True), ("2d-static-sparse", False)])
def test_the_design_read_is_the_observations_or_the_static_tasks_own(task, dynamic):
    agent = build_algorithm(make_config("pqn-belief", task, **TINY))
    if dynamic:
        assert agent.network.fixed_design is None
    else:
        np.testing.assert_array_equal(np.asarray(agent.network.fixed_design), agent.env_params.designs[0])


def both_gradients(td_loss, loss, *args):
    """The gradient of `td_loss` and `loss`'s value and gradient, in one program: jitted, not one
    program per operation, and the network's forward pass compiled once for both."""
    return jax.grad(td_loss)(*args), jax.value_and_grad(loss, has_aux=True)(*args)


@pytest.mark.slow
def test_the_belief_learns_from_the_position_loss_only_and_acting_reads_observations_only():
    agent = build_algorithm(make_config("pqn-belief", "2d-dynamic-sparse", **TINY, belief_filter=False, max_steps=5))
    state = jax.jit(agent.init)(jax.random.key(0))
    _, batch, _ = jax.jit(agent.rollout)(state, agent.env_params)
    targets = jnp.zeros(batch.reward.shape)
    carry0 = state.worlds.carry

    def td_loss(params, carry0, batch, targets):  # the Q regression alone: no position loss
        (_, q), _ = agent.network.apply(params, carry0, batch.obs, batch.reset, mutable="intermediates")
        taken = jnp.take_along_axis(q, batch.action[..., None], axis=-1)[..., 0]
        return jnp.mean((taken - targets) ** 2)

    grads, ((_, info), full) = jax.jit(both_gradients, static_argnums=(0, 1))(
        td_loss, agent._loss, state.params, carry0, batch, targets
    )
    grads = grads["params"]
    assert all(float(np.abs(g).max()) == 0.0 for g in jax.tree.leaves(grads["auxiliary_heads"]))
    assert float(np.abs(grads["ScannedRNN_0"]["GRUCell_0"]["hn"]["kernel"]).max()) > 0  # the check bites
    assert float(np.abs(full["params"]["auxiliary_heads"]["Dense_0"]["kernel"]).max()) > 0
    assert np.isfinite(float(info["position_loss"])) and float(info["belief_nll"]) >= 0.0

    policy = agent.policy(state.params)
    policy_state = policy.init(jax.random.key(1), agent.env_params.designs[0])
    obs, _ = agent.env.reset(jax.random.key(2), agent.env_params)
    action, _ = jax.jit(policy.act)(state.params, policy_state, obs, jax.random.key(3))
    assert 0 <= int(action) < agent.env.num_actions


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_a_wider_egocentric_view_without_the_design_encoder():
    agent = build_algorithm(make_config("pqn-belief", "2d-dynamic-dense", **TINY, view_radius=7, design_encoder=False))
    params = jax.jit(agent.init)(jax.random.key(0)).params["params"]
    assert agent.network.view_shape == (15, 15)
    assert "DesignEncoder_0" not in params["ObservationEncoder_0"]  # the design is read through the view alone
    # the Q head's hidden layer reads the GRU output (16), the 15 x 15 view and the 7 x 7 window's "missing"
    assert params["Dense_0"]["kernel"].shape == (16 + 225 + 49, 16)
    default = build_algorithm(make_config("pqn-belief", "1d-dynamic", **TINY))
    assert (
        default.network.view_shape == (1, 5)
        and "DesignEncoder_0" in jax.jit(default.init)(jax.random.key(0)).params["params"]["ObservationEncoder_0"]
    )
    assert build_algorithm(make_config("pqn-belief", "1d-dynamic", **TINY, view_radius=4)).network.view_shape == (1, 9)
    with pytest.raises(ValueError, match=r"view_radius must be 0 or in 3\.\.19 on 2d-static-dense, got 2"):
        make_config("pqn-belief", "2d-static-dense", view_radius=2)


def test_each_belief_needs_the_loss_that_trains_it():
    with pytest.raises(ValueError, match=r"pqn-belief needs position_coef > 0 \(or belief_filter\)"):
        make_config("pqn-belief", "1d-dynamic", belief_filter=False, position_coef=0.0)
    with pytest.raises(ValueError, match="pqn-belief with belief_filter needs move_coef > 0"):
        make_config("pqn-belief", "1d-dynamic", move_coef=0.0)
    with pytest.raises(ValueError, match="pqn-belief with belief_filter needs previous_step=True"):
        make_config("pqn-belief", "1d-dynamic", previous_step=False)
    with pytest.raises(ValueError, match="pqn-belief needs recurrent=True"):
        make_config("pqn-belief", "1d-dynamic", recurrent=False)
    assert make_config("pqn-belief", "1d-dynamic", position_coef=0.0).belief_filter  # the default belief
    assert not make_config("pqn-belief", "1d-dynamic", belief_filter=False, move_coef=0.0).belief_filter


@pytest.mark.slow
def test_the_filters_move_head_learns_from_the_move_loss_only():
    agent = build_algorithm(
        make_config(
            "pqn-belief", "3d-dynamic-dense", **TINY, belief_filter=True, move_coef=0.01, position_coef=0.0, max_steps=5
        )
    )
    assert agent.network.carry_size == 16 + 20 + 20  # the GRU's state, then the row and column beliefs
    state = jax.jit(agent.init)(jax.random.key(0))
    assert "auxiliary_heads" not in state.params["params"]  # no head on the GRU state: the move head is the filter's
    after, batch, _ = jax.jit(agent.rollout)(state, agent.env_params)
    targets, carry0 = jnp.zeros(batch.reward.shape), state.worlds.carry

    def td_loss(params, carry0, batch, targets):
        (_, q), _ = agent.network.apply(params, carry0, batch.obs, batch.reset, mutable="intermediates")
        return jnp.mean((jnp.take_along_axis(q, batch.action[..., None], axis=-1)[..., 0] - targets) ** 2)

    grads, ((_, info), full) = jax.jit(both_gradients, static_argnums=(0, 1))(
        td_loss, agent._loss, state.params, carry0, batch, targets
    )
    grads = grads["params"]
    assert all(float(np.abs(g).max()) == 0.0 for g in jax.tree.leaves(grads["move_head"]))
    assert all(float(np.abs(g).max()) > 0.0 for g in jax.tree.leaves(full["params"]["move_head"])[:1])
    assert np.isfinite(float(info["move_loss"])) and float(info["belief_nll"]) >= 0.0
    # The belief after the rollout rides in the carry: each world's rows and columns sum to 1.
    after = after.worlds.carry
    np.testing.assert_allclose(after[:, 16:36].sum(-1), 1.0, rtol=1e-5)
    np.testing.assert_allclose(after[:, 36:].sum(-1), 1.0, rtol=1e-5)


@pytest.mark.slow  # a training and an evaluation subprocess
def test_cli_trains_two_seeds_and_evaluates(tmp_path):
    out = tmp_path / "run"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    cmd = [
        sys.executable,
        "-m",
        "snac_jax.cli",
        "train",
        "pqn-belief",
        "--task",
        "1d-dynamic",
        "--seeds",
        "2",
        "--total-steps",
        "256",
        "--num-envs",
        "8",
        "--rollout-steps",
        "8",
        "--num-minibatches",
        "2",
        "--hidden-size",
        "8",
        "--rnn-size",
        "8",
        "--max-steps",
        "40",
        "--chunks",
        "2",
        "--out",
        str(out),
        "--eval-episodes",
        "1",
        "--no-progress",
    ]
    result = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    for name in ("config.json", "metrics.jsonl", "eval.json"):
        assert (out / name).is_file(), name
    saved = json.loads((out / "config.json").read_text())
    assert saved["algorithm"] == "pqn-belief" and saved["position_coef"] > 0
    assert len(json.loads((out / "eval.json").read_text())) == 2  # one result per training seed


@pytest.mark.parametrize(("task", "allowed"), [("2d-static-dense", r"3\.\.19"), ("1d-dynamic", r"2\.\.29")])
def test_a_view_wider_than_the_plan_is_refused_before_tracing(task, allowed):
    """A view of radius max(rows, cols) - 1 already shows the whole plan from every position; a
    wider one only adds padding, and its cost grows with the radius (a huge one never compiles)."""
    with pytest.raises(ValueError, match=rf"view_radius must be 0 or in {allowed} on {task}, got 100000"):
        make_config("pqn-belief", task, view_radius=100000)
    largest = int(allowed.split(r"\.\.")[1])
    assert make_config("pqn-belief", task, view_radius=largest).view_radius == largest


def test_the_cli_refuses_a_view_wider_than_the_plan_in_one_line(tmp_path, capsys, monkeypatch):
    from snac_jax.cli import main

    monkeypatch.delenv("SNAC_TRACEBACK", raising=False)
    argv = [
        "train",
        "pqn-belief",
        "--task",
        "2d-static-dense",
        "--view-radius",
        "100000",
        "--total-steps",
        "256",
        "--num-envs",
        "16",
        "--no-progress",
        "--out",
        str(tmp_path / "run"),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("snac train pqn-belief: error: view_radius must be 0 or in 3..19 on 2d-static-dense")
    assert err.count("\n") == 1
    assert not (tmp_path / "run").exists()
