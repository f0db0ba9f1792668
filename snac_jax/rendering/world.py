"""Pictures of one world's state: the 1D columns, the 2D grid, the 3D voxel and top views.

`render` is what `SNACEnv.render`, the `snac render` CLI and the notebooks call. A frame's
shape depends only on the configuration, the params' designs and `cell`, never on the state,
so the frames of an episode stack into a video. `world_layout` says where each cell lands,
for tests and for anyone drawing on top of a frame.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from snac_jax.config import EnvConfig
from snac_jax.rendering.draw import (
    CAPTION_HEIGHT,
    CORRECT,
    CURVE,
    DESIGN,
    EMPTY,
    LANDMARK,
    OVERFLOW,
    PADDING_COLOUR,
    PARTIAL,
    ROBOT,
    WINDOW,
    WRONG,
    add_caption,
    box,
    config_of,
    disc,
    pad_to_height,
    upscale,
)
from snac_jax.rendering.isometric import iso_geometry, render_isometric
from snac_jax.rendering.snapshot import Snapshot
from snac_jax.state import EnvParams, EnvState
from snac_jax.transition import PADDING

DEFAULT_CELL = {1: 12, 2: 16, 3: 14}
"""Default pixels per cell side (in 3D: the top view's cells and half an isometric tile)."""

HEADROOM_1D = 8
"""Levels drawn above the tallest design column in 1D (taller stacks are cut, see OVERFLOW)."""

HEADROOM_3D = 4
"""Voxel levels drawn above the tallest design height in 3D."""


@dataclasses.dataclass(frozen=True)
class WorldLayout:
    """Where the cells of `render`'s world view land in the frame (caption included).

    `cell_box(row, col)` gives the pixel box (y0, x0, y1, x1) of a padded-grid cell in the
    2D view, the 3D top view, or (1D) the box of brick `level` of a column through
    `level_box(col, level)`. `robot_center(col)` is the 1D robot's ground-strip centre.
    """

    dim: int
    cell: int
    top: int  # first pixel row of the world view (below the caption)
    left: int  # first pixel column of the grid / top view
    levels: int = 0  # 1D: visible levels per column

    def cell_box(self, row: int, col: int) -> tuple[int, int, int, int]:
        y0, x0 = self.top + row * self.cell, self.left + col * self.cell
        return (y0, x0, y0 + self.cell, x0 + self.cell)

    def cell_center(self, row: int, col: int) -> tuple[int, int]:
        y0, x0, _, _ = self.cell_box(row, col)
        return (y0 + self.cell // 2, x0 + self.cell // 2)

    def level_box(self, col: int, level: int) -> tuple[int, int, int, int]:
        """1D: the box of brick level `level` (0 = on the ground) of padded column `col`."""
        return self.cell_box(self.levels - 1 - level, col)

    def robot_center(self, col: int) -> tuple[int, int]:
        """1D: the robot disc's centre under padded column `col`."""
        return self.cell_center(self.levels, col)


def render(
    env,
    state: EnvState,
    params: EnvParams | None = None,
    *,
    cell: int | None = None,
    caption: bool | Sequence[str] = True,
) -> np.ndarray:
    """One world as a uint8 RGB frame (H, W, 3); see the package docstring for the views.

    `env` is a `SNACEnv` (or its `EnvConfig`), `state` one unbatched `EnvState`, `params` the
    `EnvParams` (only its designs are read, to fix the frame's height; defaults to the env's).
    `caption=True` adds a band with task, step, bricks and IoU; a list of strings adds those
    lines instead; `False` adds nothing.
    """
    config = config_of(env)
    if params is None:
        params = env.default_params
    snapshot = Snapshot.of(config, state)
    cell = _check_cell(cell if cell is not None else DEFAULT_CELL[config.dim])
    tallest = int(np.max(np.asarray(params.designs)))
    if config.dim == 1:
        world = _render_1d(config, snapshot, cell, tallest + HEADROOM_1D)
    elif config.dim == 2:
        world = _render_top(config, snapshot, cell)
    else:
        world = _render_3d(config, snapshot, cell, tallest + HEADROOM_3D)
    if caption is False:
        return world
    lines = caption_lines(config, snapshot) if caption is True else list(caption)
    return add_caption(world, lines)


def world_layout(
    env, params: EnvParams | None = None, *, cell: int | None = None, caption_lines: int = 1
) -> WorldLayout:
    """Where `render` puts the cells (with `caption_lines` caption lines; 0 for `caption=False`)."""
    config = config_of(env)
    params = params if params is not None else env.default_params
    cell = cell if cell is not None else DEFAULT_CELL[config.dim]
    top = caption_lines * CAPTION_HEIGHT
    if config.dim == 1:
        levels = int(np.max(np.asarray(params.designs))) + HEADROOM_1D
        return WorldLayout(dim=1, cell=cell, top=top, left=0, levels=levels)
    if config.dim == 2:
        return WorldLayout(dim=2, cell=cell, top=top, left=0)
    iso_width = iso_geometry(config, cell, 1)[0]
    return WorldLayout(dim=3, cell=cell, top=top, left=iso_width)


def caption_lines(env_or_config, state: EnvState | Snapshot, reward: float | None = None) -> list[str]:
    """The default caption: task, step, bricks used of the budget, IoU (and a reward if given);
    with the extensions, the landmarks left to place and the step the design changes at."""
    config = config_of(env_or_config)
    snap = state if isinstance(state, Snapshot) else Snapshot.of(config, state)
    text = f"{config.task_id}  step {snap.time}  bricks {snap.bricks_used}/{snap.max_bricks}  IoU {snap.iou:.3f}"
    if reward is not None:
        text += f"  reward {reward:+g}"
    if snap.landmarks_left is not None:
        text += f"  landmarks left {snap.landmarks_left}"
    if snap.change_step is not None:  # the step the design changes at (SPEC §15)
        text += f"  design {'changed' if snap.time >= snap.change_step else 'changes'} at step {snap.change_step}"
    return [text]


def _check_cell(cell: int) -> int:
    if not isinstance(cell, (int, np.integer)) or isinstance(cell, bool) or cell < 4:
        raise ValueError(f"cell must be an int >= 4 (pixels per cell), got {cell!r}")
    return int(cell)


def _render_1d(config: EnvConfig, snap: Snapshot, cell: int, levels: int) -> np.ndarray:
    pc = config.pad[1]
    heights = snap.grid[0]
    design = snap.padded_design(config)[0]
    is_padding = heights == PADDING
    built = np.maximum(heights, 0)
    level = np.arange(levels)[::-1, None]  # row 0 of the picture is the top level
    colours = np.empty((levels + 1, heights.size, 3), np.uint8)
    colours[:levels] = EMPTY
    colours[:levels][level < design] = DESIGN
    colours[:levels][(level < built) & (level < design)] = CORRECT
    colours[:levels][(level < built) & (level >= design)] = WRONG
    colours[0][built > levels] = OVERFLOW
    colours[:levels, is_padding] = PADDING_COLOUR
    colours[levels] = PADDING_COLOUR  # ground strip
    image = upscale(colours, cell)

    # The design curve: a line on top of each design column, joined between columns.
    thickness = max(1, cell // 6)
    tops = (levels - design) * cell
    for col in range(pc, pc + config.plan_shape[1]):
        y = tops[col]
        image[max(y - thickness // 2, 0) : y + (thickness + 1) // 2, col * cell : (col + 1) * cell] = CURVE
        if col + 1 < pc + config.plan_shape[1]:
            y0, y1 = sorted((tops[col], tops[col + 1]))
            x = (col + 1) * cell
            image[y0 : y1 + 1, max(x - thickness // 2, 0) : x + (thickness + 1) // 2] = CURVE

    robot_col = snap.position[1] + pc
    disc(image, levels * cell + cell // 2, robot_col * cell + cell // 2, cell * 0.4, ROBOT)
    x0 = snap.position[1] * cell  # the window's first column is the robot's plan column (padded)
    box(image, 0, x0, image.shape[0], x0 + config.window_shape[1] * cell, max(2, cell // 6), WINDOW)
    return image


def _render_top(config: EnvConfig, snap: Snapshot, cell: int) -> np.ndarray:
    """The padded grid seen from above: the 2D view, and the right half of the 3D view."""
    grid = snap.grid
    design = snap.padded_design(config)
    colours = np.empty(grid.shape + (3,), np.uint8)
    colours[:] = EMPTY
    colours[design > 0] = DESIGN
    if config.dim == 3:
        colours[(grid > 0) & (grid < design)] = PARTIAL
        colours[(grid > 0) & (grid == design)] = CORRECT
        colours[(grid > 0) & (grid > design)] = WRONG
    else:
        colours[(grid > 0) & (design > 0)] = CORRECT
        colours[(grid > 0) & (design == 0)] = WRONG
    if snap.landmarks is not None:
        colours[snap.landmarks] = LANDMARK
    colours[grid == PADDING] = PADDING_COLOUR
    image = upscale(colours, cell)

    pr, pc = config.pad
    row, col = snap.position[0] + pr, snap.position[1] + pc
    disc(image, row * cell + cell // 2, col * cell + cell // 2, cell * 0.36, ROBOT)
    wr, wc = config.window_shape
    y0, x0 = snap.position[0] * cell, snap.position[1] * cell  # window top-left = plan position, padded
    box(image, y0, x0, y0 + wr * cell, x0 + wc * cell, max(2, cell // 7), WINDOW)
    return image


def _render_3d(config: EnvConfig, snap: Snapshot, cell: int, levels: int) -> np.ndarray:
    iso = render_isometric(config, snap, cell, levels)
    top = _render_top(config, snap, cell)
    height = max(iso.shape[0], top.shape[0])
    return np.concatenate([pad_to_height(iso, height), pad_to_height(top, height)], axis=1)
