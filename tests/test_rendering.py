"""Rendering: documented frame shapes and the documented colours at known cells."""

from __future__ import annotations

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import snac_jax
from snac_jax import rendering
from snac_jax.rendering import (
    CAPTION_HEIGHT,
    CORRECT,
    CURVE,
    DESIGN,
    EMPTY,
    HEADROOM_1D,
    LANDMARK,
    PADDING_COLOUR,
    PARTIAL,
    ROBOT,
    WINDOW,
    WRONG,
    render,
    world_layout,
)


def _reset(task, **overrides):
    env, params = snac_jax.make(task, **overrides)
    _, state = env.reset(jax.random.key(0), params)
    return env, params, state


def _with(state, config, plan_cells: dict, position=None):
    """`state` with plan cells set to heights (grid only) and the robot moved."""
    (pr, pc) = config.pad
    grid = np.asarray(state.grid).copy()
    for (r, c), h in plan_cells.items():
        grid[r + pr, c + pc] = h
    state = state.replace(grid=jnp.asarray(grid))
    if position is not None:
        state = state.replace(position=jnp.asarray(position, jnp.int32))
    return state


def _colour(frame, yx):
    return tuple(int(v) for v in frame[yx[0], yx[1]])


def test_2d_shape_and_cell_colours():
    env, params, state = _reset("2d-static-dense", landmarks=4)
    design = np.asarray(state.design)
    on_design = tuple(int(i) for i in np.argwhere(design > 0)[0])
    off_design = (0, 19)
    assert design[off_design] == 0
    empty_design = tuple(int(i) for i in np.argwhere(design > 0)[-1])
    landmark = tuple(int(i) for i in np.argwhere(np.asarray(state.landmarks))[0])  # padded coordinates
    state = _with(state, env.config, {on_design: 1, off_design: 1}, position=(10, 3))

    frame = render(env, state, params)
    cell = rendering.DEFAULT_CELL[2]
    assert frame.dtype == np.uint8
    assert frame.shape == (CAPTION_HEIGHT + 26 * cell, 26 * cell, 3)
    layout = world_layout(env, params)
    pad = env.config.pad[0]
    at = lambda plan: _colour(frame, layout.cell_center(plan[0] + pad, plan[1] + pad))
    assert at(on_design) == CORRECT
    assert at(off_design) == WRONG
    assert at(empty_design) == DESIGN
    assert at((19, 0)) == EMPTY
    assert _colour(frame, layout.cell_center(0, 0)) == PADDING_COLOUR
    assert _colour(frame, layout.cell_center(*landmark)) == LANDMARK
    assert at((10, 3)) == ROBOT
    # The window box: its top-left corner is the robot's plan position in padded coordinates.
    y0, x0, _, _ = layout.cell_box(10, 3)
    assert _colour(frame, (y0, x0 + cell // 2)) == WINDOW
    y1, x1 = layout.cell_box(10 + 6, 3 + 6)[2:]
    assert _colour(frame, (y1 - 1, x1 - cell // 2)) == WINDOW
    # Outside the window nothing is boxed.
    y, x = layout.cell_box(2, 20)[:2]
    assert _colour(frame, (y + 1, x + cell // 2)) != WINDOW


def test_1d_columns_against_the_design_curve():
    env, params, state = _reset("1d-static-sin")
    design = np.asarray(state.design)[0]
    # column 3: one brick short of its design; column 10: two bricks over it
    state = _with(state, env.config, {(0, 3): int(design[3]) - 1, (0, 10): int(design[10]) + 2}, position=(0, 7))
    frame = render(env, state, params, caption=False)
    cell = rendering.DEFAULT_CELL[1]
    levels = int(np.max(np.asarray(params.designs))) + HEADROOM_1D
    assert frame.shape == ((levels + 1) * cell, 34 * cell, 3)
    layout = world_layout(env, params, caption_lines=0)
    pc = env.config.pad[1]
    level = lambda col, k: _colour(frame, _centre(layout.level_box(col + pc, k)))
    assert level(3, 0) == CORRECT
    assert level(3, int(design[3]) - 2) == CORRECT
    assert level(3, int(design[3]) - 1) == DESIGN  # the missing top brick
    assert level(3, int(design[3])) == EMPTY
    assert level(10, int(design[10]) - 1) == CORRECT
    assert level(10, int(design[10])) == WRONG
    assert level(10, int(design[10]) + 1) == WRONG
    assert level(10, int(design[10]) + 2) == EMPTY
    assert level(0, 0) == DESIGN  # an unbuilt column
    assert _colour(frame, _centre(layout.level_box(0, 0))) == PADDING_COLOUR
    assert _colour(frame, layout.robot_center(7 + pc)) == ROBOT
    # The design curve sits on top of the design levels of each column.
    y = layout.level_box(20 + pc, int(design[20]) - 1)[0]
    assert _colour(frame, (y, _centre(layout.level_box(20 + pc, 0))[1])) == CURVE
    # The window spans the 5 columns from the robot's plan column (padded coordinates).
    x0 = layout.level_box(7, 0)[1]
    assert _colour(frame, (frame.shape[0] // 2, x0)) == WINDOW


def test_3d_top_view_and_voxels():
    env, params, state = _reset("3d-static-sparse")
    design = np.asarray(state.design)
    ring = [tuple(int(i) for i in rc) for rc in np.argwhere(design > 0)[:3]]
    d = int(design[ring[0]])
    empty_frame = render(env, state, params)
    state = _with(state, env.config, {ring[0]: d, ring[1]: d - 2, ring[2]: d + 1, (0, 0): 1}, position=(0, 1))
    frame = render(env, state, params)
    assert frame.shape == empty_frame.shape  # the shape never depends on the state
    layout = world_layout(env, params)
    pad = env.config.pad[0]
    at = lambda plan: _colour(frame, layout.cell_center(plan[0] + pad, plan[1] + pad))
    assert at(ring[0]) == CORRECT
    assert at(ring[1]) == PARTIAL
    assert at(ring[2]) == WRONG
    assert at((0, 0)) == WRONG  # off the design
    assert at((10, 10)) == EMPTY
    assert at((0, 1)) == ROBOT
    # The voxel view (left of the top view) shows correct and wrong cubes once they are built.
    iso_before, iso_after = empty_frame[:, : layout.left], frame[:, : layout.left]
    count = lambda image, colour: int(np.sum(np.all(image == colour, axis=-1)))
    assert count(iso_before, CORRECT) == 0 and count(iso_before, WRONG) == 0
    assert count(iso_after, CORRECT) > 0 and count(iso_after, WRONG) > 0


def test_caption_is_a_band_on_top():
    env, params, state = _reset("2d-static-sparse")
    plain = render(env, state, params, caption=False)
    captioned = render(env, state, params, caption=["a", "b"])
    assert captioned.shape == (plain.shape[0] + 2 * CAPTION_HEIGHT,) + plain.shape[1:]
    np.testing.assert_array_equal(captioned[2 * CAPTION_HEIGHT :], plain)
    band = captioned[: 2 * CAPTION_HEIGHT]
    assert np.any(np.all(band == rendering.CAPTION_FG, axis=-1))  # some text was written


def test_observation_view_uses_only_the_observation():
    env, params, state = _reset("2d-dynamic-sparse", test_design=1)
    obs = env.get_obs(state, params)
    view = rendering.render_observation(env, obs, cell=20)
    window_px = 7 * 20
    assert view.shape[0] >= window_px and view.shape[1] > window_px  # window plus the design beside it
    # robot at the window's centre; at the corner (0, 0) the upper-left window cells are padding
    assert _colour(view, (3 * 20 + 10, 3 * 20 + 10)) == ROBOT
    assert _colour(view, (10, 10)) == PADDING_COLOUR
    with pytest.raises(ValueError, match="observation"):
        rendering.render_observation(env, obs[:-1])


def test_bad_input_is_rejected():
    env, params, state = _reset("2d-static-dense")
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    with pytest.raises(ValueError, match="one world"):
        render(env, batch, params)
    with pytest.raises(ValueError, match="cell"):
        render(env, state, params, cell=2)
    with pytest.raises(ValueError, match="SNACEnv"):
        render(object(), state, params)


def test_png_and_gif_round_trip(tmp_path):
    env, params, state = _reset("1d-static-step")
    frame = render(env, state, params)
    png = rendering.save_png(tmp_path / "f.png", frame)
    np.testing.assert_array_equal(iio.imread(png), frame)
    frames = [rendering.add_caption(frame, [f"frame {i}"]) for i in range(3)]
    gif = rendering.save_gif(tmp_path / "f.gif", frames, fps=5)
    assert iio.imread(gif, index=None).shape == (3,) + frames[0].shape
    with pytest.raises(ValueError, match="one shape"):
        rendering.save_gif(tmp_path / "g.gif", [frame, frame[:-1]])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.gif", "f.png"]  # no temporary files left


def _centre(box):
    y0, x0, y1, x1 = box
    return ((y0 + y1) // 2, (x0 + x1) // 2)
