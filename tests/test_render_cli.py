"""`snac render`: one episode to a GIF with the documented number of frames."""

from __future__ import annotations

import re

import imageio.v3 as iio
import numpy as np
import pytest

from snac_jax.cli import main
from snac_jax.cli.render import frame_indices
from snac_jax.rendering import CAPTION_HEIGHT


def test_frame_indices_always_end_on_the_last_state():
    assert frame_indices(12, 5) == [0, 5, 10, 12]
    assert frame_indices(10, 5) == [0, 5, 10]
    assert frame_indices(3, 1) == [0, 1, 2, 3]


@pytest.mark.parametrize(
    "task, policy, every",
    [("1d-static-gauss", "random", 1), ("2d-dynamic-dense", "handcrafted", 4), ("3d-static-sparse", "random", 3)],
)
def test_render_writes_a_gif_with_one_frame_per_drawn_state(tmp_path, capsys, task, policy, every):
    out = tmp_path / "run.gif"
    rc = main(
        [
            "render",
            "--task",
            task,
            "--policy",
            policy,
            "--out",
            str(out),
            "--max-steps",
            "14",
            "--every",
            str(every),
            "--seed",
            "3",
        ]
    )
    assert rc == 0
    printed = capsys.readouterr().out
    steps = int(re.search(r"(\d+) steps", printed).group(1))
    assert 1 <= steps <= 14
    frames = iio.imread(out, index=None)
    assert frames.shape[0] == len(frame_indices(steps, every))
    assert frames.shape[-1] == 3 and frames.shape[1] > 2 * CAPTION_HEIGHT
    assert not np.array_equal(frames[0], frames[-1])  # the counters (at least) changed
    assert [p.name for p in tmp_path.iterdir()] == ["run.gif"]


def test_render_rejects_bad_requests(tmp_path, capsys):
    assert main(["render", "--task", "2d-static-dense", "--out", str(tmp_path / "x.png")]) == 2
    assert "gif" in capsys.readouterr().err
    # a policy or a checkpoint, not both
    rc = main(
        [
            "render",
            "--task",
            "2d-static-dense",
            "--policy",
            "handcrafted",
            "--checkpoint",
            str(tmp_path),
            "--out",
            str(tmp_path / "x.gif"),
        ]
    )
    assert rc == 2
    assert "not both" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["render", "--task", "4d-static", "--out", str(tmp_path / "x.gif")])
    assert not list(tmp_path.iterdir())


def test_outputs_and_sizes_are_checked_before_the_episode(tmp_path, capsys, monkeypatch):
    import snac_jax.recording

    monkeypatch.setattr(snac_jax.recording, "record_episode", lambda *a, **k: pytest.fail("ran the episode first"))
    (tmp_path / "file").write_text("")
    rc = main(["render", "--task", "2d-static-dense", "--out", str(tmp_path / "file" / "x.gif")])
    assert rc == 2 and "snac render: error: --out " in capsys.readouterr().err
    rc = main(["render", "--task", "2d-static-dense", "--out", str(tmp_path / "x.gif"), "--cell", "100000"])
    err = capsys.readouterr().err
    assert rc == 2 and "snac render: error: one frame at --cell 100000 needs about" in err and "lower --cell" in err
    with pytest.raises(SystemExit):
        main(["render", "--task", "2d-static-dense", "--out", str(tmp_path / "x.gif"), "--cell", "3"])
    assert "must be an int >= 4" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_a_team_checkpoint_is_drawn_as_its_team(tmp_path, capsys):
    """`snac render --checkpoint` of an ippo run draws its robots in one world: robot 1's colour,
    which no single-robot picture holds, is in every frame, and the frame count is the one
    documented for the episode's length."""
    from snac_jax.rendering.robots import ROBOT_COLOURS

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
            "1",
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
    capsys.readouterr()
    out = tmp_path / "team.gif"
    rc = main(
        [
            "render",
            "--task",
            "1d-static-sin",
            "--checkpoint",
            str(run),
            "--out",
            str(out),
            "--max-steps",
            "9",
            "--every",
            "4",
            "--seed",
            "2",
        ]
    )
    assert rc == 0, capsys.readouterr().err[-2000:]
    printed = capsys.readouterr().out
    assert ", 2 robots, seed 2: " in printed
    steps = int(re.search(r"(\d+) steps", printed).group(1))
    assert 1 <= steps <= 9
    frames = iio.imread(out, index=None)
    assert frames.shape[0] == len(frame_indices(steps, 4))
    second = np.all(frames == np.array(ROBOT_COLOURS[1], np.uint8), axis=-1)
    assert second.any(axis=(1, 2)).all()
    single = tmp_path / "single.gif"
    assert (
        main(["render", "--task", "1d-static-sin", "--policy", "random", "--out", str(single), "--max-steps", "2"]) == 0
    )
    assert not np.all(iio.imread(single, index=None) == np.array(ROBOT_COLOURS[1], np.uint8), axis=-1).any()


@pytest.mark.slow
def test_a_registered_policy_is_drawn_as_a_team_of_robots(tmp_path, capsys):
    """`snac render --policy handcrafted --robots 3` draws the handcrafted split's team: robot 2's
    colour, which neither a single robot nor a team of two holds, is in every frame; `--robots`
    with a checkpoint is refused before anything runs."""
    from snac_jax.rendering.robots import ROBOT_COLOURS

    third = np.array(ROBOT_COLOURS[2], np.uint8)
    out = tmp_path / "team.gif"
    args = ["render", "--task", "2d-static-dense", "--policy", "handcrafted", "--max-steps", "6", "--every", "3"]
    assert main([*args, "--robots", "3", "--out", str(out), "--seed", "1"]) == 0
    printed = capsys.readouterr().out
    assert "policy handcrafted-split, 3 robots, seed 1: " in printed
    steps = int(re.search(r"(\d+) steps", printed).group(1))
    frames = iio.imread(out, index=None)
    assert frames.shape[0] == len(frame_indices(steps, 3))
    assert np.all(frames == third, axis=-1).any(axis=(1, 2)).all()
    pair = tmp_path / "pair.gif"
    assert main([*args, "--robots", "2", "--out", str(pair)]) == 0
    assert not np.all(iio.imread(pair, index=None) == third, axis=-1).any()
    capsys.readouterr()
    rc = main(
        ["render", "--task", "2d-static-dense", "--checkpoint", str(tmp_path), "--robots", "2", "--out", str(out)]
    )
    assert rc == 2 and "--robots goes with --policy" in capsys.readouterr().err


def test_a_team_episode_compiles_once_per_configuration():
    """Two episodes of one team and world (other keys) reuse one compilation of the recorder."""
    import jax

    from snac_jax import multi
    from snac_jax.multi.episodes import _record_scan, record_team_episode
    from snac_jax.policies.team import team_policy

    env = multi.make("1d-static-sin", num_robots=2)
    team = team_policy("handcrafted", env)
    before = _record_scan._cache_size()
    first = record_team_episode(env, env.default_params, team, jax.random.key(0))
    record_team_episode(env, env.default_params, team, jax.random.key(1))
    assert _record_scan._cache_size() == before + 1
    assert first.actions.shape[1] == 2 and len(first.actions) >= 1
