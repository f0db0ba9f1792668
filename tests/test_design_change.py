"""SPEC §15, designs that change within an episode: a hand-written episode with the IoU computed
by hand, the draw of the change, jit/vmap, compilation, and the evaluation's fixed schedule."""

import jax
import numpy as np
import pytest

from snac_jax import design_change, designs, make
from snac_jax.tasks import make_params, test_design_names
from tests.helpers import random_episode

RIGHT, DROP = 1, 4  # 2D table (SPEC §3)


def _design(*cells):
    design = np.zeros((20, 20), np.int16)
    for cell in cells:
        design[cell] = 1
    return design


OLD = _design((0, 0), (0, 1), (1, 1))
NEW = _design((0, 1), (0, 2), (1, 2), (2, 2))


def _jitted(env):
    """`env`'s `reset_to_design` and `step_with_stride`, jitted: one program each, not one per
    operation (the action and stride are traced, so the known-value checks are `step`'s)."""
    return jax.jit(env.reset_to_design), jax.jit(env.step_with_stride)


def _hand_iou(built_cells, design):
    built = _design(*built_cells) > 0
    return np.sum(built & (design > 0)) / np.sum(built | (design > 0))


@pytest.mark.slow
def test_a_change_mid_episode_follows_the_new_design_from_its_step():
    env, _ = make("2d-dynamic-dense", design_change=(3, 3), design_bank_size=2)
    params = make_params(np.stack([OLD, NEW]), 2, max_steps=600)  # a bank of two hand-made designs
    reset_to_design, step_with_stride = _jitted(env)
    _, state = reset_to_design(jax.random.key(0), params, 0)
    assert int(state.change_step) == 3  # a..b = 3..3
    np.testing.assert_array_equal(state.next_design, NEW)  # the bank's only other design
    layout = env.observation_layout

    def step(state, action):
        obs, state, reward, terminated, info = step_with_stride(state, action, 1, params)
        return np.asarray(obs), state, float(reward), float(info["final_iou"])

    obs, state, reward, iou = step(state, DROP)  # brick on (0, 0): in OLD
    assert reward == 5.0 and iou == pytest.approx(_hand_iou([(0, 0)], OLD))  # 1/3
    np.testing.assert_array_equal(layout.design_cells(obs), OLD)
    obs, state, reward, iou = step(state, RIGHT)
    np.testing.assert_array_equal(layout.design_cells(obs), OLD)
    obs, state, reward, iou = step(state, DROP)  # step 3: brick on (0, 1), rewarded by OLD
    assert reward == 5.0
    assert iou == pytest.approx(_hand_iou([(0, 0), (0, 1)], NEW)) == pytest.approx(1 / 5)
    np.testing.assert_array_equal(layout.design_cells(obs), NEW)
    np.testing.assert_array_equal(state.design, NEW)
    assert int(state.max_bricks) == 2 + 30  # N_b + NEW's own budget, max(4 cells, 30)
    obs, state, reward, iou = step(state, RIGHT)
    obs, state, reward, iou = step(state, DROP)  # brick on (0, 2): in NEW only
    assert reward == 5.0 and iou == pytest.approx(_hand_iou([(0, 0), (0, 1), (0, 2)], NEW))  # 2/5
    _, state, reward, iou = step(state, 0)  # back left, then a brick on (0, 1) again: full, earns 0
    _, state, reward, iou = step(state, DROP)
    assert reward == 0.0 and int(state.time) == 7 and iou == pytest.approx(2 / 5)


@pytest.mark.slow
def test_the_change_step_is_uniform_in_a_b_and_the_next_design_is_another_bank_design():
    # A bank of 8, the size the other tests here use: its generator compiles once for the file.
    env, params = make("2d-dynamic-dense", design_change=(10, 14), design_bank_size=8)
    _, states = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.key(0), 2000), params)
    steps = np.asarray(states.change_step)
    counts = np.bincount(steps, minlength=15)[10:]
    assert steps.min() >= 10 and steps.max() <= 14 and counts.sum() == 2000
    assert np.all(np.abs(counts - 400) < 80), counts  # 5 sigma is about 90
    bank = np.asarray(params.designs)
    current = np.asarray(states.design).reshape(2000, -1)
    following = np.asarray(states.next_design).reshape(2000, -1)
    assert not np.any(np.all(current == following, axis=1))
    assert all(any(np.array_equal(d, b) for b in bank.reshape(8, -1)) for d in following[:50])
    # The change is fixed by the reset key: the same key, the same change.
    _, again = env.reset(jax.random.key(7), params)
    _, same = env.reset(jax.random.key(7), params)
    assert int(again.change_step) == int(same.change_step)
    np.testing.assert_array_equal(again.next_design, same.next_design)


@pytest.mark.slow
def test_training_never_changes_to_a_test_design():
    env, params = make("2d-dynamic-sparse", design_change=(1, 5), design_bank_size=256)
    _, states = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.key(3), 1024), params)
    following = np.asarray(states.next_design).reshape(1024, -1)
    for name in test_design_names("2d-dynamic-sparse"):
        test = designs.fixed_design(name).reshape(-1)
        assert not np.any(np.all(following == test, axis=1)), name


@pytest.mark.slow
def test_random_play_under_jit_and_vmap_keeps_the_iou_and_the_observation_on_the_design_in_force():
    env, params = make("2d-dynamic-dense", design_change=(5, 20), design_bank_size=8, max_steps=40)
    episode = jax.jit(jax.vmap(lambda k: random_episode(k, env, params, 120)))
    _, (obs, action, reward, terminated, truncated, info, state) = episode(jax.random.split(jax.random.key(2), 3))
    (pr, pc), (h, w) = env.config.pad, env.config.plan_shape
    built = np.asarray(state.grid)[..., pr : pr + h, pc : pc + w] > 0
    design = np.asarray(state.design) > 0
    np.testing.assert_array_equal(np.asarray(state.overlap), np.sum(built & design, axis=(-2, -1)))
    np.testing.assert_array_equal(np.asarray(state.union), np.sum(built | design, axis=(-2, -1)))
    # Some episodes got past their change step, and each state shows the design in force.
    assert np.any(np.asarray(state.time) >= np.asarray(state.change_step))
    assert np.any(np.any(np.asarray(state.design) != np.asarray(state.next_design), axis=(-2, -1)))
    # final_observation[t] is the state after step t, which state[t + 1] is unless a reset came between.
    shown = env.observation_layout.design_cells(np.asarray(info["final_observation"]))[:, :-1]
    kept = ~(np.asarray(terminated) | np.asarray(truncated))[:, :-1]
    np.testing.assert_array_equal(shown[kept], np.asarray(state.design)[:, 1:][kept])


@pytest.mark.slow
def test_compiles_once_per_configuration():
    # (a, b) values no other test uses, so the cache holds neither configuration yet.
    env_a, params = make("2d-dynamic-sparse", design_change=(31, 37), design_bank_size=4)
    env_b, _ = make("2d-dynamic-sparse", design_change=(31, 37), design_bank_size=4)
    env_c, _ = make("2d-dynamic-sparse", design_change=(31, 38), design_bank_size=4)
    assert env_a == env_b and env_a != env_c
    key = jax.random.key(0)
    _, state = env_a.reset(key, params)
    before = type(env_a).step._cache_size()
    env_a.step(key, state, 4, params)
    env_b.step(key, state, 4, params)
    assert type(env_a).step._cache_size() == before + 1
    env_c.step(key, state, 4, params)
    assert type(env_a).step._cache_size() == before + 2


def test_the_evaluation_schedule_is_fixed_and_pairs_test_design_i_with_i_plus_1():
    env, _ = make("2d-dynamic-dense", design_change=(100, 300), design_bank_size=2)
    steps = [int(design_change.scheduled_step(env.config, i, 10)) for i in range(10)]
    assert steps == [100, 122, 144, 166, 188, 211, 233, 255, 277, 300]  # the list in SPEC §15
    stack = np.stack([designs.fixed_design(n) for n in test_design_names("2d-dynamic-dense")])
    params = make_params(stack, 2, max_steps=600)

    @jax.jit  # one program, not one per operation
    def scheduled_reset(key, params, i):
        _, state = env.reset_to_design(key, params, i)
        return design_change.schedule(env.config, params, state, i)

    for i in (0, 9):
        state = scheduled_reset(jax.random.key(i), params, i)
        assert int(state.change_step) == steps[i]
        np.testing.assert_array_equal(state.next_design, stack[(i + 1) % 10])


def _build_one_cell(row, col):
    """Test only: with stride 1, walks to plan (row, col), drops one brick there and walks right
    to the wall: the final grid is that one brick, whatever the design."""
    import jax.numpy as jnp

    from snac_jax.policy import Policy

    def init(key, design):
        return jnp.zeros((), jnp.int32)

    def act(params, t, obs, key):
        action = jnp.where(t < col, RIGHT, jnp.where(t < col + row, 2, jnp.where(t == col + row, DROP, RIGHT)))
        return action.astype(jnp.int32), t + 1

    return Policy(init, act, None, "one-cell")


@pytest.mark.slow
def test_evaluation_scores_each_test_design_against_the_one_it_changes_to():
    from snac_jax.evaluation import evaluate_task

    task, cell = "2d-dynamic-dense", (10, 10)
    stack = [designs.fixed_design(n) for n in test_design_names(task)]
    expected = [_hand_iou([cell], stack[(i + 1) % 10]) for i in range(10)]
    unchanged = [_hand_iou([cell], stack[i]) for i in range(10)]
    assert expected != unchanged  # the cell is in some test designs and not in others
    # Every scheduled change step (1 + floor(i * 29 / 9) <= 30) comes before the step limit.
    result = evaluate_task(
        task,
        _build_one_cell(*cell),
        episodes_per_test_design=2,
        stride_probs=(1, 0, 0),
        max_steps=40,
        design_change=(1, 30),
    )
    means = [stats["mean"] for stats in result.per_design.values()]
    np.testing.assert_allclose(means, expected, rtol=1e-6)


@pytest.mark.slow
def test_the_handcrafted_policy_re_plans_on_the_changed_design():
    import dataclasses

    from snac_jax.evaluation import evaluate_task
    from snac_jax.policies.handcrafted import handcrafted_policy

    env, _ = make("2d-dynamic-dense", design_change=(1, 1), design_bank_size=2)
    frozen_config = dataclasses.replace(env.config, design_change=None)  # plans on the first design only
    frozen = handcrafted_policy(type(env)(frozen_config, env.default_params))
    kwargs = dict(episodes_per_test_design=2, design_change=(1, 1))  # every test design changes at step 1
    following = evaluate_task("2d-dynamic-dense", handcrafted_policy, **kwargs).mean
    stale = evaluate_task("2d-dynamic-dense", frozen, **kwargs).mean
    assert following > 0.55 and following > stale + 0.25, (following, stale)  # seed 0: 0.69 and 0.30


def test_the_caption_marks_the_change_step():
    from snac_jax.rendering import caption_lines

    env, _ = make("2d-dynamic-dense", design_change=(3, 3), design_bank_size=2)
    params = make_params(np.stack([OLD, NEW]), 2, max_steps=600)
    reset_to_design, step_with_stride = _jitted(env)
    _, state = reset_to_design(jax.random.key(0), params, 0)
    assert "design changes at step 3" in caption_lines(env, state)[0]
    for _ in range(3):
        state = step_with_stride(state, RIGHT, 1, params)[1]
    assert "design changed at step 3" in caption_lines(env, state)[0]
    assert env.render(state, params).ndim == 3  # draws the design in force


@pytest.mark.slow
@pytest.mark.parametrize("reset", ["loop", "select"])
def test_step_batch_equals_vmapped_step_with_both_extensions(reset):
    env, params = make("2d-dynamic-dense", design_change=(2, 4), landmark_action=2, design_bank_size=8, max_steps=6)
    keys = jax.random.split(jax.random.key(4), 5)
    _, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    batched, vmapped = states, states
    for t in range(9):  # past the step limit: some worlds reset
        keys = jax.random.split(jax.random.fold_in(jax.random.key(5), t), 5)
        actions = jax.numpy.asarray([4, 5, 1, 2, t % 6])
        out_b = env.step_batch(keys, batched, actions, params, reset=reset)
        out_v = step(keys, vmapped, actions, params)
        for a, b in zip(jax.tree.leaves(out_b), jax.tree.leaves(out_v)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        batched, vmapped = out_b[1], out_v[1]


def test_a_numpy_int_bank_of_one_is_refused_as_a_python_int_is():
    for size in (1, np.int64(1)):
        with pytest.raises(ValueError, match="design_change needs a design bank of at least 2 designs"):
            make("2d-dynamic-dense", design_change=(10, 14), design_bank_size=size)
