"""What the agent sees, drawn from its observation vector alone: the human game's screen.

The human baseline must get exactly the agent's information, so this view never reads the
state: it slices the observation through `snac_jax.observation.layout`. For the same reason
bricks are one `BRICK` colour (the player cannot know whether a brick is right).
"""

from __future__ import annotations

import numpy as np

from snac_jax.config import EnvConfig
from snac_jax.observation import LANDMARK_VALUE
from snac_jax.observation import layout as observation_layout
from snac_jax.rendering.draw import (
    BRICK,
    CAPTION_FG,
    DESIGN,
    EMPTY,
    LANDMARK,
    PADDING_COLOUR,
    ROBOT,
    WINDOW,
    box,
    config_of,
    disc,
    draw_text,
    hstack,
    upscale,
)
from snac_jax.transition import PADDING


def render_observation(
    env, obs, *, cell: int = 44, design_cell: int | None = None, labels: dict[tuple[int, int], str] | None = None
) -> np.ndarray:
    """What the agent sees, drawn from its observation vector only (the human game's view).

    The window is drawn large (cell `cell`) with the robot at its centre: padding `PADDING`,
    empty `EMPTY`, bricks `BRICK` (the player cannot know whether a brick is right, so there is
    no correct/wrong colouring), landmarks `LANDMARK`; 1D windows are columns of that many
    bricks, 3D cells carry their height as a number. Dynamic tasks add the design from the
    observation beside it. Counters are left to the caller (they are part of the game's text).
    `labels` maps window offsets (d_row, d_col) from the robot to a short text drawn in that
    cell's corner (the game labels the drop keys).
    """
    config = config_of(env)
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
        items = [
            ((centre[1] + dc) * cell + cell - 14, (centre[0] + dr) * cell + cell - 18, text, WINDOW)
            for (dr, dc), text in labels.items()
        ]
        view = draw_text(view, items, size=14)
    if not config.dynamic:
        return view
    design = layout.design_cells(obs)
    design_view = _design_thumbnail(config, design, design_cell)
    return hstack([view, design_view], gap=16)


def _observation_cells(window: np.ndarray, cell: int, numbers: bool) -> np.ndarray:
    colours = np.empty(window.shape + (3,), np.uint8)
    colours[:] = EMPTY
    colours[window > 0] = BRICK
    colours[window == LANDMARK_VALUE] = LANDMARK
    colours[window == PADDING] = PADDING_COLOUR
    image = upscale(colours, cell)
    centre = (window.shape[0] // 2, window.shape[1] // 2)
    disc(image, centre[0] * cell + cell // 2, centre[1] * cell + cell // 2, cell * 0.3, ROBOT)
    box(image, centre[0] * cell, centre[1] * cell, (centre[0] + 1) * cell, (centre[1] + 1) * cell, 2, WINDOW)
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
    disc(image, levels * brick + cell // 2, centre * cell + cell // 2, cell * 0.3, ROBOT)
    return draw_text(image, items)


def _design_thumbnail(config: EnvConfig, design: np.ndarray, cell: int | None) -> np.ndarray:
    if config.dim == 1:
        cell = cell or 8
        heights = design[0].astype(int)
        levels = int(heights.max()) + 2
        colours = np.empty((levels, heights.size, 3), np.uint8)
        colours[:] = EMPTY
        colours[np.arange(levels)[::-1, None] < heights] = DESIGN
        return upscale(colours, cell)
    cell = cell or 12
    colours = np.empty(design.shape + (3,), np.uint8)
    colours[:] = EMPTY
    if config.dim == 2:
        colours[design > 0] = DESIGN
    else:  # deeper blue for taller design columns
        tallest = max(int(design.max()), 1)
        shade = (design / tallest)[..., None]
        colours[:] = (
            np.where(design[..., None] > 0, (1.15 - 0.4 * shade) * np.asarray(DESIGN), colours)
            .clip(0, 255)
            .astype(np.uint8)
        )
    return upscale(colours, cell)
