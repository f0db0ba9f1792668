"""`bench/belief_episodes.py`: the worst episodes by hand, the belief the Q head reads, a tiny
trained run drawn (the evaluator's episodes and IoUs, beliefs that sum to 1), and the one-line
refusals."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.belief_episodes import (
    HEAT_ANCHORS,
    _record,
    belief_numbers,
    drop_tally,
    episode_drops,
    episode_endings,
    heat_colours,
    main,
    worst_episodes,
)
from snac_jax.evaluation import protocol_episodes, run_episodes
from snac_jax.tasks import make

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "bench" / "belief_episodes.py"
TASK = "2d-dynamic-sparse"
TINY = dict(num_envs=16, rollout_steps=8, num_minibatches=2, update_epochs=1, hidden_size=8, rnn_size=8, max_steps=20)


def test_the_worst_episodes_are_the_lowest_ious_ties_by_lower_index():
    iou = np.array([0.5, 0.1, 0.3, 0.1, 0.0, 0.3], np.float32)
    assert worst_episodes(iou, 3).tolist() == [4, 1, 3]
    assert worst_episodes(iou, 5).tolist() == [4, 1, 3, 2, 5]


def test_the_belief_numbers_by_hand():
    belief = np.zeros((3, 4))
    belief[0, 1], belief[2, 3], belief[1, 1] = 0.2, 0.5, 0.3
    assert belief_numbers(belief, (1, 1)) == (0.3, 3, (2, 3))  # argmax (2, 3): one row and two columns away
    assert belief_numbers(belief, (2, 3)) == (0.5, 0, (2, 3))
    tied = np.full((2, 2), 0.25)
    assert belief_numbers(tied, (1, 1)) == (0.25, 2, (0, 0))  # the first largest in row-major order


def test_drops_against_the_belief_by_hand():
    # a 2x3 plan, padding 1 all round; the design fills (0, 1) and (1, 1)
    design = np.array([[0, 1, 0], [0, 1, 0]])
    empty = np.full((4, 5), -1)
    empty[1:3, 1:4] = 0
    grids = np.stack([empty] * 4)
    grids[1:, 1, 1] = 1  # step 1: a brick on (0, 0), off the design
    grids[2:, 2, 2] = 1  # step 2: a brick on (1, 1), on the design
    positions = np.array(
        [[0, 0], [1, 1], [1, 1], [1, 1]]
    )  # the robot on (0, 0) for the first drop, on (1, 1) for the others
    bricks_used = np.array([0, 1, 2, 3])  # step 3: a drop on (1, 1) again, which changes no cell
    beliefs = np.zeros((4, 2, 3))
    beliefs[0, 0, 0], beliefs[0, 0, 1] = 0.7, 0.3  # P(on a design cell) 0.3 when the first brick dropped
    beliefs[1, 1, 1], beliefs[1, 1, 2] = 0.4, 0.6  # 0.4 for the second: on the design, believed off
    rows = episode_drops(grids, positions, bricks_used, beliefs, np.stack([design] * 4), (1, 1), 3)
    np.testing.assert_allclose(rows[:2], [[1, 0, 0.3], [2, 1, 0.4]])
    assert rows[2, 0] == 3 and rows[2, 1] == -1 and np.isnan(rows[2, 2])
    # a neighbour drop (3D): the robot at (0, 0) drops on (0, 1); the belief is moved one column
    grids_3d = np.stack([empty, empty.copy()])
    grids_3d[1, 1, 2] = 1
    rows = episode_drops(
        grids_3d, np.array([[0, 0], [0, 0]]), np.array([0, 1]), beliefs[:2], np.stack([design] * 2), (1, 1), 1
    )
    np.testing.assert_allclose(rows, [[1, 1, 0.7]])  # P 0.7 at (0, 0) moves to (0, 1); 0.3 at (0, 1) to (0, 2)
    # the design changed after the first step (SPEC §15): the second brick is judged by the new one, off it
    changed = np.stack([design, 1 - design, 1 - design, 1 - design])
    assert episode_drops(grids, positions, bricks_used, beliefs, changed, (1, 1), 3)[:2, 1].tolist() == [0, 0]
    tally = drop_tally(
        [episode_drops(grids, positions, bricks_used, beliefs, np.stack([design] * 4), (1, 1), 3), np.zeros((0, 3))]
    )
    assert tally == {
        "drops": 3,
        "on a brick already there": 1,
        "off the design": 1,
        "off the design, believed off": 1,
        "off the design, in the first 20 steps": 1,
        "on the design, believed off": 1,
    }


def test_heat_colours_run_from_the_first_anchor_to_the_last():
    colours = heat_colours(np.array([0.0, 1.0, 0.125, 2.0]))
    np.testing.assert_array_equal(colours[0], HEAT_ANCHORS[0])
    np.testing.assert_array_equal(colours[1], HEAT_ANCHORS[-1])
    # 0.125 of four intervals is halfway between anchors 0 and 1: (0+80)/2, (0+18)/2, (4+123)/2 = 63.5 -> 64
    np.testing.assert_array_equal(colours[2], [40, 9, 64])
    np.testing.assert_array_equal(colours[3], HEAT_ANCHORS[-1])  # clipped


def _untrained(**options):
    """A tiny pqn-belief agent and its greedy policy with freshly initialised weights."""
    from agents.training.registry import build_algorithm, make_config

    agent = build_algorithm(make_config("pqn-belief", TASK, **TINY, **options))
    policy = agent.policy(None)
    obs, _ = agent.env.reset(jax.random.key(0), agent.env_params)
    start = policy.init(None, None)

    @jax.jit  # one program, not one per operation of the network's initialisation
    def init(key, obs, start):
        net_obs = agent.layout.acting_inputs(obs, start)
        return agent.network.init(key, start["carry"][None], net_obs[None, None], start["reset"][None, None])

    return agent, policy._replace(params=init(jax.random.key(1), obs, start))


@pytest.mark.slow
def test_the_held_belief_is_the_one_the_q_head_reads():
    """Along an episode of the greedy policy: the filter's held belief is the product of the row
    and column beliefs it carries after acting, whose row and column sums are the marginals the
    network sows for the Q head."""
    agent, policy = _untrained()
    network, layout = agent.network, agent.layout
    rows, cols = layout.plan_shape
    env, env_params = agent.env, agent.env_params
    obs, state = env.reset(jax.random.key(2), env_params)
    policy_state = policy.init(None, None)

    @jax.jit
    def step(policy_state, obs, state, key):
        held = agent.held_belief(policy.params, policy_state, obs)
        net_obs = layout.acting_inputs(obs, policy_state)
        _, sown = network.apply(
            policy.params,
            policy_state["carry"][None],
            net_obs[None, None],
            policy_state["reset"][None, None],
            mutable="intermediates",
        )
        p_row, p_col = sown["intermediates"]["belief"][0]
        action, policy_state = policy.act(policy.params, policy_state, obs, key)
        obs, state, *_ = env.step_env(key, state, action, env_params)
        return held, (p_row[0, 0], p_col[0, 0]), policy_state, obs, state

    for t in range(6):
        held, (p_row, p_col), policy_state, obs, state = step(policy_state, obs, state, jax.random.key(10 + t))
        assert held.shape == (rows, cols)
        np.testing.assert_allclose(held.sum(), 1.0, atol=1e-5)
        np.testing.assert_allclose(held.sum(axis=1), p_row, atol=1e-6)
        np.testing.assert_allclose(held.sum(axis=0), p_col, atol=1e-6)
        carried = policy_state["carry"][network.rnn_size :]
        np.testing.assert_allclose(held, np.outer(carried[:rows], carried[rows:]), atol=1e-7)


RIGHT, DOWN, DROP = 1, 2, 4  # 2D action table: left, right, down, up, drop


def _wander_and_drop(params, step, obs, key):
    """Right, down or drop, drawn from the step's key: episodes that differ by key alone."""
    return jnp.array([RIGHT, DOWN, DROP], jnp.int32)[jax.random.randint(key, (), 0, 3)], step + 1


def _flat_belief(params, step, obs):
    return jnp.full((20, 20), 1.0 / 400)  # the task's 20 x 20 plan


@pytest.mark.slow
def test_record_plays_the_evaluators_episodes_and_keeps_a_belief_per_state():
    """A policy that draws its actions from the evaluator's per-step keys: the recorded episodes
    end where `run_episodes`' do (IoU, length, bricks), which they would not with another key
    schedule, and the belief is written for each of the length + 1 states and nowhere after."""
    from snac_jax.policy import Policy

    policy = Policy(lambda key, design: jnp.zeros((), jnp.int32), _wander_and_drop, None, "wander")
    env, params = make(TASK, max_steps=40)
    setup = protocol_episodes(TASK, params, 5, episodes_per_test_design=1)
    scored = jax.device_get(run_episodes(env, setup.params, policy, setup.key, setup.design_indices))
    chosen = np.array([7, 2, 0, 9])
    recorded = jax.device_get(
        _record(
            env,
            policy.init,
            policy.act,
            _flat_belief,
            None,
            setup.params,
            setup.keys[chosen],
            jnp.asarray(setup.design_indices[chosen]),
            40,
        )
    )
    assert len(set(np.asarray(scored.iou)[chosen].tolist())) > 1 and (np.asarray(scored.iou)[chosen] > 0).any()
    np.testing.assert_array_equal(recorded.iou, np.asarray(scored.iou)[chosen])
    np.testing.assert_array_equal(recorded.length, np.asarray(scored.length)[chosen])
    for i, length in enumerate(np.asarray(recorded.length)):
        assert int(recorded.states.bricks_used[i, length]) == int(scored.bricks_used[chosen[i]])
        assert np.asarray(recorded.states.time[i, : length + 1]).tolist() == list(range(length + 1))
        mass = np.asarray(recorded.beliefs[i]).sum(axis=(1, 2))
        np.testing.assert_allclose(mass[: length + 1], 1.0, rtol=1e-5)
        assert (mass[length + 1 :] == 0).all()


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from agents.training.driver import train
    from agents.training.registry import make_config

    run = tmp_path_factory.mktemp("belief") / "run"
    train(make_config("pqn-belief", TASK, seeds=1, total_steps=256, chunks=1, **TINY), run, progress=False)
    return run


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_a_tiny_run_draws_the_evaluators_worst_episodes_with_their_beliefs(tiny_run, tmp_path, monkeypatch):
    from agents.training import trained
    from agents.training.checkpoint import read_config
    from agents.training.registry import build_algorithm
    from bench import belief_episodes

    monkeypatch.setattr(belief_episodes, "TALLY_BATCH", 7)  # 20 episodes: 7, 7 and a last 6 filled out to 7
    out = tmp_path / "out"
    assert main(["--run", str(tiny_run), "--out", str(out), "--episodes", "2", "--worst", "3", "--eval-seed", "7"]) == 0
    report = json.loads((out / "belief_episodes.json").read_text())
    assert report["run"] == str(tiny_run) and report["seed_index"] == 0 and report["eval_seed"] == 7
    assert report["episodes_played"] == 20 and report["belief"] == "row marginal x column marginal"
    rows = report["episodes"]
    assert [r["rank"] for r in rows] == [1, 2, 3]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["belief_episodes.json"] + [r["gif"] for r in rows] + [r["png"] for r in rows]
    )

    # the evaluator's own episodes: the three lowest IoUs, and each drawn one ends at its IoU
    config = read_config(tiny_run)
    env, params = make(TASK, **config.env_overrides)
    setup = protocol_episodes(TASK, params, 7, episodes_per_test_design=2)
    policy = trained.checkpoint_policy(env, tiny_run, 0)
    scored = jax.device_get(run_episodes(env, setup.params, policy, setup.key, setup.design_indices))
    chosen = worst_episodes(scored.iou, 3)
    assert [r["episode"] for r in rows] == chosen.tolist()
    # 2D has no obstacle rule, so no episode ends stuck: each ran to the step limit or spent its bricks
    limit = int(setup.params.max_steps_in_episode)
    assert report["endings"] == {
        "bricks spent": int((np.asarray(scored.length) < limit).sum()),
        "step limit": int((np.asarray(scored.length) == limit).sum()),
        "stuck": 0,
    }
    # every counted drop of every played episode is tallied once (the filled-out last batch's
    # repeats are not), each in one of the three kinds
    drops = report["drops"]
    assert drops["drops"] == int(np.asarray(scored.bricks_used).sum())
    assert drops["off the design, believed off"] <= drops["off the design"] <= drops["drops"]
    for r in rows:
        assert r["iou"] == float(scored.iou[r["episode"]]) and r["length"] == int(scored.length[r["episode"]])
        assert r["design"] == setup.names[int(setup.design_indices[r["episode"]])]
        assert len(r["p_true"]) == len(r["argmax_distance"]) == r["length"] + 1
        assert all(0.0 <= p <= 1.0 + 1e-6 for p in r["p_true"]) and all(d >= 0 for d in r["argmax_distance"])

    # the beliefs behind the numbers: each sums to 1, and P(true) is its entry at the true position
    agent = build_algorithm(config)
    recorded = jax.device_get(
        _record(
            env,
            policy.init,
            policy.act,
            agent.held_belief,
            policy.params,
            setup.params,
            setup.keys[chosen],
            jnp.asarray(setup.design_indices[chosen]),
            20,
        )
    )
    for i, r in enumerate(rows):
        beliefs = np.asarray(recorded.beliefs[i, : r["length"] + 1])
        np.testing.assert_allclose(beliefs.sum(axis=(1, 2)), 1.0, atol=1e-5)
        positions = np.asarray(recorded.states.position[i, : r["length"] + 1])
        np.testing.assert_allclose(
            r["p_true"], beliefs[np.arange(len(beliefs)), positions[:, 0], positions[:, 1]], rtol=1e-6
        )

    from PIL import Image

    with Image.open(out / rows[0]["gif"]) as gif:
        assert gif.n_frames >= 2  # identical consecutive frames may merge; the captions' step counter differs
        size = gif.size
    with Image.open(out / rows[0]["png"]) as png:
        assert png.size == size


def test_endings_are_told_apart_by_bricks_then_steps_then_stuck():
    # budgets 10, 10, 10, 5; step limit 100: spent (a drop at the limit counts as spent), at the
    # limit, stuck early, spent early
    endings = episode_endings(
        length=[100, 100, 37, 40], bricks_used=[10, 3, 7, 5], max_bricks=[10, 10, 10, 5], max_steps=100
    )
    assert endings == {"bricks spent": 2, "step limit": 1, "stuck": 1}


@pytest.mark.slow
def test_a_run_of_another_algorithm_is_refused_in_one_line(tmp_path):
    from agents.training.config import save_config
    from agents.training.registry import make_config

    run = tmp_path / "run"
    run.mkdir()
    save_config(make_config("pqn", TASK, **TINY), run / "config.json")
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--run", str(run), "--out", str(out)], capture_output=True, text=True, cwd=ROOT
    )
    assert done.returncode == 2
    assert done.stderr == (
        f"belief_episodes.py: error: {run} is a pqn run; only pqn-belief runs carry a belief to draw\n"
    )
    assert not out.exists()


@pytest.mark.slow
def test_a_missing_run_a_run_without_checkpoints_and_bad_choices_are_refused_in_one_line(tmp_path, capsys):
    from agents.training import sweep
    from agents.training.config import save_config
    from agents.training.registry import make_config

    out = tmp_path / "out"
    missing = tmp_path / "nowhere"
    assert main(["--run", str(missing), "--out", str(out)]) == 2
    assert capsys.readouterr().err == (
        f"belief_episodes.py: error: {missing} is not a training run directory: config.json is missing\n"
    )
    run = tmp_path / "run"
    run.mkdir()
    save_config(make_config("pqn-belief", TASK, **TINY), run / "config.json")
    assert main(["--run", str(run), "--out", str(out), "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"belief_episodes.py: error: {run}: no checkpoint under") and err.count("\n") == 1
    assert main(["--run", str(run), "--out", str(out), "--seed-index", "1"]) == 2
    assert capsys.readouterr().err == f"belief_episodes.py: error: --seed-index must be in 0..0 for {run}, got 1\n"
    assert main(["--run", str(run), "--out", str(out), "--episodes", "1", "--worst", "11"]) == 2
    assert capsys.readouterr().err == (
        "belief_episodes.py: error: --worst must be in 1..10 (the episodes played), got 11\n"
    )
    sweep.save(sweep.Sweep(("learning_rate",), ((1e-3,), (1e-4,))), run)
    assert main(["--run", str(run), "--out", str(out)]) == 2
    assert capsys.readouterr().err == (
        f"belief_episodes.py: error: {run} is a sweep of 2 arms: --arm must be in 0..1 (none given)\n"
    )
    assert not out.exists()
