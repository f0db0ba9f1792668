"""What every view paints with: the palette, pixel primitives on uint8 (H, W, 3) arrays, text.

The views (`world`, `isometric`, `agent_view`) compose frames from these in numpy; nothing here
is traced. Text is drawn with Pillow (imageio already depends on it), so matplotlib is never
needed to make a picture.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np

from snac_jax.config import EnvConfig

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
BACKGROUND = (235, 236, 240)  # behind the isometric view and below the shorter of two panels

CAPTION_HEIGHT = 20
"""Pixels of one caption line; the caption band is this times the number of lines."""

_GRID_LINE_SHADE = 0.82  # cell borders are the cell's colour times this


def config_of(env) -> EnvConfig:
    """The `EnvConfig` of a `SNACEnv`, or the config itself: every view accepts either."""
    if isinstance(env, EnvConfig):
        return env
    config = getattr(env, "config", None)
    if not isinstance(config, EnvConfig):
        raise ValueError(f"expected a SNACEnv or an EnvConfig, got {type(env).__name__}")
    return config


# --- text ----------------------------------------------------------------------------------------


def add_caption(frame: np.ndarray, lines: Sequence[str]) -> np.ndarray:
    """`frame` with a band of text lines on top (CAPTION_HEIGHT pixels per line)."""
    band = np.empty((CAPTION_HEIGHT * len(lines), frame.shape[1], 3), np.uint8)
    band[:] = CAPTION_BG
    band = draw_text(band, [(4, 3 + i * CAPTION_HEIGHT, line, CAPTION_FG) for i, line in enumerate(lines)])
    return np.concatenate([band, frame], axis=0)


def draw_text(
    image: np.ndarray, items: Sequence[tuple[int, int, str, tuple[int, int, int]]], size: int = 13
) -> np.ndarray:
    """A copy of `image` with each (x, y, text, colour) written at pixel (x, y) (top-left)."""
    from PIL import Image, ImageDraw

    pil = Image.fromarray(np.ascontiguousarray(image))
    draw = ImageDraw.Draw(pil)
    font = _font(size)
    for x, y, text, colour in items:
        draw.text((x, y), text, fill=tuple(colour), font=font)
    return np.asarray(pil, dtype=np.uint8).copy()


@lru_cache(maxsize=8)
def _font(size: int):
    from PIL import ImageFont

    return ImageFont.load_default(size=size)


# --- pixels --------------------------------------------------------------------------------------


def upscale(colours: np.ndarray, cell: int) -> np.ndarray:
    """Each cell becomes a cell x cell block; its first pixel row and column are a darker border."""
    image = np.repeat(np.repeat(colours, cell, axis=0), cell, axis=1)
    image[::cell] = (image[::cell] * _GRID_LINE_SHADE).astype(np.uint8)
    image[:, ::cell] = (image[:, ::cell] * _GRID_LINE_SHADE).astype(np.uint8)
    return image


def disc(image: np.ndarray, cy: int, cx: int, radius: float, colour) -> None:
    """A filled disc centred on pixel (cy, cx), clipped to the image (in place)."""
    r = int(np.ceil(radius))
    y0, y1 = max(cy - r, 0), min(cy + r + 1, image.shape[0])
    x0, x1 = max(cx - r, 0), min(cx + r + 1, image.shape[1])
    y, x = np.mgrid[y0:y1, x0:x1]
    mask = (y - cy) ** 2 + (x - cx) ** 2 <= radius**2
    image[y0:y1, x0:x1][mask] = colour


def box(image: np.ndarray, y0: int, x0: int, y1: int, x1: int, thickness: int, colour) -> None:
    """An outline drawn inside the box [y0, y1) x [x0, x1), clipped to the image (in place)."""
    h, w = image.shape[:2]
    y0, x0, y1, x1 = max(y0, 0), max(x0, 0), min(y1, h), min(x1, w)
    image[y0 : y0 + thickness, x0:x1] = colour
    image[max(y1 - thickness, y0) : y1, x0:x1] = colour
    image[y0:y1, x0 : x0 + thickness] = colour
    image[y0:y1, max(x1 - thickness, x0) : x1] = colour


def pad_to_height(image: np.ndarray, height: int) -> np.ndarray:
    """`image` extended downward with `BACKGROUND` to `height` pixel rows."""
    extra = height - image.shape[0]
    if extra <= 0:
        return image
    fill = np.empty((extra, image.shape[1], 3), np.uint8)
    fill[:] = BACKGROUND
    return np.concatenate([image, fill], axis=0)


def hstack(images: Sequence[np.ndarray], gap: int) -> np.ndarray:
    """Images side by side, top-aligned, on `CAPTION_BG`, `gap` pixels apart."""
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
