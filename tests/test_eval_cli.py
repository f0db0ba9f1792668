"""`snac eval` end to end on a tiny budget: the table, the JSON, bad input, atomic writes."""

from __future__ import annotations

import json

import pytest

from snac_jax.cli import main
from snac_jax.atomic import atomic_write_json as write_json_atomic


def test_eval_prints_table_beside_the_paper_and_writes_json(tmp_path, capsys):
    out = tmp_path / "results" / "handcrafted.json"
    code = main(
        ["eval", "--policy", "handcrafted", "--task", "2d-static-sparse", "--episodes", "2", "--seed", "4", "--json", str(out)]
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
    main(["eval", "--policy", "handcrafted", "--task", "2d-static-sparse", "--episodes", "2", "--paper-results", str(paper)])
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
