"""The human-play game: key bindings, a scripted headless episode, the JSONL record, its summary."""

from __future__ import annotations

import functools
import json
import os
import sys

import numpy as np
import pytest

from snac_jax import designs, make
from snac_jax.human import records, window
from snac_jax.human.game import GameSession, key_bindings, key_legend


@pytest.fixture(autouse=True)
def headless(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("SDL_AUDIODRIVER", "dummy")


def test_key_bindings_follow_the_action_tables():
    config_1d = make("1d-static-sin")[0].config
    config_2d = make("2d-static-dense")[0].config
    config_3d = make("3d-static-dense")[0].config
    assert key_bindings(config_1d) == {"left": 0, "right": 1, "space": 2}
    assert key_bindings(config_2d) == {"left": 0, "right": 1, "down": 2, "up": 3, "space": 4}
    assert key_bindings(config_3d) == {"left": 0, "right": 1, "down": 2, "up": 3, "a": 4, "d": 5, "s": 6, "w": 7}
    assert key_bindings(make("2d-static-dense", obstacles=True)[0].config) == key_bindings(config_3d)
    assert "W=up" in key_legend(config_3d) and "space" not in key_legend(config_3d)


def test_scripted_headless_episode_is_recorded(tmp_path):
    path = tmp_path / "human.jsonl"
    session = GameSession("2d-static-sparse", "train", seed=5, max_steps=6, record_path=path, player="t")
    script = ["right", "x", "down", "space", "right", "space", "left", "return"]  # "x" is not bound
    assert window.run_window(session, max_episodes=1, script=script) == 1
    [record] = records.load_records(path)
    assert record.task == "2d-static-sparse" and record.mode == "train" and record.seed == 5
    assert record.actions == [1, 2, 4, 1, 4, 0] and record.steps == 6
    assert len(record.strides) == 6 and set(record.strides) <= {1, 2, 3}
    assert not record.terminated  # the step limit ended it
    assert record.iou == pytest.approx(records.replay_iou(record), abs=1e-7)
    assert record.bricks_used == 2 and record.duration_s >= 0 and record.player == "t"
    np.testing.assert_array_equal(record.design, designs.fixed_design("2d-static-sparse"))
    assert "IoU" in session.status_lines()[-2]
    # Every line is a complete JSON object.
    lines = path.read_text().splitlines()
    assert len(lines) == 1 and json.loads(lines[0])["actions"] == record.actions


def test_a_second_episode_and_quitting_mid_episode(tmp_path):
    path = tmp_path / "human.jsonl"
    session = GameSession("1d-static-step", "eval", seed=0, max_steps=3, record_path=path)
    script = ["space", "right", "space", "return", "space", "escape"]
    assert window.run_window(session, script=script) == 1  # the unfinished second episode is not saved
    assert session.episode_index == 1 and session.episode_seed == 1
    assert len(records.load_records(path)) == 1


def test_modes_show_rewards_only_in_training():
    train = GameSession("3d-static-sparse", "train", max_steps=4)
    evaluation = GameSession("3d-static-sparse", "eval", max_steps=4)
    for session in (train, evaluation):
        for key in ("d", "d", "right", "s"):
            session.press(key)
        assert session.over
    assert "reward" in train.status_lines()[1] and "total" in train.status_lines()[1]
    assert "reward" not in "".join(evaluation.status_lines())
    assert evaluation.status_lines()[1].startswith("step 4/4")
    frame = evaluation.frame()
    assert frame.dtype == np.uint8 and frame.shape == train.frame().shape


def test_eval_mode_cycles_the_test_designs_of_a_dynamic_task():
    session = GameSession("2d-dynamic-dense", "eval", max_steps=1)
    for index in range(2):
        assert session.test_design == index
        expected = designs.fixed_design(f"2d-dynamic-dense-test{index}")
        np.testing.assert_array_equal(np.asarray(session.state.design), expected)
        session.press("space")
        assert session.over
        session.new_episode()


def test_append_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "human.jsonl"
    session = GameSession("1d-static-sin", "eval", max_steps=2, record_path=path)
    session.press("space")
    session.press("space")
    before = path.read_bytes()

    def crash(*args):
        raise OSError("disk gone")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError):
        records.append_record(path, session.records[0])
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["human.jsonl"]  # no temporary file left


def test_summary_matches_the_records_and_catches_a_false_iou(tmp_path):
    path = tmp_path / "human.jsonl"
    session = GameSession("2d-static-dense", "eval", seed=1, max_steps=5, record_path=path)
    for _ in range(3):
        for key in ("space", "right", "space", "down", "space"):
            session.press(key)
        session.new_episode()
    loaded = records.load_records(path)
    [result] = records.summarize_records(loaded)
    assert result.task == "2d-static-dense" and result.episodes == 3
    assert result.mean == pytest.approx(np.mean([r.iou for r in loaded]))
    assert result.min == pytest.approx(min(r.iou for r in loaded))
    assert result.mean_length == 5
    forged = [records.EpisodeRecord(**{**vars(loaded[0]), "iou": min(loaded[0].iou + 0.25, 1.0)})]
    with pytest.raises(ValueError, match="replay"):
        records.summarize_records(forged)
    path.write_text(path.read_text() + '{"task": "2d-static-dense"}\n')
    with pytest.raises(ValueError, match=":4:"):
        records.load_records(path)


def test_play_command_runs_a_scripted_episode(tmp_path, monkeypatch, capsys):
    from snac_jax.cli import main

    scripted = functools.partial(window.run_window, script=["space", "space", "return"])
    monkeypatch.setattr(window, "run_window", scripted)
    path = tmp_path / "h.jsonl"
    rc = main(
        [
            "play",
            "--task",
            "1d-dynamic",
            "--mode",
            "eval",
            "--max-steps",
            "2",
            "--episodes",
            "1",
            "--record",
            str(path),
            "--seed",
            "7",
        ]
    )
    assert rc == 0
    [record] = records.load_records(path)
    assert record.test_design == 0 and record.seed == 7 and record.actions == [2, 2]
    assert "appended" in capsys.readouterr().out


def test_human_report_is_the_evaluator_table_beside_the_paper(tmp_path):
    path = tmp_path / "human.jsonl"
    session = GameSession("2d-static-sparse", "eval", max_steps=3, record_path=path)
    for key in ("space", "right", "space"):
        session.press(key)
    report = records.human_report(path)
    row = next(line for line in report.splitlines() if line.startswith("| 2d-static-sparse"))
    assert f"{session.records[0].iou:.3f}" in row
    assert "0.606" in row  # the paper's human mean on 2d-static-sparse, from paper_results.json
    with pytest.raises(ValueError, match="train mode"):
        records.human_report(path, mode="train")


def test_snac_eval_human_prints_the_summary(tmp_path, capsys):
    from snac_jax.cli import main

    path = tmp_path / "human.jsonl"
    session = GameSession("2d-static-sparse", "eval", max_steps=3, record_path=path)
    for key in ("space", "right", "space"):
        session.press(key)
    assert main(["eval", "--human", str(path)]) == 0
    out = capsys.readouterr().out
    assert "| 2d-static-sparse | 1 |" in out and "0.606" in out
    assert main(["eval", "--human", str(path), "--policy", "random"]) == 2
    assert "snac eval: error: give exactly one of" in capsys.readouterr().err


def _honest_record(task="2d-static-sparse", mode="eval", keys=("space", "right", "space"), **kwargs):
    session = GameSession(task, mode, seed=3, max_steps=len(keys), **kwargs)
    for key in keys:
        session.press(key)
    [record] = session.records
    records.verify_record(record)  # the honest record passes
    return record


def _doctored(record, **changes):
    return records.EpisodeRecord(**{**vars(record), **changes})


def test_doctored_records_are_refused():
    honest = _honest_record()
    one_brick = np.zeros((20, 20), int)
    one_brick[0, 0] = 1
    cases = {
        "actions must be in 0..4, got 7": dict(actions=[7, *honest.actions[1:]]),
        "actions must be ints >= 0": dict(actions=[-1, *honest.actions[1:]]),
        "more than the step limit": dict(actions=honest.actions + [4], strides=honest.strides + [1]),
        "design must be 20 x 20": dict(design=[[1]]),
        "its design is not its test design|its design is not the design": dict(design=one_brick.tolist()),
        "claims IoU": dict(iou=min(1.0, honest.iou + 0.1)),
        "claims bricks used 3": dict(bricks_used=3),
        "claims total reward": dict(total_reward=honest.total_reward + 5),
        "claims terminated True": dict(terminated=True),
        "has not ended after its 3 actions": dict(max_steps=4),
        "test_design must be null": dict(test_design=2),
    }
    for message, changes in cases.items():
        with pytest.raises(ValueError, match=message):
            records.verify_record(_doctored(honest, **changes))
    with pytest.raises(ValueError, match="claims bricks used"):
        records.summarize_records([_doctored(honest, bricks_used=0)])


def test_a_one_brick_design_cannot_score_on_a_20x20_task(tmp_path, capsys):
    """The forged record of the issue: a one-brick design, one drop on it, IoU 1 claimed."""
    honest = _honest_record(keys=("space",))
    design = np.zeros((20, 20), int)
    design[0, 0] = 1
    forged = _doctored(honest, design=design.tolist(), iou=1.0, total_reward=5.0)
    assert records.replay_iou(forged) == 1.0  # the replay alone would believe it
    path = tmp_path / "forged.jsonl"
    records.append_record(path, forged)
    with pytest.raises(ValueError, match="its design is not"):
        records.human_report(path)
    from snac_jax.cli import main

    assert main(["eval", "--human", str(path)]) == 2
    err = capsys.readouterr().err
    assert (
        err.startswith("snac eval: error: record of 2d-static-sparse seed 3: its design is not")
        and err.count("\n") == 1
    )


def test_dynamic_records_must_hold_the_design_the_game_gives():
    test = _honest_record("1d-dynamic", "eval", keys=("space", "space"))
    with pytest.raises(ValueError, match="its design is not its test design"):
        records.verify_record(_doctored(test, test_design=(test.test_design + 1) % 10))
    trained = _honest_record("1d-dynamic", "train", keys=("space", "space"))
    other = _honest_record("1d-dynamic", "train", keys=("space", "space"), player="other")
    with pytest.raises(ValueError, match="not the design the game gives this episode"):
        records.verify_record(_doctored(trained, seed=trained.seed + 1))
    assert trained.design == other.design  # the seed alone decides it


def test_play_checks_the_record_path_before_opening_the_window(tmp_path, monkeypatch, capsys):
    from snac_jax.cli import main

    monkeypatch.setattr(window, "run_window", lambda *a, **k: pytest.fail("the window opened"))
    (tmp_path / "file").write_text("")
    for record, message in ((tmp_path, "is a directory"), (tmp_path / "file" / "h.jsonl", "is not a directory")):
        assert main(["play", "--task", "1d-static-sin", "--record", str(record)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("snac play: error: record file ") and message in err


def test_play_without_a_display_refuses_in_one_line(tmp_path, monkeypatch, capsys):
    """On Linux with no DISPLAY, WAYLAND_DISPLAY or SDL_VIDEODRIVER, `snac play` says so in one
    line before pygame opens anything (SDL would find no video device and the game would hang)."""
    pytest.importorskip("pygame")
    from snac_jax.cli import main

    for name in window.DISPLAY_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(sys, "platform", "linux")  # where the check applies (macOS and Windows have a display)
    record = tmp_path / "h.jsonl"
    assert main(["play", "--task", "1d-static-sin", "--record", str(record)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and err.startswith("snac play: error: no display to open the game window on")
    assert "SDL_VIDEODRIVER=dummy" in err and not record.exists()


@pytest.mark.parametrize(
    ("environ", "platform"),
    [({"DISPLAY": ":0"}, "linux"), ({"WAYLAND_DISPLAY": "wayland-0"}, "linux"), ({"SDL_VIDEODRIVER": "dummy"}, "linux")]
    + [({}, platform) for platform in ("darwin", "win32")],
)
def test_a_display_variable_or_a_desktop_platform_lets_the_window_open(environ, platform):
    window.check_display(environ, platform)  # no error


def test_a_finished_episode_is_never_dropped(tmp_path, monkeypatch, capsys):
    """The record file fails when the episode ends (disk full, permissions changed): the episode
    is kept, written to a file in the temporary folder, and the command says where."""
    from snac_jax.cli import main
    from snac_jax.human import game

    def full_disk(path, record):
        if os.path.basename(path) == "h.jsonl":
            raise OSError(28, "No space left on device")
        return records.append_record(path, record)

    monkeypatch.setattr(game, "append_record", full_disk)
    monkeypatch.setattr(game.tempfile, "gettempdir", lambda: str(tmp_path))
    monkeypatch.setattr(window, "run_window", functools.partial(window.run_window, script=["space", "space", "return"]))
    rc = main(
        [
            "play",
            "--task",
            "1d-static-sin",
            "--max-steps",
            "2",
            "--episodes",
            "1",
            "--record",
            str(tmp_path / "h.jsonl"),
        ]
    )
    err = capsys.readouterr().err
    assert rc == 1 and "1 episode(s) could not be appended" in err and "No space left on device" in err
    [saved] = tmp_path.glob("snac-play-unsaved-*.jsonl")
    [record] = records.load_records(saved)
    assert record.actions == [2, 2] and str(saved) in err
    records.verify_record(record)
