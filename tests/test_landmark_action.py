"""SPEC §14, the landmark placement action: hand-written episodes with `step_with_stride`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from snac_jax import make
from snac_jax.observation import LANDMARK_VALUE
from tests.helpers import random_episode

CENTRE = 24  # the window's centre cell (7x7, row-major): the robot's own cell
RIGHT, DOWN = 1, 2  # moves of the 2D/3D tables (SPEC §3)


def _start(task="2d-static-sparse", **overrides):
    env, params = make(task, **overrides)
    _, state = env.reset(jax.random.key(0), params)
    return env, params, state


def _step(env, params, state, action, stride=1):
    obs, state, reward, terminated, info = env.step_with_stride(state, action, stride, params)
    return np.asarray(obs), state, float(reward), bool(terminated), info


def test_the_placement_is_the_action_after_the_table_and_shows_minus_two_at_the_robots_cell():
    env, params, state = _start(landmark_action=2)
    place = env.config.place_landmark_action
    assert (place, env.num_actions, len(env.config.actions)) == (5, 6, 5)
    obs, after, reward, terminated, info = _step(env, params, state, place, stride=3)
    assert obs[CENTRE] == LANDMARK_VALUE and reward == 0.0 and not terminated
    np.testing.assert_array_equal(after.position, [0, 0])  # the stride does not move it
    np.testing.assert_array_equal(after.grid, state.grid)  # no brick
    assert (int(after.bricks_used), int(after.time), int(after.landmarks_left)) == (0, 1, 1)
    assert (int(after.overlap), int(after.union)) == (int(state.overlap), int(state.union))
    assert float(info["final_iou"]) == 0.0
    assert np.argwhere(np.asarray(after.landmarks)).tolist() == [[3, 3]]  # plan (0, 0) + padding 3
    # Seen from the next cell, the landmark is the window's cell left of the centre.
    obs, *_ = _step(env, params, after, RIGHT)
    assert obs[CENTRE - 1] == LANDMARK_VALUE and obs[CENTRE] == 0.0


def test_an_exhausted_supply_makes_the_action_a_step_that_does_nothing():
    env, params, state = _start(landmark_action=1)
    place = env.config.place_landmark_action
    _, state, *_ = _step(env, params, state, place)
    _, state, *_ = _step(env, params, state, RIGHT)
    obs, after, reward, terminated, _ = _step(env, params, state, place)
    assert obs[CENTRE] == 0.0 and reward == 0.0 and not terminated
    assert int(np.sum(after.landmarks)) == 1 and int(after.landmarks_left) == 0 and int(after.time) == 3


def test_a_placement_on_a_landmark_or_a_brick_does_nothing_and_spends_nothing():
    env, params, state = _start(landmark_action=3)
    place, drop = env.config.place_landmark_action, 4
    _, state, *_ = _step(env, params, state, place)
    _, again, *_ = _step(env, params, state, place)
    assert int(again.landmarks_left) == 2 and int(np.sum(again.landmarks)) == 1
    _, state, *_ = _step(env, params, again, RIGHT)
    _, state, *_ = _step(env, params, state, drop)  # a brick on plan (0, 1)
    obs, after, reward, _, _ = _step(env, params, state, place)
    assert obs[CENTRE] == 1.0 and reward == 0.0  # the brick shows, not a landmark
    assert int(after.landmarks_left) == 2 and not bool(after.landmarks[3, 4])


def test_a_drop_on_a_placed_landmark_spends_the_brick_and_changes_nothing():
    env, params, state = _start(landmark_action=1)
    _, state, *_ = _step(env, params, state, env.config.place_landmark_action)
    obs, after, reward, terminated, _ = _step(env, params, state, 4)
    assert int(after.bricks_used) == 1 and reward == 0.0 and not terminated
    np.testing.assert_array_equal(after.grid, state.grid)
    assert (int(after.overlap), int(after.union)) == (int(state.overlap), int(state.union))
    assert obs[CENTRE] == LANDMARK_VALUE


def _walk_to(env, params, state, row, col):
    for _ in range(col):
        _, state, *_ = _step(env, params, state, RIGHT)
    for _ in range(row):
        _, state, *_ = _step(env, params, state, DOWN)
    return state


def test_a_placement_on_a_design_cell_lands_and_that_cell_can_no_longer_be_built():
    env, params, state = _start(landmark_action=1)
    design = np.asarray(params.designs[0])
    cells = np.argwhere(design > 0)
    (row, col), (row2, col2) = cells[0], cells[1]
    state = _walk_to(env, params, state, row, col)
    obs, state, reward, *_ = _step(env, params, state, env.config.place_landmark_action)
    assert obs[CENTRE] == LANDMARK_VALUE and reward == 0.0
    _, state, reward, *_ = _step(env, params, state, 4)
    assert reward == 0.0 and int(state.bricks_used) == 1 and int(state.overlap) == 0
    # IoU by hand: one brick on another design cell; the landmarked cell stays in the union.
    state = _walk_to(env, params, state.replace(position=jnp.zeros(2, jnp.int32)), row2, col2)
    _, state, reward, _, info = _step(env, params, state, 4)
    assert reward == 5.0
    assert float(info["final_iou"]) == pytest.approx(1 / design.sum())


def test_3d_places_on_the_own_cell_and_a_neighbour_drop_on_it_is_spent():
    env, params, state = _start("3d-static-sparse", landmark_action=1)
    place, drop_left, left = env.config.place_landmark_action, 4, 0
    assert (place, env.num_actions) == (8, 9)
    _, state, *_ = _step(env, params, state, place)
    _, state, *_ = _step(env, params, state, RIGHT)
    np.testing.assert_array_equal(state.position, [0, 1])
    obs, after, reward, *_ = _step(env, params, state, drop_left)
    assert obs[CENTRE - 1] == LANDMARK_VALUE and reward == 0.0 and int(after.bricks_used) == 1
    np.testing.assert_array_equal(after.grid, state.grid)
    _, back, *_ = _step(env, params, after, left)  # a landmark does not block a move
    np.testing.assert_array_equal(back.position, [0, 0])


def test_fixed_landmarks_and_placements_share_one_mask():
    env, params, state = _start("2d-static-dense", landmarks=3, landmark_action=2)
    assert int(np.sum(state.landmarks)) == 3 and int(state.landmarks_left) == 2
    _, state, *_ = _step(env, params, state, env.config.place_landmark_action)
    assert int(np.sum(state.landmarks)) == 4


@pytest.mark.slow
def test_random_play_under_jit_and_vmap_keeps_the_rules():
    env, params = make("2d-dynamic-sparse", landmark_action=3, design_bank_size=8, max_steps=60)
    episode = jax.jit(jax.vmap(lambda k: random_episode(k, env, params, 150)))
    _, (obs, action, reward, terminated, truncated, info, state) = episode(jax.random.split(jax.random.key(1), 4))
    marks, grid = np.asarray(state.landmarks), np.asarray(state.grid)
    assert np.all(marks.sum(axis=(-2, -1)) + np.asarray(state.landmarks_left) == 3)
    assert not np.any(marks & (grid > 0))  # a landmark never holds a brick
    assert np.any(np.asarray(state.landmarks_left) < 3)  # random play placed some
    placed = np.asarray(action) == env.config.place_landmark_action
    assert np.all(np.asarray(reward)[placed] == 0.0)


def test_compiles_once_per_configuration():
    # K values no other test uses, so the cache holds neither configuration yet.
    env_a, params = make("2d-static-sparse", landmark_action=17)
    env_b, _ = make("2d-static-sparse", landmark_action=17)
    env_c, _ = make("2d-static-sparse", landmark_action=18)
    assert env_a == env_b and hash(env_a) == hash(env_b) and env_a != env_c
    key = jax.random.key(0)
    _, state = env_a.reset(key, params)
    before = type(env_a).step._cache_size()
    env_a.step(key, state, 5, params)
    env_b.step(key, state, 5, params)
    assert type(env_a).step._cache_size() == before + 1
    env_c.step(key, state, 5, params)
    assert type(env_a).step._cache_size() == before + 2


def test_human_play_binds_l_to_the_placement_and_the_caption_counts_what_is_left():
    from snac_jax.human.game import key_bindings, key_legend
    from snac_jax.rendering import caption_lines

    for task, index in (("2d-static-sparse", 5), ("3d-static-sparse", 8)):
        env, params, state = _start(task, landmark_action=2)
        assert key_bindings(env.config)["l"] == index and "L: landmark" in key_legend(env.config)
        _, state, *_ = _step(env, params, state, index)
        assert "landmarks left 1" in caption_lines(env, state)[0]
    plain, _ = make("2d-static-sparse")
    assert "l" not in key_bindings(plain.config) and "landmark" not in key_legend(plain.config)


def test_several_robots_refuse_the_extensions():
    import snac_jax.multi

    with pytest.raises(ValueError, match="landmark_action is a single-robot switch"):
        snac_jax.multi.make("2d-static-sparse", num_robots=2, landmark_action=2)
    with pytest.raises(ValueError, match="design_change is a single-robot switch"):
        snac_jax.multi.make("2d-dynamic-sparse", num_robots=2, design_change=(1, 2))
