"""`snac eval` end to end on a tiny budget: the table, the JSON, bad input, atomic writes."""

from __future__ import annotations

import json

import pytest

from snac_jax.atomic import atomic_write_json as write_json_atomic
from snac_jax.cli import main


@pytest.mark.slow
def test_eval_prints_table_beside_the_paper_and_writes_json(tmp_path, capsys):
    out = tmp_path / "results" / "handcrafted.json"
    code = main(
        [
            "eval",
            "--policy",
            "handcrafted",
            "--task",
            "2d-static-sparse",
            "--episodes",
            "2",
            "--seed",
            "4",
            "--json",
            str(out),
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "| 2d-static-sparse | 2 |" in printed
    assert "| 0.655 | 0.143 |" in printed  # the paper's handcrafted row for this task
    results = json.loads(out.read_text())
    assert list(results) == ["2d-static-sparse"]
    entry = results["2d-static-sparse"]
    assert entry["episodes"] == 2 and entry["seed"] == 4
    assert 0.0 <= entry["min"] <= entry["mean"] <= 1.0
    lo, hi = entry["ci95"]
    assert lo <= entry["mean"] <= hi
    assert {"std", "mean_length", "mean_bricks_used", "per_design"} <= set(entry)


def test_eval_reads_another_paper_results_file(tmp_path, capsys):
    paper = tmp_path / "paper.json"
    paper.write_text(json.dumps({"methods": {"handcrafted": {"2d-static-sparse": {"avg": 0.123, "min": 0.045}}}}))
    main(
        [
            "eval",
            "--policy",
            "handcrafted",
            "--task",
            "2d-static-sparse",
            "--episodes",
            "2",
            "--paper-results",
            str(paper),
        ]
    )
    assert "| 0.123 | 0.045 |" in capsys.readouterr().out


def test_a_1d_shape_is_printed_beside_the_papers_1d_static_column(capsys):
    """The paper reports the three 1D shapes as one column; a single shape is shown beside it,
    as `snac train`'s own evaluation shows it, and the header says so."""
    main(["eval", "--policy", "handcrafted", "--task", "1d-static-sin", "--episodes", "2"])
    printed = capsys.readouterr().out
    assert "1d-static-sin beside the paper's 1d-static column" in printed
    assert "| 0.948 | 0.839 |" in printed  # the paper's handcrafted 1d-static column


def test_random_policy_has_no_paper_row(capsys):
    main(["eval", "--policy", "random", "--task", "2d-static-sparse", "--episodes", "2"])
    printed = capsys.readouterr().out
    assert "paper row: none" in printed
    assert "| — | — | — |" in printed


@pytest.mark.parametrize(
    "argv, message",
    [
        (["eval", "--policy", "ppo-nope", "--task", "all"], "registered policies: handcrafted"),
        (["eval", "--policy", "handcrafted", "--task", "2d-static"], "allowed: all, 1d-static"),
        (["eval", "--policy", "handcrafted", "--episodes", "0"], "must be an int >= 1"),
    ],
)
def test_bad_arguments_are_rejected_before_running(argv, message, capsys):
    with pytest.raises(SystemExit):
        main(argv)
    assert message in capsys.readouterr().err


def test_json_write_is_atomic(tmp_path):
    path = tmp_path / "results.json"
    write_json_atomic(path, {"ok": 1})
    with pytest.raises(TypeError):
        write_json_atomic(path, {"bad": object()})
    assert json.loads(path.read_text()) == {"ok": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]


def test_outputs_and_sizes_are_checked_before_the_evaluation(tmp_path, capsys, monkeypatch):
    import snac_jax.evaluation

    monkeypatch.setattr(snac_jax.evaluation, "evaluate_task", lambda *a, **k: pytest.fail("evaluated first"))
    (tmp_path / "file").write_text("")
    for target, message in ((tmp_path, "is a directory"), (tmp_path / "file" / "out.json", "is not a directory")):
        code = main(["eval", "--policy", "random", "--task", "1d-static-sin", "--json", str(target)])
        err = capsys.readouterr().err
        assert code == 2 and err.startswith("snac eval: error: --json ") and message in err
    monkeypatch.undo()
    code = main(["eval", "--policy", "random", "--task", "1d-dynamic", "--episodes", "1000000000"])
    err = capsys.readouterr().err
    assert code == 2 and "snac eval: error: 10,000,000,000 episodes at once needs about" in err


def test_a_policy_for_another_task_is_not_scored(capsys, monkeypatch):
    """The registry's random policy sized for 2D (5 actions) on a 1D task (3): refused."""
    from snac_jax.policies import random as random_module
    from snac_jax.policy import uniform_random_policy

    monkeypatch.setattr(random_module, "random_policy", lambda env, **options: uniform_random_policy(5))
    code = main(["eval", "--policy", "random", "--task", "1d-static-sin", "--episodes", "2"])
    err = capsys.readouterr().err
    assert code == 2 and "outside 0..2" in err and "not scored" in err


# --- switches and teams ----------------------------------------------------------------------------


def _protocol_fields(entry: dict) -> dict:
    """The protocol's numbers of an entry: not its wall time, nor the overrides written beside them."""
    return {k: v for k, v in entry.items() if k not in ("wall_s", "overrides")}


@pytest.mark.slow
def test_switches_build_the_evaluated_tasks(tmp_path, capsys):
    """`--switches stride_probs=1/0/0` scores the tasks `evaluate_task` scores with that override,
    not the task as defined."""
    from snac_jax.evaluation import evaluate_task
    from snac_jax.policies.handcrafted import handcrafted_policy

    out = tmp_path / "out.json"
    argv = ["eval", "--policy", "handcrafted", "--task", "2d-static-sparse", "--episodes", "3", "--seed", "5"]
    assert main([*argv, "--switches", "stride_probs=1/0/0", "--json", str(out)]) == 0
    assert "with the switches {'stride_probs': (1.0, 0.0, 0.0)}" in capsys.readouterr().err
    switched = json.loads(out.read_text())["2d-static-sparse"]
    expected = evaluate_task("2d-static-sparse", handcrafted_policy, static_episodes=3, seed=5, stride_probs=(1, 0, 0))
    assert _protocol_fields(switched) == _protocol_fields(expected.to_json())
    plain = evaluate_task("2d-static-sparse", handcrafted_policy, static_episodes=3, seed=5)
    assert _protocol_fields(switched) != _protocol_fields(plain.to_json())
    assert switched["overrides"] == {"stride_probs": [1.0, 0.0, 0.0]}  # what it was scored with travels with it
    assert main([*argv, "--switches", "stride_probs=1/0/0"]) == 0
    printed = capsys.readouterr().out
    assert "(no paper row)" in printed and "| 0.655 | 0.143 |" not in printed  # the paper scored the task as it is


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["--policy", "handcrafted", "--switches", "foo=1"],
            "unknown switch 'foo'; allowed: gps, stride_probs, obstacles, landmarks, reward_scheme",
        ),
        (
            ["--policy", "handcrafted", "--task", "all", "--switches", "reward_scheme=nope"],
            "reward_scheme must be one of ('height', 'binary'), got 'nope'",
        ),
        (["--policy", "handcrafted", "--task", "1d-static-sin", "--switches", "obstacles=true"], "obstacles"),
        (
            ["--checkpoint", "runs/none", "--switches", "gps=true"],
            "--switches: a checkpoint is scored with its run's own switches and robots",
        ),
        (["--checkpoint", "runs/none", "--robots", "2"], "--robots: a checkpoint is scored with its run's own"),
        (
            ["--policy", "handcrafted", "--robots", "4", "--task", "all"],
            "num_robots must be an int in 1..2 for 1d-static-sin (one per end of the row), got 4",
        ),
        (
            [
                "--policy",
                "handcrafted",
                "--robots",
                "2",
                "--task",
                "2d-dynamic-dense",
                "--switches",
                "design_change=100/300",
            ],
            "design_change is a single-robot switch",
        ),
        (
            ["--policy", "handcrafted", "--robots", "2", "--task", "2d-static-dense", "--devices", "2"],
            "--devices 2: a team's episodes run on one device",
        ),
    ],
)
def test_bad_switches_and_robots_are_one_line_errors_before_anything_runs(argv, message, capsys, monkeypatch):
    import snac_jax.evaluation
    import snac_jax.multi.evaluation

    monkeypatch.setattr(snac_jax.evaluation, "evaluate_task", lambda *a, **k: pytest.fail("evaluated first"))
    monkeypatch.setattr(snac_jax.multi.evaluation, "evaluate_team_task", lambda *a, **k: pytest.fail("evaluated first"))
    code = main(["eval", *argv, "--episodes", "1"])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_team_of_one_is_the_single_robot(tmp_path, capsys):
    """In 1D the handcrafted policy draws no randomness, and one robot is the single-robot env
    (SPEC §13), so `--robots 1` scores the same episodes as the single robot. Two robots share
    the same budget and step limit; an episode ends before the limit exactly when it is shorter."""
    outs = {name: tmp_path / f"{name}.json" for name in ("single", "one", "two")}
    argv = ["eval", "--policy", "handcrafted", "--task", "1d-static-sin", "--episodes", "3", "--seed", "7"]
    assert main([*argv, "--json", str(outs["single"])]) == 0
    assert main([*argv, "--robots", "1", "--json", str(outs["one"])]) == 0
    assert main([*argv, "--robots", "2", "--json", str(outs["two"])]) == 0
    assert "a team of 2 robot(s)" in capsys.readouterr().out
    single, one, two = (json.loads(outs[name].read_text())["1d-static-sin"] for name in ("single", "one", "two"))
    assert {
        k: v for k, v in _protocol_fields(one).items() if k not in ("robots", "max_steps", "finished_fraction")
    } == _protocol_fields(single)
    assert one["robots"] == 1 and two["robots"] == 2 and one["max_steps"] == two["max_steps"] == 750
    assert one["finished_fraction"] == 1.0 and one["mean_length"] < 750  # the single robot spends its budget
    assert two["mean_bricks_used"] <= 600 and two["episodes"] == 3
    assert (two["finished_fraction"] == 0.0) == (two["mean_length"] == 750)


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_a_team_checkpoint_is_scored_as_its_training_scored_it(tmp_path, capsys):
    """`snac eval --checkpoint` of an ippo run: the team, its robots and step limit from the run,
    the same numbers as the run's own evaluation (`evaluate_team`) on the same key."""
    run = tmp_path / "run"
    code = main(
        [
            "train",
            "ippo",
            "--robots",
            "2",
            "--task",
            "1d-static-sin",
            "--total-steps",
            "32",
            "--chunks",
            "1",
            "--max-steps",
            "20",
            "--eval-episodes",
            "3",
            "--out",
            str(run),
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
    )
    assert code == 0, capsys.readouterr().err[-2000:]
    out = tmp_path / "eval.json"
    assert main(["eval", "--checkpoint", str(run), "--episodes", "3", "--json", str(out)]) == 0
    assert "a team of 2 robot(s)" in capsys.readouterr().out
    entry = json.loads(out.read_text())["1d-static-sin"]
    trained = json.loads((run / "eval.json").read_text())["1d-static-sin"]
    assert entry["robots"] == 2 and entry["max_steps"] == 20 and entry["mean_length"] <= 20
    assert {k: entry[k] for k in _protocol_fields(trained)} == _protocol_fields(trained)
