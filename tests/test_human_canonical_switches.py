"""The game's switches text: one canonical form for switches that parse equal, which records
written in any spelling compare and group by; and `verify_record`'s one-line error for a record
whose world cannot be built."""

from __future__ import annotations

import json
import re

import pytest

from snac_jax.human import records
from snac_jax.human.game import GameSession, canonical_switches
from snac_jax.tasks import format_switches, parse_switches


@pytest.fixture(autouse=True)
def headless(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("SDL_AUDIODRIVER", "dummy")


@pytest.mark.parametrize(
    "typed, canonical",
    [
        ("landmarks=4,design_change=100/300", "landmarks=4,design_change=100/300"),
        ("design_change=100/300,landmarks=4", "landmarks=4,design_change=100/300"),
        ("landmarks=04, design_change = 0100/300", "landmarks=4,design_change=100/300"),
        ("design_change=100/300,landmark_action=2,landmarks=4", "landmarks=4,landmark_action=2,design_change=100/300"),
        ("stride_probs=1/0/0,gps=True", "gps=true,stride_probs=1/0/0"),
        ("stride_probs=1.0/0.0/0.0", "stride_probs=1/0/0"),
        ("stride_probs=0.50/0.25/0.250", "stride_probs=0.5/0.25/0.25"),
        ("stride_probs=5e-1/25E-2/0.25", "stride_probs=0.5/0.25/0.25"),
        ("reward_scheme=height,obstacles=FALSE", "obstacles=false,reward_scheme=height"),
        ("landmarks=true", "landmarks=true"),
        (" , ", ""),
    ],
)
def test_switches_that_parse_equal_have_one_canonical_text(typed, canonical):
    assert canonical_switches(typed) == canonical
    assert canonical_switches(canonical) == canonical  # the canonical text is its own canonical form
    assert parse_switches(canonical) == parse_switches(typed)  # and means the same switches


def test_format_switches_refuses_a_key_parse_switches_would_not_give():
    with pytest.raises(ValueError, match=r"^unknown switch 'max_steps'; allowed: gps, stride_probs, "):
        format_switches({"max_steps": 5})


def _game(switches, record_path):
    session = GameSession("1d-dynamic", "eval", seed=2, max_steps=3, switches=switches, record_path=record_path)
    for key in ("space", "right", "space"):
        session.press(key)
    return session.records[0]


@pytest.mark.slow
def test_a_record_in_another_spelling_loads_verifies_and_shares_the_canonical_row(tmp_path):
    """A record written by a game that kept the switches as typed: it loads and replays as it is,
    and its games join the row of the same switches in canonical text."""
    path = tmp_path / "human.jsonl"
    played = _game("design_change=01/2, landmarks=0", path)
    assert played.switches == "landmarks=0,design_change=1/2"
    line = json.loads(played.to_json())
    with path.open("a") as f:
        f.write(json.dumps({**line, "switches": "design_change=01/2, landmarks=0", "player": "old"}) + "\n")
    mine, old = records.load_records(path)
    assert old.switches == "design_change=01/2, landmarks=0" and old.player == "old"
    assert canonical_switches(old.switches) == mine.switches
    records.verify_record(old)
    [result] = records.summarize_records([mine, old])
    assert result.task == "1d-dynamic (landmarks=0,design_change=1/2)" and result.episodes == 2


@pytest.mark.parametrize(
    "switches, message",
    [
        ("landmarks=-1", r"landmarks must be an int >= 0, got -1"),
        ("design_change=5/3", r"design_change must be two ints \(a, b\) with 1 <= a <= b < max_steps"),
        ("wings=true", r"unknown switch 'wings'; allowed: gps, "),
    ],
)
def test_a_record_whose_world_cannot_be_built_is_a_one_line_error_naming_it(switches, message):
    honest = _game("", None)
    broken = records.EpisodeRecord(**{**vars(honest), "switches": switches})
    with pytest.raises(ValueError) as caught:
        records.verify_record(broken)
    text = str(caught.value)
    assert text.startswith("record of 1d-dynamic seed 2: ") and "\n" not in text
    assert re.search(message, text), text
