"""bench/multi_results.py: a tiny run's JSON and table, one robot against the single-robot
evaluation, and bad arguments refused before anything runs."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _bench():
    spec = importlib.util.spec_from_file_location("multi_results", ROOT / "bench" / "multi_results.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_tiny_run_writes_rows_and_one_robot_is_the_single_robot(tmp_path, capsys):
    """1D: the handcrafted policy draws no randomness and one robot is the single-robot env step
    for step (SPEC §13), so N = 1 scores the single robot's IoUs on the same keys. (In 2D the
    split gives each robot a key of its own, so the episodes differ from the single robot's.)"""
    from snac_jax.evaluation import evaluate_task
    from snac_jax.policies.handcrafted import handcrafted_policy

    bench = _bench()
    assert (
        bench.main(
            [
                "--out",
                str(tmp_path),
                "--tasks",
                "1d-static-sin",
                "--robots",
                "1",
                "2",
                "--episodes",
                "2",
                "--seed",
                "11",
            ]
        )
        == 0
    )
    data = json.loads((tmp_path / "multi_results.json").read_text())
    assert data["context"]["seed"] == 11 and data["context"]["episodes_per_design"] == 2
    one, two = data["rows"]
    assert (one["task"], one["robots"], two["robots"]) == ("1d-static-sin", 1, 2)
    for row in (one, two):
        assert row["episodes"] == 2 and row["max_steps"] == 750
        assert row["ci95"][0] <= row["mean_iou"] <= row["ci95"][1] and 0.0 <= row["min_iou"] <= row["mean_iou"] <= 1.0
        assert row["mean_length"] <= 750 and 0.0 <= row["finished_fraction"] <= 1.0
        assert row["mean_bricks_used"] <= 600  # the team shares the task's budget
    single = evaluate_task("1d-static-sin", handcrafted_policy, static_episodes=2, seed=11)
    assert (one["mean_iou"], one["min_iou"], one["mean_length"]) == (single.mean, single.min, single.mean_length)
    table = (tmp_path / "multi_results.md").read_text()
    assert "| 1d-static-sin | 2 | 2 |" in table and table in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--tasks", "1d-static-sin", "--robots", "4"], "num_robots must be an int in 1..2 for 1d-static-sin"),
        (["--tasks", "2d-nope"], "unknown task '2d-nope'"),
        (["--robots", "0"], "must be an int >= 1"),
    ],
)
def test_bad_arguments_are_refused_before_anything_runs(tmp_path, argv, message, capsys):
    with pytest.raises(SystemExit):
        _bench().main(["--out", str(tmp_path / "out"), *argv])
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out" / "multi_results.json").exists()
