"""Pictures of SNAC worlds: RGB frames composed with numpy, outside the jitted step.

Nothing here is traced: every function takes one concrete (unbatched) state or observation,
converts it to numpy and paints cells as blocks of pixels. Text (the caption and the game's
counters) is drawn with Pillow, which imageio already depends on; matplotlib is not needed,
even for the 3D voxel view, which is an isometric painter's-algorithm projection in numpy.

Modules: `draw` (the palette, pixel primitives, text), `snapshot` (a state copied to numpy),
`world` (`render`: the state's views), `isometric` (the 3D voxel view), `agent_view`
(`render_observation`: what the agent sees), `files` (PNG and GIF), `robots` (`render_robots`:
a world of several robots, SPEC §13, each robot in its `ROBOT_COLOURS` colour). Everything a
caller needs is importable from `snac_jax.rendering` itself.

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

from snac_jax.rendering.agent_view import render_observation
from snac_jax.rendering.draw import (
    BACKGROUND,
    BRICK,
    CAPTION_BG,
    CAPTION_FG,
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
    draw_text,
)
from snac_jax.rendering.files import save_gif, save_png
from snac_jax.rendering.robots import ROBOT_COLOURS, render_robots
from snac_jax.rendering.world import (
    DEFAULT_CELL,
    HEADROOM_1D,
    HEADROOM_3D,
    WorldLayout,
    caption_lines,
    render,
    world_layout,
)

__all__ = [
    "BACKGROUND",
    "BRICK",
    "CAPTION_BG",
    "CAPTION_FG",
    "CAPTION_HEIGHT",
    "CORRECT",
    "CURVE",
    "DEFAULT_CELL",
    "DESIGN",
    "EMPTY",
    "HEADROOM_1D",
    "HEADROOM_3D",
    "LANDMARK",
    "OVERFLOW",
    "PADDING_COLOUR",
    "PARTIAL",
    "ROBOT",
    "ROBOT_COLOURS",
    "WINDOW",
    "WRONG",
    "WorldLayout",
    "add_caption",
    "caption_lines",
    "draw_text",
    "render",
    "render_observation",
    "render_robots",
    "save_gif",
    "save_png",
    "world_layout",
]
