"""The 3D world's voxel view: an isometric projection painted with the painter's algorithm.

Drawn in numpy (cube sprites pasted back to front, bottom to top), so a 3D frame needs no 3D
plotting library and costs milliseconds. Voxels at or below the design height are `CORRECT`,
above it `WRONG`, the design's unbuilt voxels translucent `DESIGN` ghosts; floor tiles show
the design, landmarks and (tinted `WINDOW`) what the robot sees.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from snac_jax.config import EnvConfig
from snac_jax.rendering.draw import BACKGROUND, CORRECT, DESIGN, EMPTY, LANDMARK, OVERFLOW, ROBOT, WINDOW, WRONG, disc
from snac_jax.rendering.snapshot import Snapshot

_GHOST_ALPHA = 0.14
_MARGIN = 6


def iso_geometry(config: EnvConfig, cell: int, levels: int) -> tuple[int, int, int, int, int]:
    """(width, height, half tile width a, half tile height b, cube height) of the isometric view."""
    rows, cols = config.plan_shape
    a = max((3 * cell) // 4, 3)
    b = max(a // 2, 2)
    cube = a
    width = (rows + cols) * a + 2 * _MARGIN
    height = (rows + cols) * b + (levels + 2) * cube + 2 * _MARGIN  # + the floor sprite's box
    return width, height, a, b, cube


@lru_cache(maxsize=16)
def _cube_sprite(a: int, b: int, cube: int) -> tuple[np.ndarray, ...]:
    """Masks (top, left, right, outline) of an isometric cube in a (2b+cube, 2a) box."""
    h, w = 2 * b + cube, 2 * a
    y, x = np.mgrid[0:h, 0:w] + 0.5
    top = (np.abs(x - a) / a + np.abs(y - b) / b) <= 1.0
    slope = b / a
    left = (x <= a) & (y >= b + x * slope) & (y <= b + cube + x * slope) & ~top
    right = (x > a) & (y >= 2 * b - (x - a) * slope) & (y <= 2 * b + cube - (x - a) * slope) & ~top
    solid = top | left | right
    faces = np.where(top, 1, np.where(left, 2, np.where(right, 3, 0)))
    # Outline: pixels whose right or lower neighbour lies on another face or outside.
    edge = np.zeros_like(solid)
    edge[:, :-1] |= faces[:, :-1] != faces[:, 1:]
    edge[:-1, :] |= faces[:-1, :] != faces[1:, :]
    edge[:, -1] = edge[-1, :] = True
    return top, left, right, edge & solid


def _paint_cube(canvas: np.ndarray, y: int, x: int, sprite, colour, alpha: float = 1.0, floor_only: bool = False):
    top, left, right, edge = sprite
    region = canvas[y : y + top.shape[0], x : x + top.shape[1]]
    base = np.asarray(colour, np.float32)
    faces = ((top, 1.0),) if floor_only else ((top, 1.0), (left, 0.78), (right, 0.6))
    for mask, shade in faces:
        target = base * shade
        if alpha < 1.0:
            region[mask] = (region[mask] * (1 - alpha) + target * alpha).astype(np.uint8)
        else:
            region[mask] = target.astype(np.uint8)
    if alpha == 1.0:
        outline = edge & (top if floor_only else (top | left | right))
        region[outline] = (region[outline] * (0.85 if floor_only else 0.55)).astype(np.uint8)


def render_isometric(config: EnvConfig, snap: Snapshot, cell: int, levels: int) -> np.ndarray:
    """The voxel view of one world, `levels` levels tall.

    Painter's algorithm: back (row + col small) to front, bottom to top.
    """
    width, height, a, b, cube = iso_geometry(config, cell, levels)
    rows, cols = config.plan_shape
    pr, pc = config.pad
    canvas = np.empty((height, width, 3), np.uint8)
    canvas[:] = BACKGROUND
    sprite = _cube_sprite(a, b, cube)
    built = np.maximum(snap.grid[pr : pr + rows, pc : pc + cols], 0)
    design = snap.design
    landmarks = None if snap.landmarks is None else snap.landmarks[pr : pr + rows, pc : pc + cols]
    robot = snap.position
    window_rows = range(robot[0] - config.half_window, robot[0] + config.half_window + 1)
    window_cols = range(robot[1] - config.half_window, robot[1] + config.half_window + 1)
    origin_x = (rows - 1) * a + _MARGIN
    origin_y = levels * cube + _MARGIN  # the floor tile of cell (0, 0) sits at level 0

    order = sorted(((r, c) for r in range(rows) for c in range(cols)), key=lambda rc: (rc[0] + rc[1], rc[0]))
    for r, c in order:
        x = origin_x + (c - r) * a
        floor_y = origin_y + (c + r) * b + cube
        floor = DESIGN if design[r, c] > 0 else EMPTY
        if landmarks is not None and landmarks[r, c]:
            floor = LANDMARK
        if r in window_rows and c in window_cols:
            floor = tuple(int(0.65 * f + 0.35 * w) for w, f in zip(WINDOW, floor))
        _paint_cube(canvas, floor_y, x, sprite, floor, floor_only=True)
        h, d = int(built[r, c]), int(design[r, c])
        for level in range(min(h, levels)):
            colour = OVERFLOW if (level == levels - 1 and h > levels) else (CORRECT if level < d else WRONG)
            _paint_cube(canvas, floor_y - (level + 1) * cube, x, sprite, colour)
        for level in range(h, min(d, levels)):
            _paint_cube(canvas, floor_y - (level + 1) * cube, x, sprite, DESIGN, alpha=_GHOST_ALPHA)
        if (r, c) == robot:
            robot_centre = (floor_y - min(h, levels) * cube + b - cube // 2, x + a)
    # The robot is painted last, on top of whatever stands in front of it, so it never hides.
    disc(canvas, robot_centre[0], robot_centre[1], a * 0.55, ROBOT)
    return canvas
