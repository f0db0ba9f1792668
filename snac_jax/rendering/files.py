"""Frames to files: PNG and looping GIF, written atomically.

A picture is written to a temporary file and renamed, so a reader (a browser, a notebook, a
second process) never sees half a file, and an interrupted run leaves the previous one intact.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from snac_jax.atomic import atomic_write


def save_png(path: str | os.PathLike, frame: np.ndarray) -> Path:
    """Write `frame` as a PNG atomically (temporary file, then rename)."""
    from PIL import Image

    _check_frame(frame)
    return atomic_write(path, lambda f: Image.fromarray(frame).save(f, format="PNG"))


def save_gif(
    path: str | os.PathLike,
    frames: Sequence[np.ndarray],
    fps: float = 10.0,
    durations_ms: Sequence[float] | None = None,
) -> Path:
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


def _check_frame(frame: np.ndarray) -> None:
    if not (isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3):
        raise ValueError("a frame must be a uint8 numpy array of shape (H, W, 3)")
