"""Pictures of SNAC worlds: RGB frames composed with numpy, outside the jitted step.

Nothing here is traced: every function takes one concrete (unbatched) state, converts it to
numpy and paints cells as blocks of pixels. Text (the caption and the game's counters) is drawn
with Pillow, which imageio already depends on; matplotlib is not needed, even for the 3D voxel
view, which is an isometric painter's-algorithm projection in numpy.

Views (`render`):

- **1D**: one column of bricks per cell of the padded world (34 columns; the two padding
  columns on each side are `PADDING`-coloured). Brick levels at or below the design height are
  `CORRECT`, above it `WRONG`; unbuilt design levels are `DESIGN`; the design curve is a
  `CURVE` line on top of the design levels. Under the columns a ground strip holds the robot
  (a `ROBOT` disc under its column); the window (2·ws+1 columns) is a `WINDOW` box.
- **2D**: the padded 26x26 grid seen from above. Empty cells are `EMPTY`, empty design cells
  `DESIGN`, bricks on the design `CORRECT`, bricks off the design `WRONG`, landmarks
  `LANDMARK`, padding `PADDING`; the robot is a `ROBOT` disc in its cell and the window a
  `WINDOW` box around the (2·ws+1)² cells it sees.
- **3D**: an isometric voxel view of the design area (left) and a top view of the padded grid
  (right). Voxels at or below the design height are `CORRECT`, above it `WRONG`; the design's
  unbuilt voxels are drawn as translucent `DESIGN` ghosts. In the top view a cell is
  `CORRECT` when built exactly to the design height, `PARTIAL` when below it, `WRONG` when above
  it (or built off the design).

Frame shape: `render` returns uint8 (H, W, 3) whose shape depends only on the environment's
configuration, `params` and `cell` (never on the state), so the frames of an episode can be
stacked into a video. With `caption=True` a `CAPTION_HEIGHT`-pixel band on top carries the
task, step, bricks used and IoU. `world_layout` tells where each cell lands (tests and the game
use it).
"""

from __future__ import annotations

import dataclasses
import os
from functools import lru_cache
from pathlib import Path
from typing import Sequence

import numpy as np

from snac_jax.atomic import atomic_write
from snac_jax.config import EnvConfig
from snac_jax.observation import LANDMARK_VALUE
from snac_jax.observation import layout as observation_layout
from snac_jax.state import EnvParams, EnvState
from snac_jax.transition import PADDING

# --- colours (RGB) -------------------------------------------------------------------------------
PADDING_COLOUR = (70, 72, 82)  # outside the design area
EMPTY = (246, 246, 242)  # an empty cell that the design leaves empty
DESIGN = (176, 206, 240)  # an empty cell (or level) that the design wants built
CORRECT = (58, 160, 80)  # a brick the design wants (at or below the design height)
PARTIAL = (150, 208, 150)  # 3D top view: built, but below the design height
WRONG = (212, 64, 54)  # a brick off the design or above its height
OVERFLOW = (120, 20, 70)  # 1D/3D: the topmost visible level of a stack cut off by the frame
LANDMARK = (242, 182, 24)  # a landmark cell (seen as -2 in the window)
ROBOT = (24, 40, 150)  # the robot
WINDOW = (255, 128, 0)  # the box around what the robot sees
CURVE = (20, 20, 20)  # 1D design curve
BRICK = (150, 105, 70)  # game view: a brick whose correctness the player cannot know
CAPTION_BG = (32, 34, 40)
CAPTION_FG = (255, 255, 255)

CAPTION_HEIGHT = 20
"""Pixels of one caption line; the caption band is this times the number of lines."""

DEFAULT_CELL = {1: 12, 2: 16, 3: 14}
"""Default pixels per cell side (in 3D: the top view's cells and half an isometric tile)."""

HEADROOM_1D = 8
"""Levels drawn above the tallest design column in 1D (taller stacks are cut, see OVERFLOW)."""

HEADROOM_3D = 4
"""Voxel levels drawn above the tallest design height in 3D."""

_GRID_LINE_SHADE = 0.82  # cell borders are the cell's colour times this
_GHOST_ALPHA = 0.14
_MARGIN = 6


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


# --- public API -----------------------------------------------------------------------------------


def render(env, state: EnvState, params: EnvParams | None = None, *, cell: int | None = None,
           caption: bool | Sequence[str] = True) -> np.ndarray:
    """One world as a uint8 RGB frame (H, W, 3); see the module docstring for the views.

    `env` is a `SNACEnv` (or its `EnvConfig`), `state` one unbatched `EnvState`, `params` the
    `EnvParams` (only its designs are read, to fix the frame's height; defaults to the env's).
    `caption=True` adds a band with task, step, bricks and IoU; a list of strings adds those
    lines instead; `False` adds nothing.
    """
    config = _config_of(env)
    if params is None:
        params = env.default_params
    snapshot = _Snapshot.of(config, state)
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


def world_layout(env, params: EnvParams | None = None, *, cell: int | None = None, caption_lines: int = 1) -> WorldLayout:
    """Where `render` puts the cells (with `caption_lines` caption lines; 0 for `caption=False`)."""
    config = _config_of(env)
    params = params if params is not None else env.default_params
    cell = cell if cell is not None else DEFAULT_CELL[config.dim]
    top = caption_lines * CAPTION_HEIGHT
    if config.dim == 1:
        return WorldLayout(1, cell, top, 0, int(np.max(np.asarray(params.designs))) + HEADROOM_1D)
    if config.dim == 2:
        return WorldLayout(2, cell, top, 0)
    iso_width = _iso_geometry(config, cell, 1)[0]
    return WorldLayout(3, cell, top, iso_width)


def caption_lines(env_or_config, state: EnvState | "_Snapshot", reward: float | None = None) -> list[str]:
    """The default caption: task, step, bricks used of the budget, IoU (and a reward if given)."""
    config = _config_of(env_or_config)
    snap = state if isinstance(state, _Snapshot) else _Snapshot.of(config, state)
    text = f"{config.task_id}  step {snap.time}  bricks {snap.bricks_used}/{snap.max_bricks}  IoU {snap.iou:.3f}"
    if reward is not None:
        text += f"  reward {reward:+g}"
    return [text]


def add_caption(frame: np.ndarray, lines: Sequence[str]) -> np.ndarray:
    """`frame` with a band of text lines on top (CAPTION_HEIGHT pixels per line)."""
    band = np.empty((CAPTION_HEIGHT * len(lines), frame.shape[1], 3), np.uint8)
    band[:] = CAPTION_BG
    band = draw_text(band, [(4, 3 + i * CAPTION_HEIGHT, line, CAPTION_FG) for i, line in enumerate(lines)])
    return np.concatenate([band, frame], axis=0)


def draw_text(image: np.ndarray, items: Sequence[tuple[int, int, str, tuple[int, int, int]]], size: int = 13) -> np.ndarray:
    """A copy of `image` with each (x, y, text, colour) written at pixel (x, y) (top-left)."""
    from PIL import Image, ImageDraw

    pil = Image.fromarray(np.ascontiguousarray(image))
    draw = ImageDraw.Draw(pil)
    font = _font(size)
    for x, y, text, colour in items:
        draw.text((x, y), text, fill=tuple(colour), font=font)
    return np.asarray(pil, dtype=np.uint8).copy()


def save_png(path: str | os.PathLike, frame: np.ndarray) -> Path:
    """Write `frame` as a PNG atomically (temporary file, then rename)."""
    from PIL import Image

    _check_frame(frame)
    return atomic_write(path, lambda f: Image.fromarray(frame).save(f, format="PNG"))


def save_gif(path: str | os.PathLike, frames: Sequence[np.ndarray], fps: float = 10.0,
             durations_ms: Sequence[float] | None = None) -> Path:
    """Write equally shaped frames as a looping GIF atomically (temporary file, then rename).

    Each frame lasts 1/fps seconds, or `durations_ms[i]` milliseconds when given. The GIF
    encoder (Pillow) merges consecutive identical frames into one, adding their durations;
    frames with a step counter in their caption always differ.
    """
    import imageio.v3 as iio

    if not frames:
        raise ValueError("save_gif needs at least one frame")
    for frame in frames:
        _check_frame(frame)
    if len({f.shape for f in frames}) != 1:
        raise ValueError(f"all frames must have one shape, got {sorted({f.shape for f in frames})}")
    if durations_ms is None:
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        durations_ms = [1000.0 / fps] * len(frames)
    if len(durations_ms) != len(frames) or min(durations_ms) <= 0:
        raise ValueError("durations_ms must hold one positive duration per frame")
    stack = np.stack(frames)
    durations = [float(d) for d in durations_ms]
    return atomic_write(path, lambda f: iio.imwrite(f, stack, extension=".gif", duration=durations, loop=0))


def render_observation(env, obs, *, cell: int = 44, design_cell: int | None = None,
                       labels: dict[tuple[int, int], str] | None = None) -> np.ndarray:
    """What the agent sees, drawn from its observation vector only (the human game's view).

    The window is drawn large (cell `cell`) with the robot at its centre: padding `PADDING`,
    empty `EMPTY`, bricks `BRICK` (the player cannot know whether a brick is right, so there is
    no correct/wrong colouring), landmarks `LANDMARK`; 1D windows are columns of that many
    bricks, 3D cells carry their height as a number. Dynamic tasks add the design from the
    observation beside it. Counters are left to the caller (they are part of the game's text).
    `labels` maps window offsets (d_row, d_col) from the robot to a short text drawn in that
    cell's corner (the game labels the drop keys).
    """
    config = _config_of(env)
    obs = np.asarray(obs, dtype=np.float32)
    layout = observation_layout(config)
    if obs.shape != (layout.size,):
        raise ValueError(f"expected one observation of shape ({layout.size},), got {obs.shape}")
    wr, wc = config.window_shape
    window = layout.window_cells(obs)
    if config.dim == 1:
        view = _observation_columns(window[0], cell)
    else:
        view = _observation_cells(window, cell, numbers=config.dim == 3)
    if labels:
        centre = (wr // 2, wc // 2)
        items = [((centre[1] + dc) * cell + cell - 14, (centre[0] + dr) * cell + cell - 18, text, WINDOW)
                 for (dr, dc), text in labels.items()]
        view = draw_text(view, items, size=14)
    if not config.dynamic:
        return view
    design = layout.design_cells(obs)
    design_view = _design_thumbnail(config, design, design_cell)
    return _hstack([view, design_view], gap=16)


# --- state snapshot -----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Snapshot:
    """One state's arrays in numpy (a device-to-host copy once per frame)."""

    grid: np.ndarray
    position: tuple[int, int]
    design: np.ndarray
    landmarks: np.ndarray | None
    time: int
    bricks_used: int
    max_bricks: int
    iou: float

    @classmethod
    def of(cls, config: EnvConfig, state: EnvState) -> "_Snapshot":
        grid = np.asarray(state.grid)
        if grid.shape != config.grid_shape:
            raise ValueError(
                f"render takes one world: grid shape {config.grid_shape}, got {grid.shape} "
                "(select one from a batch with jax.tree.map(lambda x: x[i], states))"
            )
        position = np.asarray(state.position)
        landmarks = None if state.landmarks is None else np.asarray(state.landmarks)
        union = int(state.union)
        return cls(
            grid=grid.astype(np.int32),
            position=(int(position[0]), int(position[1])),
            design=np.asarray(state.design).astype(np.int32),
            landmarks=landmarks,
            time=int(state.time),
            bricks_used=int(state.bricks_used),
            max_bricks=int(state.max_bricks),
            iou=int(state.overlap) / max(union, 1),
        )

    def padded_design(self, config: EnvConfig) -> np.ndarray:
        (pr, pc) = config.pad
        return np.pad(self.design, ((pr, pr), (pc, pc)))


# --- 1D -----------------------------------------------------------------------------------------------


def _render_1d(config: EnvConfig, snap: _Snapshot, cell: int, levels: int) -> np.ndarray:
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
    image = _upscale(colours, cell)

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
    _disc(image, levels * cell + cell // 2, robot_col * cell + cell // 2, cell * 0.4, ROBOT)
    x0 = snap.position[1] * cell  # the window's first column is the robot's plan column (padded)
    _box(image, 0, x0, image.shape[0], x0 + config.window_shape[1] * cell, max(2, cell // 6), WINDOW)
    return image


# --- 2D and the 3D top view ------------------------------------------------------------------------


def _render_top(config: EnvConfig, snap: _Snapshot, cell: int) -> np.ndarray:
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
    image = _upscale(colours, cell)

    pr, pc = config.pad
    row, col = snap.position[0] + pr, snap.position[1] + pc
    _disc(image, row * cell + cell // 2, col * cell + cell // 2, cell * 0.36, ROBOT)
    wr, wc = config.window_shape
    y0, x0 = snap.position[0] * cell, snap.position[1] * cell  # window top-left = plan position, padded
    _box(image, y0, x0, y0 + wr * cell, x0 + wc * cell, max(2, cell // 7), WINDOW)
    return image


# --- 3D -----------------------------------------------------------------------------------------------


def _render_3d(config: EnvConfig, snap: _Snapshot, cell: int, levels: int) -> np.ndarray:
    iso = _render_isometric(config, snap, cell, levels)
    top = _render_top(config, snap, cell)
    height = max(iso.shape[0], top.shape[0])
    return np.concatenate([_pad_to_height(iso, height), _pad_to_height(top, height)], axis=1)


def _iso_geometry(config: EnvConfig, cell: int, levels: int) -> tuple[int, int, int, int, int]:
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


def _render_isometric(config: EnvConfig, snap: _Snapshot, cell: int, levels: int) -> np.ndarray:
    """Painter's algorithm: back (row + col small) to front, bottom to top."""
    width, height, a, b, cube = _iso_geometry(config, cell, levels)
    rows, cols = config.plan_shape
    pr, pc = config.pad
    canvas = np.empty((height, width, 3), np.uint8)
    canvas[:] = (235, 236, 240)
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
    _disc(canvas, robot_centre[0], robot_centre[1], a * 0.55, ROBOT)
    return canvas


# --- the game's observation view ------------------------------------------------------------------


def _observation_cells(window: np.ndarray, cell: int, numbers: bool) -> np.ndarray:
    colours = np.empty(window.shape + (3,), np.uint8)
    colours[:] = EMPTY
    colours[window > 0] = BRICK
    colours[window == LANDMARK_VALUE] = LANDMARK
    colours[window == PADDING] = PADDING_COLOUR
    image = _upscale(colours, cell)
    centre = (window.shape[0] // 2, window.shape[1] // 2)
    _disc(image, centre[0] * cell + cell // 2, centre[1] * cell + cell // 2, cell * 0.3, ROBOT)
    _box(image, centre[0] * cell, centre[1] * cell, (centre[0] + 1) * cell, (centre[1] + 1) * cell, 2, WINDOW)
    if numbers:
        items = []
        for (r, c), value in np.ndenumerate(window):
            if value > 0:
                items.append((c * cell + 3, r * cell + 2, str(int(value)), CAPTION_FG))
        image = draw_text(image, items, size=max(10, cell // 3))
    return image


def _observation_columns(heights: np.ndarray, cell: int) -> np.ndarray:
    """1D window: one column per cell, bricks stacked `brick` pixels each, count on top."""
    brick = max(3, cell // 8)
    levels = 40
    image = np.empty((levels * brick + cell, heights.size * cell, 3), np.uint8)
    image[:] = EMPTY
    items = []
    for i, h in enumerate(heights):
        x0, x1 = i * cell, (i + 1) * cell
        if h == PADDING:
            image[:, x0:x1] = PADDING_COLOUR
            continue
        shown = int(min(h, levels))
        if shown:
            image[levels * brick - shown * brick : levels * brick, x0 + 2 : x1 - 2] = BRICK
            image[levels * brick - shown * brick : levels * brick : brick, x0 + 2 : x1 - 2] = (90, 60, 40)
        items.append((x0 + 4, max(levels * brick - shown * brick - 16, 0), str(int(h)), (0, 0, 0)))
    image[levels * brick :] = PADDING_COLOUR
    centre = heights.size // 2
    _disc(image, levels * brick + cell // 2, centre * cell + cell // 2, cell * 0.3, ROBOT)
    return draw_text(image, items)


def _design_thumbnail(config: EnvConfig, design: np.ndarray, cell: int | None) -> np.ndarray:
    if config.dim == 1:
        cell = cell or 8
        heights = design[0].astype(int)
        levels = int(heights.max()) + 2
        colours = np.empty((levels, heights.size, 3), np.uint8)
        colours[:] = EMPTY
        colours[np.arange(levels)[::-1, None] < heights] = DESIGN
        return _upscale(colours, cell)
    cell = cell or 12
    colours = np.empty(design.shape + (3,), np.uint8)
    colours[:] = EMPTY
    if config.dim == 2:
        colours[design > 0] = DESIGN
    else:  # deeper blue for taller design columns
        tallest = max(int(design.max()), 1)
        shade = (design / tallest)[..., None]
        colours[:] = np.where(design[..., None] > 0, (1.15 - 0.4 * shade) * np.asarray(DESIGN), colours).clip(0, 255).astype(np.uint8)
    return _upscale(colours, cell)


# --- helpers -----------------------------------------------------------------------------------------


def _config_of(env) -> EnvConfig:
    if isinstance(env, EnvConfig):
        return env
    config = getattr(env, "config", None)
    if not isinstance(config, EnvConfig):
        raise ValueError(f"expected a SNACEnv or an EnvConfig, got {type(env).__name__}")
    return config


def _check_cell(cell: int) -> int:
    if not isinstance(cell, (int, np.integer)) or isinstance(cell, bool) or cell < 4:
        raise ValueError(f"cell must be an int >= 4 (pixels per cell), got {cell!r}")
    return int(cell)


def _check_frame(frame: np.ndarray) -> None:
    if not (isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3):
        raise ValueError("a frame must be a uint8 numpy array of shape (H, W, 3)")


def _upscale(colours: np.ndarray, cell: int) -> np.ndarray:
    """Each cell becomes a cell x cell block; its first pixel row and column are a darker border."""
    image = np.repeat(np.repeat(colours, cell, axis=0), cell, axis=1)
    image[::cell] = (image[::cell] * _GRID_LINE_SHADE).astype(np.uint8)
    image[:, ::cell] = (image[:, ::cell] * _GRID_LINE_SHADE).astype(np.uint8)
    return image


def _disc(image: np.ndarray, cy: int, cx: int, radius: float, colour) -> None:
    r = int(np.ceil(radius))
    y0, y1 = max(cy - r, 0), min(cy + r + 1, image.shape[0])
    x0, x1 = max(cx - r, 0), min(cx + r + 1, image.shape[1])
    y, x = np.mgrid[y0:y1, x0:x1]
    mask = (y - cy) ** 2 + (x - cx) ** 2 <= radius**2
    image[y0:y1, x0:x1][mask] = colour


def _box(image: np.ndarray, y0: int, x0: int, y1: int, x1: int, thickness: int, colour) -> None:
    """An outline drawn inside the box [y0, y1) x [x0, x1), clipped to the image."""
    h, w = image.shape[:2]
    y0, x0, y1, x1 = max(y0, 0), max(x0, 0), min(y1, h), min(x1, w)
    image[y0 : y0 + thickness, x0:x1] = colour
    image[max(y1 - thickness, y0) : y1, x0:x1] = colour
    image[y0:y1, x0 : x0 + thickness] = colour
    image[y0:y1, max(x1 - thickness, x0) : x1] = colour


def _pad_to_height(image: np.ndarray, height: int) -> np.ndarray:
    extra = height - image.shape[0]
    if extra <= 0:
        return image
    fill = np.empty((extra, image.shape[1], 3), np.uint8)
    fill[:] = (235, 236, 240)
    return np.concatenate([image, fill], axis=0)


def _hstack(images: Sequence[np.ndarray], gap: int) -> np.ndarray:
    height = max(i.shape[0] for i in images)
    parts = []
    for i, image in enumerate(images):
        if i:
            spacer = np.empty((height, gap, 3), np.uint8)
            spacer[:] = CAPTION_BG
            parts.append(spacer)
        padded = np.empty((height, image.shape[1], 3), np.uint8)
        padded[:] = CAPTION_BG
        padded[: image.shape[0]] = image
        parts.append(padded)
    return np.concatenate(parts, axis=1)


@lru_cache(maxsize=8)
def _font(size: int):
    from PIL import ImageFont

    return ImageFont.load_default(size=size)
