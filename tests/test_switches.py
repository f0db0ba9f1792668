"""The ablation switches of SPEC §9: each changes what it should and nothing else."""

import jax
import numpy as np
import pytest

from snac_jax import make
from snac_jax.observation import LANDMARK_VALUE
from snac_jax.transition import is_stuck
from tests.helpers import random_episode

STEPS = 400


def _run(task, seed=0, steps=STEPS, **overrides):
    env, params = make(task, **overrides)
    return env, params, jax.tree.map(np.asarray, random_episode(jax.random.key(seed), env, params, steps))


@pytest.mark.slow
@pytest.mark.parametrize("task", ["1d-static-step", "2d-dynamic-dense", "3d-static-sparse"])
def test_gps_appends_the_true_position_and_changes_nothing_else(task):
    bank = {"design_bank_size": 16} if "dynamic" in task else {}
    env, _, (_, (obs, act, rew, term, trunc, info, state)) = _run(task, **bank)
    env_g, _, (_, (obs_g, act_g, rew_g, term_g, trunc_g, info_g, state_g)) = _run(task, gps=True, **bank)
    n = 1 if env.config.dim == 1 else 2
    assert obs_g.shape[1] == obs.shape[1] + n
    np.testing.assert_array_equal(obs_g[:, :-n], obs)
    for a, b in [(act, act_g), (rew, rew_g), (term, term_g), (trunc, trunc_g)]:
        np.testing.assert_array_equal(a, b)
    # The position appended to obs[t] is that of the state after step t (prev state of t+1).
    position = state_g.position[1:, 1:] if n == 1 else state_g.position[1:]
    done = (term_g | trunc_g)[:-1]
    np.testing.assert_array_equal(obs_g[:-1, -n:][~done], position[~done])


@pytest.mark.parametrize(
    "probs,expected", [((1, 0, 0), {1}), ((0, 0, 1), {3}), ((0.5, 0.5, 0), {1, 2}), ((1 / 3,) * 3, {1, 2, 3})]
)
def test_stride_distribution(probs, expected):
    _, _, (_, (*_, info, _)) = _run("2d-static-dense", stride_probs=probs)
    assert set(np.unique(info["stride"])) == expected
    if probs == (0.5, 0.5, 0):
        assert abs(np.mean(info["stride"] == 1) - 0.5) < 0.1


def test_obstacles_in_2d_use_the_3d_action_set_and_rule():
    env, _, (_, (obs, act, rew, term, trunc, info, state)) = _run("2d-static-dense", seed=1, steps=2000, obstacles=True)
    assert env.num_actions == 8 and env.config.binary_grid
    pr, pc = env.config.pad
    on_cell = state.grid[np.arange(len(act)), state.position[:, 0] + pr, state.position[:, 1] + pc]
    assert np.all(on_cell == 0)  # never on a brick
    assert state.grid.max() == 1  # still binary
    assert np.any(term & (rew == 0) & (state.bricks_used < state.max_bricks - 1))  # stuck ends episodes
    plain, _ = make("2d-static-dense")
    assert plain.num_actions == 5


def test_is_stuck_is_the_rule_the_transition_ends_episodes_on():
    env, params, (_, (obs, act, rew, term, trunc, info, state)) = _run(
        "2d-static-dense", seed=1, steps=2000, obstacles=True
    )
    stuck = np.asarray(jax.vmap(lambda s: is_stuck(env.config, s))(state))  # of the state before each step
    terminated = np.asarray(jax.vmap(env.is_terminated, in_axes=(0, None))(state, params))
    assert stuck.any()
    bricks_left = state.bricks_used < state.max_bricks - 1  # this step cannot spend the last brick
    np.testing.assert_array_equal(term[bricks_left], stuck[bricks_left])
    np.testing.assert_array_equal(terminated, stuck)  # a state before a step is never out of bricks


@pytest.mark.slow
def test_no_obstacles_in_3d_lets_the_robot_stand_on_bricks_and_never_sticks():
    env, _, (_, (obs, act, rew, term, trunc, info, state)) = _run(
        "3d-static-dense", seed=2, steps=3000, obstacles=False
    )
    assert env.num_actions == 8
    pr, pc = env.config.pad
    on_cell = state.grid[np.arange(len(act)), state.position[:, 0] + pr, state.position[:, 1] + pc]
    assert np.any(on_cell > 0)
    # Only the brick limit ends an episode early: never "stuck".
    ended_early = np.flatnonzero(term)
    assert np.all(state.bricks_used[ended_early] + 1 >= state.max_bricks[ended_early])
    _, _, (_, (*_, term_default, _, _, state_default)) = _run("3d-static-dense", seed=2, steps=3000)
    assert term_default.sum() > term.sum()  # with obstacles the random robot gets stuck


def test_landmarks_are_seen_outside_the_design_and_hold_no_bricks():
    env, params = make("2d-static-sparse", landmarks=8)
    obs, state = env.reset(jax.random.key(4), params)
    marks = np.asarray(state.landmarks)
    pr, pc = env.config.pad
    plan_marks = marks[pr:-pr, pc:-pc]
    assert marks.sum() == 8 and plan_marks.sum() == 8
    assert not np.any(plan_marks & (np.asarray(params.designs[0]) > 0))
    # Put the robot next to a landmark: it shows as -2 in the window.
    r, c = np.argwhere(plan_marks)[0]
    state = state.replace(position=np.asarray([r, c], np.int32))
    window = np.asarray(env.get_obs(state, params))[:49].reshape(7, 7)
    assert window[3, 3] == LANDMARK_VALUE
    assert np.sum(window == LANDMARK_VALUE) == marks[r : r + 7, c : c + 7].sum()
    # A drop on it is spent and changes nothing; reward 0; IoU unchanged.
    obs2, state2, reward, terminated, info = env.step_with_stride(state, 4, 1, params)
    assert int(state2.bricks_used) == 1 and float(reward) == 0.0
    np.testing.assert_array_equal(state2.grid, state.grid)
    assert int(state2.overlap) == int(state.overlap) and int(state2.union) == int(state.union)
    # Moving onto a landmark is allowed (with obstacles too).
    env3, params3 = make("3d-static-sparse", landmarks=8)
    _, s3 = env3.reset(jax.random.key(4), params3)
    m3 = np.asarray(s3.landmarks)[pr:-pr, pc:-pc]
    r, c = next((r, c) for r, c in np.argwhere(m3) if c > 0 and not m3[r, c - 1])
    s3 = s3.replace(position=np.asarray([r, c - 1], np.int32))
    _, s3b, *_ = env3.step_with_stride(s3, 1, 1, params3)
    assert tuple(np.asarray(s3b.position)) == (r, c)


def test_without_landmarks_no_cell_is_a_landmark():
    _, _, (_, (obs, *_)) = _run("2d-static-sparse")
    assert not np.any(obs == LANDMARK_VALUE)


@pytest.mark.slow
def test_3d_reward_scheme_changes_rewards_only():
    kw = dict(task="3d-static-dense", seed=5, steps=1500, obstacles=False)
    _, _, (_, (obs, act, rew, term, trunc, info, state)) = _run(**kw)
    _, _, (_, (obs_b, act_b, rew_b, term_b, trunc_b, info_b, state_b)) = _run(reward_scheme="binary", **kw)
    for a, b in [(obs, obs_b), (act, act_b), (term, term_b), (trunc, trunc_b), (state.grid, state_b.grid)]:
        np.testing.assert_array_equal(a, b)
    assert set(np.unique(rew_b)) <= {0.0, 5.0}
    np.testing.assert_array_equal(rew_b == 5.0, (rew == 1.0) | (rew == 10.0))


def test_max_steps_override_truncates():
    _, _, (_, (*_, trunc, _, _)) = _run("1d-static-sin", steps=100, max_steps=30)
    assert np.flatnonzero(trunc).tolist() == [29, 59, 89]


def test_switches_as_text_parse_to_make_overrides():
    from snac_jax.tasks import parse_switches

    assert parse_switches("") == {}
    assert parse_switches("gps=true, stride_probs=1/0/0,landmarks=8,obstacles=False,reward_scheme=height") == {
        "gps": True,
        "stride_probs": (1.0, 0.0, 0.0),
        "landmarks": 8,
        "obstacles": False,
        "reward_scheme": "height",
    }
    env, _ = make("2d-static-dense", **parse_switches("obstacles=true,landmarks=8"))
    assert env.config.obstacles and env.config.num_landmarks == 8


@pytest.mark.parametrize(
    "text, message",
    [
        (
            "gps",
            r"switch 'gps' must be key=value; allowed keys: gps, stride_probs, obstacles, landmarks, reward_scheme",
        ),
        (
            "max_steps=10",
            r"unknown switch 'max_steps'; allowed: gps, stride_probs, obstacles, landmarks, reward_scheme",
        ),
        ("gps=true,gps=false", "switch 'gps' is given twice"),
        ("stride_probs=1/a/0", "numbers joined by '/' expected"),
        (None, "switches must be a string"),
    ],
)
def test_bad_switch_text_is_refused(text, message):
    from snac_jax.tasks import parse_switches

    with pytest.raises(ValueError, match=message):
        parse_switches(text)


# --- SPEC §14-15: the landmark action and design changes as overrides and as text ---------------


@pytest.mark.parametrize(
    "task,overrides,match",
    [
        ("2d-static-sparse", {"landmark_action": -1}, "landmark_action must be an int in 0..400"),
        ("2d-static-sparse", {"landmark_action": True}, "landmark_action must be an int in 0..400"),
        ("2d-static-sparse", {"landmark_action": 2.0}, "landmark_action must be an int in 0..400"),
        ("2d-static-sparse", {"landmark_action": 401}, "landmark_action must be an int in 0..400"),
        ("1d-static-sin", {"landmark_action": 2}, "landmark_action needs a 2D or 3D task"),
        ("2d-static-sparse", {"design_change": (100, 300)}, "design_change applies to dynamic tasks only"),
        ("2d-dynamic-dense", {"design_change": (300, 100)}, r"1 <= a <= b < max_steps=600"),
        ("2d-dynamic-dense", {"design_change": (0, 100)}, r"1 <= a <= b < max_steps=600"),
        ("2d-dynamic-dense", {"design_change": (-5, 100)}, r"1 <= a <= b < max_steps=600"),
        ("2d-dynamic-dense", {"design_change": (100, 600)}, r"1 <= a <= b < max_steps=600"),
        ("2d-dynamic-dense", {"design_change": (10, 20), "max_steps": 15}, r"b < max_steps=15"),
        ("2d-dynamic-dense", {"design_change": (1.5, 20)}, "design_change must be two ints"),
        ("2d-dynamic-dense", {"design_change": 100}, "design_change must be two ints"),
        ("2d-dynamic-dense", {"design_change": (1, 2, 3)}, "design_change must be two ints"),
        ("2d-dynamic-dense", {"design_change": (1, 2), "test_design": 0}, "cannot be combined with test_design"),
        ("2d-dynamic-dense", {"design_change": (1, 2), "design_bank_size": 1}, "at least 2 designs"),
    ],
)
def test_extension_switches_are_checked_at_make(task, overrides, match):
    with pytest.raises(ValueError, match=match) as error:
        make(task, **overrides)
    assert "\n" not in str(error.value)


def test_extension_switches_are_off_by_default_and_add_no_state():
    env, params = make("2d-dynamic-dense", design_bank_size=4)
    assert env.config.landmark_action == 0 and env.config.design_change is None
    _, state = env.reset(jax.random.key(0), params)
    assert state.landmarks is None and state.landmarks_left is None
    assert state.change_step is None and state.next_design is None and state.next_max_bricks is None
    assert env.num_actions == 5


def test_parse_switches_reads_the_extensions():
    from snac_jax.tasks import parse_switches

    assert parse_switches("landmark_action=4,design_change=100/300") == {
        "landmark_action": 4,
        "design_change": (100, 300),
    }
    for steps in ("1.5/3", "1_00/300"):  # int() reads '1_00' as 100: not a step number as written
        with pytest.raises(ValueError, match="two step numbers a/b"):
            parse_switches(f"design_change={steps}")
    env, _ = make("2d-dynamic-sparse", design_bank_size=4, **parse_switches("design_change=100/300,landmark_action=2"))
    assert env.config.design_change == (100, 300) and env.num_actions == 6


def test_a_training_config_carries_the_extensions_and_refuses_bad_ones_up_front():
    from agents.training.registry import make_config

    config = make_config("ppo", "2d-static-sparse", switches="landmark_action=4")
    env, _ = config.make_env()
    assert env.num_actions == 6 and env.config.landmark_action == 4
    with pytest.raises(ValueError, match="design_change applies to dynamic tasks only"):
        make_config("ppo", "2d-static-sparse", switches="design_change=100/300")
    with pytest.raises(ValueError, match=r"1 <= a <= b < max_steps=600, got \(300, 100\)"):
        make_config("ppo", "2d-dynamic-sparse", switches="design_change=300/100")


@pytest.mark.parametrize(
    "text",
    [
        "landmark_action=\u0664",  # Arabic-Indic four: Python's int() reads it as 4
        "landmarks=\uff18",  # a fullwidth 8
        "design_change=\u0661\u0660\u0660/\u0663\u0660\u0660",
        "stride_probs=\u0661/\u0660/\u0660",
        "reward_scheme=h\u00e9ight",
    ],
)
def test_a_switch_value_outside_ascii_is_refused_not_stored_as_typed(text):
    """config.json keeps the switches as text; a value Python happens to read (int('\u0664') == 4)
    would be stored as typed and read differently by anything else, so it is refused in one line."""
    from agents.training.registry import make_config
    from snac_jax.tasks import parse_switches

    key = text.partition("=")[0]
    for parse in (parse_switches, lambda t: make_config("ppo", "2d-dynamic-sparse", switches=t)):
        with pytest.raises(ValueError, match=rf"^switch {key}=.*: ASCII only") as error:
            parse(text)
        assert "\n" not in str(error.value)


@pytest.mark.parametrize("text", ["landmark_action=1_0", "landmark_action=+4", "landmarks=0x8"])
def test_an_integer_switch_is_plain_ascii_digits(text):
    """int() reads '1_0' as 10 and '+4' as 4; as a switch they are words, which `make` refuses."""
    from snac_jax.tasks import parse_switches

    key, _, value = text.partition("=")
    assert parse_switches(text) == {key: value}
    with pytest.raises(ValueError, match=rf"{key} must be an int"):
        make("2d-static-sparse", **parse_switches(text))
