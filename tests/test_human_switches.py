"""Human play with environment switches: landmark placements (SPEC §14) and design changes
(SPEC §15) are recorded with their switches and replay to the game's own episode."""

from __future__ import annotations

import functools
import json
import re

import numpy as np
import pytest

from snac_jax import designs
from snac_jax.design_change import scheduled_step
from snac_jax.human import records, window
from snac_jax.human.game import GameSession, canonical_switches


@pytest.fixture(autouse=True)
def headless(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("SDL_AUDIODRIVER", "dummy")


def _assert_same_state(replayed, played):
    for name, value in vars(played).items():
        if value is None:
            assert getattr(replayed, name) is None, name
        else:
            np.testing.assert_array_equal(np.asarray(getattr(replayed, name)), np.asarray(value), err_msg=name)


def _test_design(task, index):
    return designs.fixed_design(f"{task}-test{index}")


def test_a_landmark_game_is_recorded_with_its_switches_and_replays_to_the_same_state(tmp_path):
    path = tmp_path / "human.jsonl"
    session = GameSession(
        "2d-static-sparse", "train", seed=5, max_steps=6, switches=" landmark_action = 2 ", record_path=path
    )
    assert session.bindings["l"] == 5 and "L: landmark" in session.status_lines()[2]
    script = ["l", "right", "l", "l", "space", "down", "return"]  # the third L: none left, a step all the same
    assert window.run_window(session, max_episodes=1, script=script) == 1
    [record] = records.load_records(path)
    assert record.switches == "landmark_action=2" and record.actions == [5, 1, 5, 5, 4, 2]
    final = session.state
    assert int(final.landmarks_left) == 0 and int(final.time) == 6
    placed = np.argwhere(np.asarray(final.landmarks)).tolist()
    # plan (0, 0) and plan (0, stride of the move), padding 3 on each side
    assert placed == [[3, 3], [3, 3 + record.strides[1]]]
    out = records.replay_record(record)
    _assert_same_state(out["final_state"], final)
    assert out["final_iou"] == pytest.approx(record.iou, abs=1e-7)
    records.verify_record(record)
    # Replayed without its switches, the placements are actions the task does not have.
    with pytest.raises(ValueError, match=r"actions must be in 0\.\.4, got 5"):
        records.verify_record(records.EpisodeRecord(**{**vars(record), "switches": ""}))


def test_without_the_switch_the_landmark_key_does_nothing():
    session = GameSession("2d-static-sparse", "train", max_steps=3)
    assert "l" not in session.bindings and not session.press("l") and session.actions == []


def test_eval_mode_meets_the_evaluators_design_change_and_replays_it():
    task = "2d-dynamic-dense"
    session = GameSession(task, "eval", seed=3, max_steps=12, switches="design_change=1/10")
    # The protocol's schedule: test design i changes to i + 1 at step 1 + floor(9 i / 9) = 1 + i.
    assert [scheduled_step(session.config, i, 10) for i in range(10)] == list(range(1, 11))
    played = []
    for index in range(2):
        assert session.test_design == index
        np.testing.assert_array_equal(np.asarray(session.state.design), _test_design(task, index))
        for step in range(1, 13):
            session.press("space" if step % 2 else "right")
            now = index if step < 1 + index else index + 1
            np.testing.assert_array_equal(np.asarray(session.state.design), _test_design(task, now))
        assert session.over
        played.append(session.state)
        session.new_episode()
    for record, final in zip(session.records, played):
        np.testing.assert_array_equal(record.design, _test_design(task, record.test_design))  # the start design
        assert record.switches == "design_change=1/10"
        records.verify_record(record)
        out = records.replay_record(record)
        _assert_same_state(out["final_state"], final)
        assert out["final_iou"] == pytest.approx(record.iou, abs=1e-7)
        # Without the switch the replay keeps the first design: the record's switches decide the change.
        plain = records.replay_record(records.EpisodeRecord(**{**vars(record), "switches": ""}))
        np.testing.assert_array_equal(np.asarray(plain["final_state"].design), record.design)


def test_a_training_game_with_a_design_change_replays_the_same_change():
    session = GameSession("1d-dynamic", "train", seed=4, max_steps=3, switches="design_change=1/2")
    for key in ("space", "right", "space"):
        session.press(key)
    [record] = session.records
    final = session.state
    assert not np.array_equal(np.asarray(final.design), record.design)  # it changed, from the reset key
    assert int(final.change_step) in (1, 2)
    records.verify_record(record)
    _assert_same_state(records.replay_record(record)["final_state"], final)


def test_an_old_record_without_switches_loads_and_verifies(tmp_path):
    session = GameSession("2d-static-sparse", "eval", seed=3, max_steps=3)
    for key in ("space", "right", "space"):
        session.press(key)
    line = json.loads(session.records[0].to_json())
    assert line.pop("switches") == ""
    path = tmp_path / "old.jsonl"
    path.write_text(json.dumps(line) + "\n")
    [record] = records.load_records(path)
    assert record.switches == "" and record == session.records[0]
    records.verify_record(record)
    path.write_text(json.dumps({**line, "switches": "wings=true"}) + "\n")
    with pytest.raises(ValueError, match=r"old.jsonl:1: .*unknown switch 'wings'; allowed: gps, "):
        records.load_records(path)


def test_switched_games_form_their_own_row_of_the_summary(tmp_path):
    path = tmp_path / "human.jsonl"
    for switches in ("", "landmark_action=2"):
        session = GameSession("2d-static-sparse", "eval", max_steps=3, switches=switches, record_path=path)
        for key in ("space", "right", "space"):
            session.press(key)
    report = records.human_report(path)
    plain = next(line for line in report.splitlines() if line.startswith("| 2d-static-sparse | 1 |"))
    switched = next(
        line for line in report.splitlines() if line.startswith("| 2d-static-sparse (landmark_action=2) | 1 |")
    )
    assert "0.606" in plain and "0.606" not in switched and "—" in switched


def test_canonical_switches_drops_spaces_and_checks_keys():
    assert canonical_switches(" landmark_action = 2 , gps=true,") == "gps=true,landmark_action=2"
    assert canonical_switches("") == ""
    with pytest.raises(ValueError, match="unknown switch 'max_steps'"):
        canonical_switches("max_steps=5")


@pytest.mark.parametrize(
    "switches, message",
    [
        (
            "wings=true",
            r"unknown switch 'wings'; allowed: gps, stride_probs, obstacles, landmarks, reward_scheme, "
            r"landmark_action, design_change$",
        ),
        ("landmark_action=999", r"landmark_action must be .*0\.\.400"),
        ("design_change=5/3", r"design_change must be two ints \(a, b\) with 1 <= a <= b < max_steps"),
        ("landmark_action", r"must be key=value; allowed keys: gps, "),
    ],
)
def test_a_bad_switch_is_a_one_line_error_before_the_window(tmp_path, monkeypatch, capsys, switches, message):
    from snac_jax.cli import main

    monkeypatch.setattr(window, "run_window", lambda *a, **k: pytest.fail("the window opened"))
    record = tmp_path / "h.jsonl"
    rc = main(["play", "--task", "2d-dynamic-dense", "--switches", switches, "--record", str(record)])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("snac play: error: ") and err.count("\n") == 1
    assert re.search(message, err.strip()), err
    assert not record.exists()


def test_play_command_passes_the_switches_and_its_help_names_the_l_key(tmp_path, monkeypatch, capsys):
    from snac_jax.cli import build_parser, main

    monkeypatch.setattr(window, "run_window", functools.partial(window.run_window, script=["l", "l", "return"]))
    path = tmp_path / "h.jsonl"
    rc = main(
        [
            "play",
            "--task",
            "3d-static-sparse",
            "--switches",
            "landmark_action=1",
            "--max-steps",
            "2",
            "--episodes",
            "1",
            "--record",
            str(path),
        ]
    )
    assert rc == 0
    [record] = records.load_records(path)
    assert record.switches == "landmark_action=1" and record.actions == [8, 8]  # the second finds none left
    records.verify_record(record)
    capsys.readouterr()
    with pytest.raises(SystemExit):
        build_parser().parse_args(["play", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "--switches" in help_text and "with the L key" in help_text and "landmark_action=4" in help_text
