"""Static configuration of one SNAC environment: everything that decides shapes or code paths.

Numbers that only change values (the stride distribution, the step limit, the designs) live in
`EnvParams` instead, so they can be swapped or vmapped without recompiling. An `EnvConfig` is
frozen and hashable: two environments with equal configurations share compiled code.

1D is handled as a grid with a single row and no row padding, so one transition serves 1D, 2D
and 3D (SPEC §2-6); the dimension only selects the action table, the drop target, the grid
dtype and the default reward scheme.
"""

from __future__ import annotations

import dataclasses

import numpy as np

# The four directions (d_row, d_col) on the plan; rows grow downward, as drawn on screen.
LEFT, RIGHT, DOWN, UP = (0, -1), (0, 1), (1, 0), (-1, 0)
MOVE_DIRECTIONS = (LEFT, RIGHT, DOWN, UP)
"""The order of the moves in every action table (actions 0..3; 0..1 in 1D) and of the four
neighbour drops (actions 4..7). The transition, the handcrafted policy and the human game's
keys all read directions from here."""

# Action tables (SPEC §3): (is_drop, d_row, d_col) for each action index.
# Moves are scaled by the stride; drops hit pos + (d_row, d_col) without stride.
_MOVES = tuple((0, d_row, d_col) for d_row, d_col in MOVE_DIRECTIONS)
ACTIONS_1D = _MOVES[:2] + ((1, 0, 0),)
ACTIONS_2D = _MOVES + ((1, 0, 0),)
ACTIONS_NEIGHBOUR_DROP = _MOVES + tuple((1, d_row, d_col) for d_row, d_col in MOVE_DIRECTIONS)

REWARD_SCHEMES = ("height", "binary")
"""`height`: the code's -1 (over) / +10 (exact) / +1 (below) for a brick at height h on design D.
`binary`: the paper text's +5 when the brick belongs to the design (h <= D), else 0. On the
binary 2D grid this is exactly the reference's 2D reward (+5 for the first brick on a design
cell)."""

PLAN_SIZE_1D = 30
PLAN_SIZE_2D = 20
MAX_STRIDE = 3


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """What the compiled step depends on. Built by `snac_jax.make`; not meant to be edited."""

    task_id: str
    dim: int  # 1, 2 or 3
    dynamic: bool  # the design changes per episode and is part of the observation
    half_window: int  # `ws` in SPEC
    obstacles: bool  # 3D obstacle rule (SPEC §4); default on in 3D only
    binary_grid: bool  # 2D: a cell holds at most one brick
    reward_scheme: str  # one of REWARD_SCHEMES
    gps: bool  # append the true plan position to the observation
    num_landmarks: int  # 0 = no landmarks
    landmark_action: int = 0  # K landmarks the placement action may place per episode; 0 = no such action (SPEC §14)
    design_change: tuple[int, int] | None = None  # (a, b): the design changes at a step in a..b (SPEC §15)

    @property
    def plan_shape(self) -> tuple[int, int]:
        if self.dim == 1:
            return (1, PLAN_SIZE_1D)
        return (PLAN_SIZE_2D, PLAN_SIZE_2D)

    @property
    def pad(self) -> tuple[int, int]:
        """Padding (rows, cols) of the world around the design area."""
        return (0 if self.dim == 1 else self.half_window, self.half_window)

    @property
    def grid_shape(self) -> tuple[int, int]:
        (h, w), (pr, pc) = self.plan_shape, self.pad
        return (h + 2 * pr, w + 2 * pc)

    @property
    def window_shape(self) -> tuple[int, int]:
        pr, pc = self.pad
        return (2 * pr + 1, 2 * pc + 1)

    @property
    def actions(self) -> tuple[tuple[int, int, int], ...]:
        if self.dim == 1:
            return ACTIONS_1D
        if self.dim == 3 or self.obstacles:
            return ACTIONS_NEIGHBOUR_DROP
        return ACTIONS_2D

    @property
    def num_actions(self) -> int:
        """The moves and drops of `actions`, then the landmark placement when it is switched on.

        `actions` stays the table of moves and drops only, so everything that reads directions
        from it (the handcrafted policy, the human game's keys) is unchanged by the switch."""
        return len(self.actions) + (1 if self.landmark_action else 0)

    @property
    def place_landmark_action(self) -> int | None:
        """The index of the landmark placement (SPEC §14): right after the table's actions."""
        return len(self.actions) if self.landmark_action else None

    @property
    def grid_dtype(self) -> np.dtype:
        # 2D cells are 0/1; 1D and 3D count bricks (a whole budget of <= 888 fits in int16).
        return np.dtype(np.int8) if self.binary_grid else np.dtype(np.int16)

    @property
    def design_size(self) -> int:
        h, w = self.plan_shape
        return h * w
