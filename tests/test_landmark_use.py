"""`bench/landmark_use.py`: the placement tally on hand-built states, scripted policies whose
placements are known, a tiny trained run (counts consistent, IoUs equal to the protocol's) and
the refusal of a run trained without the switch."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.landmark_use import empty_tally, main, run_landmark_episodes, tally_step
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
    marked = state.replace(landmarks=state.landmarks.at[on[0] + pr, on[1] + pc].set(True), landmarks_left=jnp.int32(1),
                           time=jnp.int32(6))
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
    result = run_landmark_episodes(env, params, _scripted(place_when), jax.random.key(3), np.zeros(8, np.int32))
    assert result.length.tolist() == [12] * 8
    assert result.placed.tolist() == [1] * 8 and result.tally.attempts.tolist() == [attempts] * 8
    assert (result.tally.steps[:, 0] == 0).all() and (result.tally.steps[:, 1:] == -1).all()
    for i in range(8):
        [cell] = np.argwhere(result.new_cells[i]).tolist()  # exactly one new landmark cell, the tallied one
        assert cell == [int(result.tally.rows[i, 0]), int(result.tally.cols[i, 0])]
        assert bool(result.tally.on_design[i, 0]) == (design[tuple(cell)] > 0)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from agents.driver import train
    from agents.registry import make_config

    run = tmp_path_factory.mktemp("landmark") / "run"
    config = make_config("ppo", "2d-static-sparse", switches="landmark_action=4", seeds=2, total_steps=256, chunks=1,
                         **TINY)
    train(config, run, progress=False)
    return run


def test_a_tiny_run_gives_consistent_counts_and_the_protocols_ious(tiny_run, tmp_path):
    from agents import trained
    from agents.checkpoint import read_config
    from snac_jax.evaluation import evaluate_task

    out = tmp_path / "out"
    assert main(["--run", str(tiny_run), "--out", str(out), "--episodes", "6", "--eval-seed", "7"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["landmark_use.json", "landmark_use.png"]
    report = json.loads((out / "landmark_use.json").read_text())
    assert report["landmark_action"] == 4 and report["task"] == "2d-static-sparse" and report["eval_seed"] == 7
    assert set(report["seeds"]) == {"0", "1"} and report["pooled"]["episodes"] == 12
    keys = {"mean_placed", "mean_attempts", "fraction_with_placement", "fraction_on_design", "mean_first_step",
            "iou_with_placement", "iou_without_placement", "placed_histogram", "mean_iou", "placements"}
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
        protocol = evaluate_task("2d-static-sparse", lambda env: trained.checkpoint_policy(env, tiny_run, int(index)),
                                 static_episodes=6, seed=7, num_devices=1, **config.env_overrides)
        assert seed["mean_iou"] == pytest.approx(protocol.mean, abs=1e-12)
    assert (out / "landmark_use.png").stat().st_size > 0


def test_a_run_without_the_switch_is_refused_in_one_line(tmp_path):
    from agents.config import save_config
    from agents.registry import make_config

    run = tmp_path / "run"
    run.mkdir()
    save_config(make_config("ppo", "2d-static-sparse", switches="landmarks=4", **TINY), run / "config.json")
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, str(SCRIPT), "--run", str(run), "--out", str(out)], capture_output=True,
                          text=True, cwd=ROOT)
    assert done.returncode == 2
    assert done.stderr.strip() == (f"landmark_use.py: error: {run} was trained without landmark_action (switches "
                                   "'landmarks=4'): its policy has no placement action to analyse")
    assert not out.exists()
