"""One state's arrays copied to numpy, the input of every world view.

The views read the state cell by cell in Python; copying it from the device once per frame
keeps that from becoming one device-to-host transfer per read.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from snac_jax.config import EnvConfig
from snac_jax.state import EnvState


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """One (unbatched) `EnvState` in numpy, with its IoU computed."""

    grid: np.ndarray
    position: tuple[int, int]
    design: np.ndarray
    landmarks: np.ndarray | None
    time: int
    bricks_used: int
    max_bricks: int
    iou: float
    change_step: int | None = None  # SPEC §15, with design_change only
    landmarks_left: int | None = None  # SPEC §14, with landmark_action only

    @classmethod
    def of(cls, config: EnvConfig, state: EnvState) -> Snapshot:
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
            change_step=None if state.change_step is None else int(state.change_step),
            landmarks_left=None if state.landmarks_left is None else int(state.landmarks_left),
        )

    def padded_design(self, config: EnvConfig) -> np.ndarray:
        (pr, pc) = config.pad
        return np.pad(self.design, ((pr, pr), (pc, pc)))
