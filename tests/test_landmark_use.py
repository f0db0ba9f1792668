"""`bench/landmark_use.py`: the placement tally on hand-built states, scripted policies whose
placements are known, a tiny trained run (counts consistent, IoUs equal to the protocol's), the
refusal of a run trained without the switch and the choice of a sweep's arm."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.landmark_use import empty_tally, main, run_indices, run_landmark_episodes, tally_step
from snac_jax.evaluation import protocol_episodes
from snac_jax.policy import Policy
from snac_jax.tasks import make

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "bench" / "landmark_use.py"
TINY = dict(num_envs=16, rollout_steps=8, num_minibatches=2, update_epochs=1, hidden_size=8, rnn_size=8)
RIGHT = 1  # 2D action table: left, right, down, up, drop; the placement is 5


def _world(**overrides):
    env, params = make("2d-static-sparse", landmark_action=2, **overrides)
    _, state = env.reset(jax.random.key(0), params)
    return env, params, state


def test_tally_counts_attempts_and_fills_one_slot_per_landed_placement():
    env, params, state = _world()
    config, place = env.config, env.config.place_landmark_action
    design = np.asarray(params.designs[0])
    on, off = tuple(np.argwhere(design > 0)[0]), (0, 0)  # (2, 7) is a design cell, the corner is not
    assert design[off] == 0
    pr, pc = config.pad
    state = state.replace(position=jnp.array(on, jnp.int32), time=jnp.int32(5))

    tally = tally_step(config, empty_tally(2), state, jnp.int32(place))
    assert int(tally.attempts) == 1
    assert tally.steps.tolist() == [5, -1] and tally.rows.tolist() == [on[0], -1] and tally.cols.tolist() == [on[1], -1]
    assert tally.on_design.tolist() == [True, False]

    # the env then holds that landmark and one placement left: a second try on the cell is refused
    marked = state.replace(
        landmarks=state.landmarks.at[on[0] + pr, on[1] + pc].set(True), landmarks_left=jnp.int32(1), time=jnp.int32(6)
    )
    again = tally_step(config, tally, marked, jnp.int32(place))
    assert int(again.attempts) == 2 and again.steps.tolist() == [5, -1]
    # elsewhere it lands in the second slot, off the design
    moved = marked.replace(position=jnp.array(off, jnp.int32), time=jnp.int32(9))
    second = tally_step(config, again, moved, jnp.int32(place))
    assert second.steps.tolist() == [5, 9] and second.on_design.tolist() == [True, False]
    assert second.rows.tolist() == [on[0], 0] and second.cols.tolist() == [on[1], 0]
    # a brick on the cell, or no placement left: an attempt, nothing lands
    brick = moved.replace(grid=moved.grid.at[pr, pc].set(1))
    assert tally_step(config, again, brick, jnp.int32(place)).steps.tolist() == [5, -1]
    spent = moved.replace(landmarks_left=jnp.int32(0))
    none_left = tally_step(config, again, spent, jnp.int32(place))
    assert int(none_left.attempts) == 3 and none_left.steps.tolist() == [5, -1]
    # another action is no attempt
    assert int(tally_step(config, again, moved, jnp.int32(RIGHT)).attempts) == 2


def _scripted(place_when):
    """A policy that places when `place_when(step)` and otherwise moves right; it counts its steps."""

    def init(key, design):
        return jnp.zeros((), jnp.int32)

    def act(params, step, obs, key):
        return jnp.where(place_when(step), 5, RIGHT).astype(jnp.int32), step + 1

    return Policy(init, act, None, "scripted")


@pytest.mark.parametrize("place_when, attempts", [(lambda t: t == 0, 1), (lambda t: t >= 0, 12)])
def test_a_scripted_policy_placing_at_step_zero_places_one_landmark_on_its_start_cell(place_when, attempts):
    """Placing at step 0 lands on the start cell (nothing there yet); a policy that places at every
    step never moves, so only that first one lands and the other 11 attempts do nothing."""
    env, params = make("2d-static-sparse", landmark_action=4, max_steps=12)
    design = np.asarray(params.designs[0])
    setup = protocol_episodes("2d-static-sparse", params, 3, static_episodes=8)
    result = run_landmark_episodes(env, _scripted(place_when), setup)
    assert result.length.tolist() == [12] * 8
    assert result.placed.tolist() == [1] * 8 and result.tally.attempts.tolist() == [attempts] * 8
    assert (result.tally.steps[:, 0] == 0).all() and (result.tally.steps[:, 1:] == -1).all()
    for i in range(8):
        [cell] = np.argwhere(result.new_cells[i]).tolist()  # exactly one new landmark cell, the tallied one
        assert cell == [int(result.tally.rows[i, 0]), int(result.tally.cols[i, 0])]
        assert bool(result.tally.on_design[i, 0]) == (design[tuple(cell)] > 0)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from agents.training.driver import train
    from agents.training.registry import make_config

    run = tmp_path_factory.mktemp("landmark") / "run"
    config = make_config(
        "ppo", "2d-static-sparse", switches="landmark_action=4", seeds=2, total_steps=256, chunks=1, **TINY
    )
    train(config, run, progress=False)
    return run


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_a_tiny_run_gives_consistent_counts_and_the_protocols_ious(tiny_run, tmp_path):
    from agents.training import trained
    from agents.training.checkpoint import read_config
    from snac_jax.evaluation import evaluate_task

    out = tmp_path / "out"
    assert main(["--run", str(tiny_run), "--out", str(out), "--episodes", "6", "--eval-seed", "7"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["landmark_use.json", "landmark_use.png"]
    report = json.loads((out / "landmark_use.json").read_text())
    assert report["landmark_action"] == 4 and report["task"] == "2d-static-sparse" and report["eval_seed"] == 7
    assert set(report["seeds"]) == {"0", "1"} and report["pooled"]["episodes"] == 12
    keys = {
        "mean_placed",
        "mean_attempts",
        "fraction_with_placement",
        "fraction_on_design",
        "mean_first_step",
        "iou_with_placement",
        "iou_without_placement",
        "placed_histogram",
        "mean_iou",
        "placements",
    }
    config = read_config(tiny_run)
    for index, seed in report["seeds"].items():
        assert keys <= set(seed)
        rows = seed["episodes_detail"]
        assert len(rows) == 6 and sum(seed["placed_histogram"]) == 6
        for row in rows:
            assert row["placed"] <= row["attempts"] and row["placed"] <= 4
            assert len(row["steps"]) == len(row["cells"]) == len(row["on_design"]) == row["placed"]
            assert row["steps"] == sorted(set(row["steps"])) and all(0 <= s < row["length"] for s in row["steps"])
        assert seed["mean_placed"] == pytest.approx(np.mean([r["placed"] for r in rows]))
        with_one = [r["iou"] for r in rows if r["placed"]]
        assert seed["iou_with_placement"]["episodes"] == len(with_one)
        # the same episodes as the protocol's with the same key and count
        protocol = evaluate_task(
            "2d-static-sparse",
            lambda env: trained.checkpoint_policy(env, tiny_run, int(index)),
            static_episodes=6,
            seed=7,
            num_devices=1,
            **config.env_overrides,
        )
        assert seed["mean_iou"] == pytest.approx(protocol.mean, abs=1e-12)
    assert (out / "landmark_use.png").stat().st_size > 0


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_a_run_without_the_switch_is_refused_in_one_line(tmp_path):
    from agents.training.config import save_config
    from agents.training.registry import make_config

    run = tmp_path / "run"
    run.mkdir()
    save_config(make_config("ppo", "2d-static-sparse", switches="landmarks=4", **TINY), run / "config.json")
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--run", str(run), "--out", str(out)], capture_output=True, text=True, cwd=ROOT
    )
    assert done.returncode == 2
    assert done.stderr.strip() == (
        f"landmark_use.py: error: {run} was trained without landmark_action (switches "
        "'landmarks=4'): its policy has no placement action to analyse"
    )
    assert not out.exists()


def test_the_indices_of_one_arm_are_its_seeds_arm_major():
    from agents.training.sweep import Sweep

    swept = Sweep(("lr",), ((1e-3,), (3e-4,), (1e-4,)))
    assert run_indices(Path("r"), swept, 3, 2, None) == [(0, 6), (1, 7), (2, 8)]
    assert run_indices(Path("r"), swept, 3, 1, 2) == [(2, 5)]
    assert run_indices(Path("r"), None, 2, None, None) == [(0, 0), (1, 1)]
    assert run_indices(Path("r"), None, 2, None, 1) == [(1, 1)]
    with pytest.raises(ValueError, match=r"^--seed-index must be in 0\.\.2 for r, got 3$"):
        run_indices(Path("r"), swept, 3, 0, 3)


def _config_only_run(tmp_path, arms=None):
    """A run directory with a config (and a sweep of `arms` learning rates): enough for the
    refusals, which come before any checkpoint is read."""
    from agents.training import sweep
    from agents.training.config import save_config
    from agents.training.registry import make_config

    run = tmp_path / "run"
    run.mkdir()
    save_config(
        make_config("ppo", "2d-static-sparse", switches="landmark_action=4", seeds=2, **TINY), run / "config.json"
    )
    if arms is not None:
        sweep.save(sweep.Sweep(("learning_rate",), tuple((1e-3 / (i + 1),) for i in range(arms))), run)
    return run


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
@pytest.mark.parametrize(
    "arms, arm, message",
    [
        (3, None, "{run} is a sweep of 3 arms: --arm must be in 0..2 (none given)"),
        (3, 3, "{run} is a sweep of 3 arms: --arm must be in 0..2 (got 3)"),
        (3, -1, "{run} is a sweep of 3 arms: --arm must be in 0..2 (got -1)"),
        (None, 0, "--arm 0 given, but {run} is not a sweep (it trained one arm): leave --arm out"),
    ],
)
def test_a_sweep_needs_one_of_its_arms_in_one_line(tmp_path, arms, arm, message):
    run = _config_only_run(tmp_path, arms)
    out = tmp_path / "out"
    done = subprocess.run(
        [
            sys.executable,
            str(SCRIPT),
            "--run",
            str(run),
            "--out",
            str(out),
            *([] if arm is None else ["--arm", str(arm)]),
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert done.returncode == 2
    assert done.stderr.strip() == "landmark_use.py: error: " + message.format(run=run)
    assert done.stderr.count("\n") == 1 and not out.exists()


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_an_arm_of_a_sweep_is_scored_with_its_own_policies(tmp_path):
    """Arm 1 of a 2-arm sweep with 2 seeds is run indices 2 and 3: its seeds' IoUs are the
    protocol's for those policies, and differ from arm 0's (another learning rate)."""
    from agents.training import trained
    from agents.training.driver import train
    from agents.training.registry import make_config
    from agents.training.sweep import parse_sweep
    from snac_jax.evaluation import evaluate_task

    run = tmp_path / "sweep"
    config = make_config(
        "ppo", "2d-static-sparse", switches="landmark_action=4", seeds=2, total_steps=256, chunks=1, **TINY
    )
    train(config, run, progress=False, swept=parse_sweep(["learning_rate=1e-4,3e-2"], config))
    reports = {}
    for arm in (0, 1):
        out = tmp_path / f"arm{arm}"
        assert (
            main(["--run", str(run), "--out", str(out), "--arm", str(arm), "--episodes", "4", "--eval-seed", "7"]) == 0
        )
        reports[arm] = json.loads((out / "landmark_use.json").read_text())
    assert reports[1]["arm"] == 1 and reports[1]["arm_settings"] == {"learning_rate": 3e-2}
    assert set(reports[1]["seeds"]) == {"0", "1"} and reports[1]["pooled"]["episodes"] == 8
    for seed in (0, 1):
        protocol = evaluate_task(
            "2d-static-sparse",
            lambda env: trained.checkpoint_policy(env, run, 2 + seed),
            static_episodes=4,
            seed=7,
            num_devices=1,
            landmark_action=4,
        )
        assert reports[1]["seeds"][str(seed)]["mean_iou"] == pytest.approx(protocol.mean, abs=1e-12)
    rows = lambda arm: [r for s in ("0", "1") for r in reports[arm]["seeds"][s]["episodes_detail"]]
    assert rows(0) != rows(1)
