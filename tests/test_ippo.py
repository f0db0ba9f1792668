"""IPPO: the team loss by hand, robots x worlds through one network, tiny training runs through
the driver and the CLI (with the team's evaluation), resume, and the robot counts a task allows."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from agents.learners.ippo import IPPO, team_objective
from agents.training import checkpoint
from agents.training.driver import read_metrics, train
from agents.training.registry import make_config
from agents.training.schemas import EVAL_JSON, load

TINY = dict(num_envs=4, rollout_steps=8, num_minibatches=2, update_epochs=1, hidden_size=8, rnn_size=8)
TINY_FLAGS = [
    "--num-envs",
    "4",
    "--rollout-steps",
    "8",
    "--num-minibatches",
    "2",
    "--update-epochs",
    "1",
    "--hidden-size",
    "8",
    "--rnn-size",
    "8",
    "--no-progress",
    "--devices",
    "1",
]


def _leaves_equal(a, b) -> bool:
    a, b = checkpoint.to_storable(a), checkpoint.to_storable(b)
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_team_objective_matches_hand_computation():
    # Two robot-steps, two actions; uniform logits now, so log pi = log 0.5 for both.
    logits = jnp.zeros((2, 2))
    action = jnp.array([0, 1])
    old_log_prob = jnp.log(jnp.array([0.25, 1.0]))  # ratios 2 and 0.5
    advantages = jnp.array([1.0, -1.0])  # normalised: [1, -1] / std(=1) -> unchanged (up to 1e-8)
    value, old_value, targets = jnp.array([1.0, 0.0]), jnp.array([0.0, 0.0]), jnp.array([2.0, 1.0])
    clip, vf, ent = 0.2, 0.5, 0.1
    total, info = team_objective(logits, value, action, old_log_prob, old_value, advantages, targets, clip, vf, ent)

    # ratio 2, A=+1: min(2, 1.2) = 1.2; ratio 0.5, A=-1: min(-0.5, -0.8) = -0.8
    actor = -(1.2 + -0.8) / 2
    # value 1 clipped to 0.2: max((1-2)^2, (0.2-2)^2) = 3.24; value 0: max(1, 1) = 1
    value_loss = 0.5 * (3.24 + 1.0) / 2
    entropy = np.log(2.0)
    np.testing.assert_allclose(info["actor_loss"], actor, rtol=1e-6)
    np.testing.assert_allclose(info["value_loss"], value_loss, rtol=1e-6)
    np.testing.assert_allclose(info["entropy"], entropy, rtol=1e-6)
    np.testing.assert_allclose(total, actor + vf * value_loss - ent * entropy, rtol=1e-6)


@pytest.mark.slow
def test_every_robot_reads_its_index_and_the_worlds_keep_their_axis_first():
    ippo = IPPO(make_config("ippo", "2d-static-dense", robots=3, total_steps=4 * 8, **TINY))
    state = ippo.init(jax.random.key(0))
    assert state.worlds.obs.shape[:2] == (4, 3) and state.worlds.carry.shape[:2] == (4, 3)
    assert all(leaf.shape[0] == 4 for leaf in jax.tree.leaves(state.worlds))  # what the driver shards
    inputs = ippo._network_inputs(state.worlds)
    np.testing.assert_array_equal(inputs[..., -3:], np.broadcast_to(np.eye(3), (4, 3, 3)))
    # The same observation under another index gives other logits: the index reaches the output.
    same = jnp.broadcast_to(inputs[:1, :1], (1, 3, inputs.shape[-1]))
    same = same.at[..., -3:].set(jnp.eye(3))
    _, logits, _ = ippo._apply(state.params, state.worlds.carry[:1], same[None], jnp.ones((1, 1), bool))
    assert not np.allclose(logits[0, 0, 0], logits[0, 0, 1])


@pytest.mark.slow
@pytest.mark.parametrize("robots", [pytest.param(1, marks=pytest.mark.slow), 2])
def test_training_counts_episodes_per_world_and_learns_finite(robots):
    # A step limit of 6 ends every world's episode inside a rollout of 8 steps.
    config = make_config("ippo", "1d-static-sin", robots=robots, max_steps=6, total_steps=2 * 4 * 8, **TINY)
    ippo = IPPO(config)
    assert ippo.team_env.num_agents == robots
    state, metrics = jax.jit(lambda s: ippo.train_chunk(s, ippo.env_params, 2))(ippo.init(jax.random.key(1)))
    assert int(state.update) == 2
    np.testing.assert_array_equal(metrics["episodes"], [4, 4])  # 4 worlds, one ending each, not one per robot
    assert all(np.isfinite(np.asarray(v)).all() for v in metrics.values())
    assert {"loss", "value_loss", "actor_loss", "entropy", "iou_sum", "return_sum"} <= set(metrics)


@pytest.mark.parametrize(
    "task, robots, message",
    [
        ("1d-static-sin", 3, "robots must be an int in 1..2 for 1d-static-sin, got 3"),  # the task's range
        ("2d-static-dense", 5, r"robots must be an int in \[1, 4\], got 5"),  # the field's own bounds
        ("3d-static-sparse", 0, r"robots must be an int in \[1, 4\], got 0"),
    ],
)
def test_robots_outside_the_tasks_range_are_refused_in_one_line(task, robots, message):
    with pytest.raises(ValueError, match=f"^{message}$"):
        make_config("ippo", task, robots=robots)
    make_config("ippo", task, robots=2)


def test_a_single_robot_switch_is_refused():
    with pytest.raises(ValueError, match="landmark_action is a single-robot switch"):
        make_config("ippo", "2d-static-dense", switches="landmark_action=2")


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_resume_equals_uninterrupted(tmp_path):
    config = make_config("ippo", "2d-static-dense", robots=2, seeds=2, total_steps=3 * 4 * 8, chunks=3, **TINY)
    _, straight = train(config, tmp_path / "straight", progress=False)
    _, first = train(config, tmp_path / "killed", progress=False, stop_after_chunks=1)
    assert int(first.update[0]) == 1
    _, resumed = train(config, tmp_path / "killed", resume=True, progress=False)
    assert int(resumed.update[0]) == 3 and _leaves_equal(straight, resumed)
    assert [r["chunk"] for r in read_metrics(tmp_path / "killed")] == [0, 1, 2]


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_snac_train_ippo_trains_and_scores_the_team(tmp_path, capsys):
    from snac_jax.cli import main

    out = tmp_path / "run"
    code = main(
        [
            "train",
            "ippo",
            "--robots",
            "2",
            "--task",
            "2d-static-dense",
            "--total-steps",
            str(2 * 4 * 8),
            "--chunks",
            "2",
            "--max-steps",
            "20",
            "--eval-episodes",
            "3",
            "--out",
            str(out),
            *TINY_FLAGS,
        ]
    )
    captured = capsys.readouterr()
    assert code == 0, captured.err[-3000:]
    assert (captured.out + captured.err).count("compiled a chunk of 1 updates") == 1  # two equal chunks, one compile
    assert json.loads((out / "config.json").read_text())["robots"] == 2
    assert [r["chunk"] for r in read_metrics(out)] == [0, 1]
    evaluation = load(out / "eval.json", EVAL_JSON)
    row = evaluation["2d-static-dense"]
    assert row["episodes"] == 3 and 0.0 <= row["mean"] <= 1.0 and row["mean_length"] <= 20


def test_snac_train_refuses_robots_outside_the_range_before_training(tmp_path, capsys):
    from snac_jax.cli import main

    code = main(
        ["train", "ippo", "--robots", "3", "--task", "1d-static-sin", "--out", str(tmp_path / "run"), *TINY_FLAGS]
    )
    err = capsys.readouterr().err
    assert code == 2
    assert "robots must be an int in 1..2 for 1d-static-sin, got 3" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()
