"""Property tests (hypothesis) of the invariants every episode must keep, on any action/stride sequence."""

from functools import cache, partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from snac_jax import TASKS, grid_iou, iou, make
from snac_jax.replay import replay

STEPS = 150


@partial(jax.jit, static_argnames="env")
def _trajectory(env, params, key, actions, strides):
    _, state = env.reset(key, params)

    def body(state, action_stride):
        _, state, reward, terminated, _ = env.step_with_stride(state, *action_stride, params)
        return state, (state, iou(state), reward, terminated)

    return jax.lax.scan(body, state, (actions, strides))[1]


@cache
def _env(task):
    """Built when a test first needs it, not at import: a dynamic task's bank is sampled by a
    compiled program, and every xdist worker imports this module to collect it."""
    return make(task, design_bank_size=32) if "dynamic" in task else make(task)


# Drop-heavy action sequences: drops are what the invariants are about.
sequences = st.integers(0, 2**31 - 1).flatmap(
    lambda seed: st.tuples(
        st.just(seed),
        st.lists(st.integers(0, 7), min_size=STEPS, max_size=STEPS),
        st.lists(st.integers(1, 3), min_size=STEPS, max_size=STEPS),
    )
)


@pytest.mark.parametrize("task", TASKS)
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=sequences)
def test_invariants_hold_on_any_sequence(task, data):
    seed, actions, strides = data
    env, params = _env(task)
    actions = np.asarray(actions) % env.num_actions
    states, ious, rewards, terminated = _trajectory(
        env, params, jax.random.key(seed), jnp.asarray(actions, jnp.int32), jnp.asarray(strides, jnp.int32)
    )
    states = jax.tree.map(np.asarray, states)
    ious = np.asarray(ious)
    # Stop at the first end: the state is only meaningful up to there.
    ended = np.flatnonzero(np.asarray(terminated))
    last = int(ended[0]) if ended.size else STEPS - 1
    (pr, pc), (h, w) = env.config.pad, env.config.plan_shape

    assert np.all(states.bricks_used[: last + 1] <= states.max_bricks[: last + 1])
    pos = states.position[: last + 1]
    assert np.all((pos[:, 0] >= 0) & (pos[:, 0] < h) & (pos[:, 1] >= 0) & (pos[:, 1] < w))
    assert np.all((ious >= 0) & (ious <= 1))
    grids = states.grid[: last + 1]
    # Bricks never land in the padding; 2D cells stay binary.
    assert np.all(grids[:, :pr, :] == -1) and np.all(grids[:, :, :pc] == -1)
    assert np.all(grids[:, pr + h :, :] == -1) and np.all(grids[:, :, pc + w :] == -1)
    if env.config.binary_grid:
        assert grids.max() <= 1
    if env.config.obstacles:  # in 3D the robot never stands on a brick
        on_cell = grids[np.arange(last + 1), pos[:, 0] + pr, pos[:, 1] + pc]
        assert np.all(on_cell == 0)
    # The incremental IoU equals the IoU computed from the cells, and is 1 iff grid == design.
    plan = grids[last, pr : pr + h, pc : pc + w]
    design = states.design[last]
    assert ious[last] == pytest.approx(grid_iou(plan, design, env.config.dim), abs=1e-6)
    assert (ious[last] == 1.0) == bool(
        np.array_equal(np.maximum(plan, 0) if not env.config.binary_grid else plan, design)
    )
    # Rewards come from the scheme's values only.
    allowed = {0.0, 5.0} if env.config.reward_scheme == "binary" else {0.0, -1.0, 1.0, 10.0}
    assert set(np.unique(np.asarray(rewards))) <= allowed


def _build_exactly(env, design, skip_last=False):
    """Actions that build `design` exactly with stride 1 (a test-only oracle that knows the position)."""
    dim = env.config.dim
    design = np.asarray(design)
    actions = []
    if dim == 1:
        for height in design[0]:
            actions += [2] * int(height) + [1]
    elif dim == 2:
        for row in range(20):
            cols = range(20) if row % 2 == 0 else range(19, -1, -1)
            for col in cols:
                actions += [4] * int(design[row, col]) + [1 if row % 2 == 0 else 0]
            actions.append(2)
    else:  # 3D without obstacles: walk row r, drop onto row r + 1 (action 6)
        for row in range(19):
            cols = range(20) if row % 2 == 0 else range(19, -1, -1)
            for col in cols:
                actions += [6] * int(design[row + 1, col]) + [1 if row % 2 == 0 else 0]
            actions.append(2)
    drop_action = {1: 2, 2: 4, 3: 6}[dim]
    last_drop = max(i for i, a in enumerate(actions) if a == drop_action)
    actions = actions[: last_drop + 1]  # the last brick ends the episode: nothing after it
    return actions[:-1] if skip_last else actions


@pytest.mark.parametrize("task", ["1d-static-gauss", "2d-static-sparse", "3d-static-dense"])
@pytest.mark.parametrize("skip_last", [False, True])
def test_iou_is_one_exactly_when_the_design_is_built(task, skip_last):
    overrides = {"stride_probs": (1, 0, 0)}
    if task.startswith("3d"):
        overrides["obstacles"] = False
        assert np.asarray(make(task)[1].designs[0])[0].sum() == 0  # row 0 is empty: reachable from row 1
    env, params = make(task, **overrides)
    design = np.asarray(params.designs[0])
    actions = _build_exactly(env, design, skip_last)
    assert len(actions) <= int(params.max_steps_in_episode)
    out = replay(env, params, actions, [1] * len(actions))
    built = np.asarray(out["final_grid"]).reshape(design.shape)
    assert np.array_equal(built, design) != skip_last
    assert (out["final_iou"] == 1.0) != skip_last
    # The budget is exactly the design's bricks, so the last brick ends the episode.
    assert bool(out["terminated"][-1]) != skip_last
    assert not np.any(out["terminated"][:-1])
