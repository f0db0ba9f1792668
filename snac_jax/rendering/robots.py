"""Pictures of a world with several robots (SPEC §13): `render`'s views, each robot in its colour.

The world is drawn by `render` exactly as for one robot (robot 0 in its place), then every
robot's window box and disc are painted over it in `ROBOT_COLOURS[i]`: the boxes first, then the
discs, so no box hides a robot. Robot 0's disc and box cover the ones `render` drew (same centre,
radius and box), so nothing of the single-robot colours is left. In 3D the isometric view tints
robot 0's window on the floor, as `render` does; every robot's disc is painted on its column.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from snac_jax.rendering.draw import box, disc
from snac_jax.rendering.isometric import _MARGIN, iso_geometry
from snac_jax.rendering.snapshot import Snapshot
from snac_jax.rendering.world import DEFAULT_CELL, HEADROOM_3D, render, world_layout
from snac_jax.state import EnvParams

ROBOT_COLOURS = ((24, 40, 150), (200, 30, 200), (0, 160, 170), (0, 0, 0))
"""Robot i's colour: robot 0 keeps the single robot's `ROBOT`; the others are none of the
palette's cell colours."""


def render_robots(
    env, state, params: EnvParams | None = None, *, cell: int | None = None, caption: bool | Sequence[str] = True
) -> np.ndarray:
    """One world of a `snac_jax.multi.MultiSNACEnv` as a uint8 RGB frame, each robot in its
    colour. `state` is one unbatched `MultiState`; `cell` and `caption` as `render` (the default
    caption adds the number of robots)."""
    config = env.config
    params = env.default_params if params is None else params
    positions = np.asarray(state.positions)
    if positions.ndim != 2:
        raise ValueError(f"render_robots takes one world's state, got positions of shape {positions.shape}")
    cell = cell if cell is not None else DEFAULT_CELL[config.dim]
    first = state.world.replace(position=state.positions[0])
    if caption is True:
        snap = Snapshot.of(config, first)
        caption = [
            f"{config.task_id}  {len(positions)} robots  step {snap.time}  "
            f"bricks {snap.bricks_used}/{snap.max_bricks}  IoU {snap.iou:.3f}"
        ]
    frame = render(env.single, first, params, cell=cell, caption=caption).copy()
    layout = world_layout(env.single, params, cell=cell, caption_lines=0 if caption is False else len(caption))
    (pr, pc), (wr, wc) = config.pad, config.window_shape
    for i, (row, col) in enumerate(positions):
        colour = ROBOT_COLOURS[i]
        if config.dim == 1:
            top = layout.top
            x = layout.left + col * cell
            box(frame, top, x, top + (layout.levels + 1) * cell, x + wc * cell, max(2, cell // 6), colour)
        else:
            y0, x0, _, _ = layout.cell_box(row, col)  # the window's top-left is the plan position, padded
            box(frame, y0, x0, y0 + wr * cell, x0 + wc * cell, max(2, cell // 7), colour)
    for i, (row, col) in enumerate(positions):
        colour = ROBOT_COLOURS[i]
        if config.dim == 1:
            cy, cx = layout.robot_center(col + pc)
            disc(frame, cy, cx, cell * 0.4, colour)
            continue
        cy, cx = layout.cell_center(row + pr, col + pc)
        disc(frame, cy, cx, cell * 0.36, colour)
        if config.dim == 3:
            iy, ix, radius = _isometric_centre(config, state.world, params, cell, row, col)
            disc(frame, layout.top + iy, ix, radius, colour)
    return frame


def _isometric_centre(config, world, params, cell: int, row: int, col: int) -> tuple[int, int, float]:
    """Where `render_isometric` paints the robot of plan cell (row, col): on top of its column."""
    levels = int(np.max(np.asarray(params.designs))) + HEADROOM_3D
    _, _, a, b, cube = iso_geometry(config, cell, levels)
    rows = config.plan_shape[0]
    pr, pc = config.pad
    height = int(max(np.asarray(world.grid)[row + pr, col + pc], 0))
    x = (rows - 1) * a + _MARGIN + (col - row) * a
    floor_y = levels * cube + _MARGIN + (col + row) * b + cube
    return floor_y - min(height, levels) * cube + b - cube // 2, x + a, a * 0.55
