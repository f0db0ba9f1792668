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
