"""`bench/filter_replay.py`: the scores by hand; on episodes that move and drop, the replayed
mapping filter at the agent's own weight is the belief the agent held, step for step, and the
padding alone (weight 0) is the row-and-column filter's belief; a tiny run end to end; the
one-line refusals."""

from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.filter_replay import FLOOR, _observe, _record, main, score
from snac_jax.evaluation import protocol_episodes
from snac_jax.tasks import make

TASK = "2d-dynamic-sparse"
TINY = dict(num_envs=16, rollout_steps=8, num_minibatches=2, update_epochs=1, hidden_size=8, rnn_size=8, max_steps=20)
RIGHT, DOWN, DROP = 1, 2, 4  # 2D action table: left, right, down, up, drop


def test_the_scores_by_hand():
    # two episodes of a 5-step limit (6 observations), lengths 2 and 5; steps past a length are not scored
    p_true = np.array([[1.0, 0.5, 0.0, 0.9, 0.9, 0.9], [0.25, 0.25, 0.5, 1.0, 1.0, 0.5]])
    hit = np.array([[1, 0, 0, 1, 1, 1], [0, 0, 1, 1, 1, 0]], bool)
    result = score(p_true, hit, np.array([2, 5]), num_steps=5)
    nll = [0.0, math.log(2), -math.log(FLOOR), math.log(4), math.log(4), math.log(2), 0.0, 0.0, math.log(2)]
    assert result["all"]["steps"] == 9
    assert result["all"]["nll"] == pytest.approx(sum(nll) / 9)
    assert result["all"]["argmax_hit"] == pytest.approx(4 / 9)
    # thirds of steps [0, 6): {0, 1}, {2, 3}, {4, 5}
    first, second, third = result["thirds"]
    assert first["steps"] == 4 and first["nll"] == pytest.approx((math.log(2) + 2 * math.log(4)) / 4)
    assert second["steps"] == 3 and second["nll"] == pytest.approx((-math.log(FLOOR) + math.log(2)) / 3)
    assert third["steps"] == 2 and third["argmax_hit"] == pytest.approx(0.5)
    assert score(p_true[:1], hit[:1], np.array([1]), num_steps=5)["thirds"][1:] == [None, None]


def _untrained(**options):
    """A tiny pqn-belief agent, its freshly initialised weights, and a policy that carries the
    agent's memory (its filter included) but wanders and drops by the step's key: episodes on which
    the filter moves and the map fills."""
    from agents.training.registry import build_algorithm, make_config

    agent = build_algorithm(make_config("pqn-belief", TASK, **TINY, **options))
    greedy = agent.policy(None)
    obs, _ = agent.env.reset(jax.random.key(0), agent.env_params)
    start = greedy.init(None, None)
    params = agent.network.init(
        jax.random.key(1),
        start["carry"][None],
        agent.layout.acting_inputs(obs, start)[None, None],
        start["reset"][None, None],
    )

    def act(params, policy_state, obs, key):
        _, policy_state = greedy.act(params, policy_state, obs, key)
        action = jnp.array([RIGHT, DOWN, DROP], jnp.int32)[jax.random.randint(key, (), 0, 3)]
        return action, {**policy_state, **agent.layout.remember(obs, action)}

    return agent, greedy.init, act, params


def _replayed(agent, init, act, params, weight):
    """(held P(true), held hit, replayed P(true), replayed hit, lengths) on six protocol episodes."""
    from agents.research.belief_map import drop_table

    env = agent.env
    _, env_params = make(TASK, max_steps=60)
    setup = protocol_episodes(TASK, env_params, 3, episodes_per_test_design=1)
    keys, designs = setup.keys[:6], jnp.asarray(setup.design_indices[:6])
    (inputs, position, held_p, held_hit), length, _ = jax.device_get(
        _record(env, init, act, agent.held_belief, agent.filter_inputs, params, setup.params, keys, designs, 60)
    )
    rows, cols = env.config.plan_shape
    p, hit = jax.device_get(_observe(inputs, position, jnp.float32(weight), rows, cols, drop_table(env.config), True))
    assert (np.asarray(length) == 60).all() and (np.asarray(inputs[3])[..., 4] > 0).any()  # drops were made
    return held_p, held_hit, p, hit


def test_the_replayed_mapping_filter_at_the_agents_weight_is_the_belief_it_held():
    agent, init, act, params = _untrained(brick_map=True, brick_evidence=0.3)
    held_p, held_hit, p, hit = _replayed(agent, init, act, params, 0.3)
    assert (held_p < 0.99).any()  # the belief was unsure somewhere: there is something to reproduce
    np.testing.assert_allclose(p, held_p, rtol=1e-5, atol=1e-7)
    np.testing.assert_array_equal(hit, held_hit)
    _, _, p_full, _ = _replayed(agent, init, act, params, 1.0)
    assert not np.allclose(p_full, held_p, atol=1e-3)  # the weight changes the belief


def test_the_padding_alone_on_the_joint_belief_is_the_filters_row_and_column_belief():
    """Weight 0 on a filter run: the same moves and padding on a joint belief and on a product of
    marginals agree but for the floors under unlikely cells."""
    agent, init, act, params = _untrained()
    held_p, held_hit, p, hit = _replayed(agent, init, act, params, 0.0)
    assert (held_p < 0.99).any()
    np.testing.assert_allclose(p, held_p, atol=0.02)
    assert (hit == held_hit).mean() > 0.95


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from agents.training.driver import train
    from agents.training.registry import make_config

    run = tmp_path_factory.mktemp("filter") / "run"
    train(make_config("pqn-belief", TASK, seeds=2, total_steps=512, chunks=1, **TINY), run, progress=False)
    return run


def test_a_tiny_run_is_replayed_for_each_weight_into_one_json(tiny_run, tmp_path, capsys):
    out = tmp_path / "out"
    assert (
        main(
            [
                "--run",
                str(tiny_run),
                "--out",
                str(out),
                "--episodes",
                "1",
                "--seed-index",
                "1",
                "--weights",
                "0",
                "0.5",
                "--eval-seed",
                "5",
            ]
        )
        == 0
    )
    assert [p.name for p in out.iterdir()] == ["filter_replay.json"]
    report = json.loads((out / "filter_replay.json").read_text())
    assert not report["brick_map"] and report["seed_indices"] == [1] and report["eval_seed"] == 5
    assert report["episodes"] == 10 and list(report["variants"]) == ["held", "mapping, weight 0", "mapping, weight 0.5"]
    for row in report["variants"].values():  # one seed: its own score is the whole
        assert list(row["per_seed"]) == ["1"] and row["per_seed"]["1"] == row["all"]
    both = tmp_path / "both"
    assert main(["--run", str(tiny_run), "--out", str(both), "--episodes", "1", "--weights", "0.5"]) == 0
    report = json.loads((both / "filter_replay.json").read_text())
    assert report["seed_indices"] == [0, 1] and report["episodes"] == 20
    for row in report["variants"].values():  # the seeds' scores, weighted by their steps, make the whole
        seeds = [row["per_seed"][s] for s in ("0", "1")]
        assert sum(s["steps"] for s in seeds) == row["all"]["steps"]
        for name in ("nll", "argmax_hit"):
            assert sum(s[name] * s["steps"] for s in seeds) / row["all"]["steps"] == pytest.approx(row["all"][name])
    printed = capsys.readouterr().out
    assert "| mapping, weight 0.5 |" in printed and printed.startswith("10 episodes (mean IoU ")


def test_runs_without_a_filter_and_bad_weights_are_refused_in_one_line(tmp_path, capsys):
    from agents.training.config import save_config
    from agents.training.registry import make_config

    out = tmp_path / "out"
    for algorithm, options, message in [
        ("pqn", {}, "is a pqn run; only pqn-belief runs have a filter to replay"),
        (
            "pqn-belief",
            {"belief_filter": False},
            "trained the learned belief (belief_filter=false): it has no filter to replay",
        ),
    ]:
        run = tmp_path / algorithm / str(len(options))
        run.mkdir(parents=True)
        save_config(make_config(algorithm, TASK, **TINY, **options), run / "config.json")
        assert main(["--run", str(run), "--out", str(out)]) == 2
        assert capsys.readouterr().err == f"filter_replay.py: error: {run} {message}\n"
    assert main(["--run", str(run), "--out", str(out), "--weights", "0.1", "-1"]) == 2
    assert capsys.readouterr().err == "filter_replay.py: error: --weights must be in 0..10, got -1.0\n"
    assert not out.exists()


def test_brick_evidence_needs_the_map():
    from agents.training.registry import make_config

    with pytest.raises(ValueError, match=r"^brick_evidence=0.5 needs brick_map=True: it weighs the map's evidence$"):
        make_config("pqn-belief", TASK, brick_evidence=0.5, **TINY)
