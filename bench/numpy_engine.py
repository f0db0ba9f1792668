"""A plain NumPy/Python SNAC engine: one world, stepped one action at a time.

This is the baseline a user would otherwise have (the reference implementation is written
this way: a NumPy grid per world and a Python loop over steps), and an independent oracle for
the JAX environment. It is written from SPEC.md alone and shares no step logic with
`snac_jax.transition`: only the fixed designs (data, `designs.json`) and the task ids are
imported. Tests check it against the golden traces and against `SNACEnv`, step for step.

It lives in `bench/`, not in the `snac_jax` package, because the library never runs it: it is
the throughput benchmark's baseline (`bench/throughput.py`) and the tests' second opinion
(`from bench.numpy_engine import NumpyEnv`, with the repository root on the path).

    env = NumpyEnv("2d-static-dense", seed=0)
    obs = env.reset()
    obs, reward, terminated, truncated, info = env.step(action)        # draws the stride
    obs, reward, terminated, truncated, info = env.step(action, stride=2)

Differences in representation from the JAX environment, on purpose: the 1D grid is a flat
vector and the 1D position a single column; the IoU is recomputed from the cells.
"""

from __future__ import annotations

import numpy as np

from snac_jax.designs import reference_designs
from snac_jax.tasks import TASKS

PLAN_1D = 30
PLAN_2D = 20
PADDING = -1
LANDMARK = -2
HEIGHT_3D = 6
TEST_DESIGNS = 10

# SPEC §1: dimension, step limit.
MAX_STEPS = {1: 750, 2: 600, 3: 1300}
MAX_STEPS_3D_DYNAMIC = 1000

# SPEC §3: the move directions (d_row, d_col) of actions 0..3 in 2D/3D, and of 0..1 in 1D.
# Written out again rather than imported from `snac_jax.config`: an oracle that read the
# library's table would agree with it even where the table is wrong.
MOVES = ((0, -1), (0, 1), (1, 0), (-1, 0))

# SPEC §7: the triangle cell-count rules, low < count (< high).
TRIANGLE_COUNTS = {
    (2, "dense"): (50, None),
    (2, "sparse"): (20, None),
    (3, "dense"): (50, 110),
    (3, "sparse"): (20, 110),
}


# --- designs (SPEC §7) -----------------------------------------------------------------------


def random_sine(rng: np.random.Generator) -> np.ndarray:
    """round(k1·sin(2π/30·(k2·x + φ)) + 20), k1 ~ U(3, 12), k2 ∈ {1, 2, 3}, φ ~ U(−π, π)."""
    k1 = rng.uniform(3, 12)
    k2 = rng.integers(1, 4)
    phi = rng.uniform(-np.pi, np.pi)
    x = np.arange(PLAN_1D)
    return np.round(k1 * np.sin(2 * np.pi / PLAN_1D * (k2 * x + phi)) + 20).astype(np.int64)


def line_cells(a: tuple[int, int], b: tuple[int, int]) -> list[tuple[int, int]]:
    """Cells of the 8-connected digital line from a to b (Bresenham)."""
    (r0, c0), (r1, c1) = a, b
    dr, dc = abs(r1 - r0), abs(c1 - c0)
    sr, sc = (1 if r1 > r0 else -1), (1 if c1 > c0 else -1)
    err = dc - dr
    cells = [(r0, c0)]
    while (r0, c0) != (r1, c1):
        e2 = 2 * err
        if e2 > -dr:
            err -= dr
            c0 += sc
        if e2 < dc:
            err += dc
            r0 += sr
        cells.append((r0, c0))
    return cells


def triangle(vertices, filled: bool) -> np.ndarray:
    """A 0/1 (20, 20) raster of a triangle: its outline, plus every cell whose centre lies
    inside when `filled`."""
    cells = np.zeros((PLAN_2D, PLAN_2D), dtype=np.int64)
    for i in range(3):
        for r, c in line_cells(vertices[i], vertices[(i + 1) % 3]):
            cells[r, c] = 1
    if filled:
        rows, cols = np.mgrid[0:PLAN_2D, 0:PLAN_2D]
        sides = []
        for i in range(3):
            (r0, c0), (r1, c1) = vertices[i], vertices[(i + 1) % 3]
            sides.append((r1 - r0) * (cols - c0) - (c1 - c0) * (rows - r0))
        sides = np.stack(sides)
        cells |= (np.all(sides >= 0, axis=0) | np.all(sides <= 0, axis=0)).astype(np.int64)
    return cells


def random_triangle(rng: np.random.Generator, dim: int, density: str) -> np.ndarray:
    """A triangle with uniform vertices, redrawn until its cell count is in range (×6 in 3D)."""
    low, high = TRIANGLE_COUNTS[(dim, density)]
    while True:
        vertices = [tuple(int(v) for v in rng.integers(0, PLAN_2D, 2)) for _ in range(3)]
        cells = triangle(vertices, filled=density == "dense")
        count = int(cells.sum())
        if count > low and (high is None or count < high):
            return cells * (HEIGHT_3D if dim == 3 else 1)


# --- the engine ------------------------------------------------------------------------------


class NumpyEnv:
    """One SNAC world. `task` is a task id of `snac_jax.TASKS`.

    Switches as in SPEC §9: `stride_probs`, `gps`, `obstacles` (2D/3D), `landmarks` (count),
    `reward_scheme` ("height" or "binary"), `max_steps`; `test_design` (0..9) pins a dynamic
    task to one of its test designs. `reset(design=..., landmarks=...)` can also impose the
    design and landmark cells of one episode (the tests use it to follow the JAX env).
    """

    def __init__(
        self,
        task: str,
        *,
        seed: int = 0,
        stride_probs=(1 / 3, 1 / 3, 1 / 3),
        gps: bool = False,
        obstacles: bool | None = None,
        landmarks: int = 0,
        reward_scheme: str | None = None,
        max_steps: int | None = None,
        test_design: int | None = None,
    ):
        if task not in TASKS:
            raise ValueError(f"unknown task {task!r}; allowed: {', '.join(TASKS)}")
        self.task = task
        self.dim = int(task[0])
        self.dynamic = "dynamic" in task
        self.density = task.rsplit("-", 1)[1] if self.dim > 1 else None
        self.ws = 2 if self.dim == 1 else 3
        self.obstacles = (self.dim == 3) if obstacles is None else bool(obstacles)
        if self.dim == 1 and (self.obstacles or landmarks):
            raise ValueError("obstacles and landmarks need a 2D or 3D task")
        self.reward_scheme = reward_scheme or ("binary" if self.dim == 2 else "height")
        if self.reward_scheme not in ("height", "binary"):
            raise ValueError(f"reward_scheme must be 'height' or 'binary', got {self.reward_scheme!r}")
        default_steps = MAX_STEPS_3D_DYNAMIC if (self.dim == 3 and self.dynamic) else MAX_STEPS[self.dim]
        self.max_steps = default_steps if max_steps is None else int(max_steps)
        cumulative = np.cumsum(np.asarray(stride_probs, dtype=np.float32))  # as the JAX env compares
        self.stride_thresholds = (float(cumulative[0]), float(cumulative[1]))
        self.gps = bool(gps)
        self.num_landmarks = int(landmarks)
        self.rng = np.random.default_rng(seed)
        self.fixed_design = None
        if not self.dynamic:
            self.fixed_design = self._reference(task)
        elif test_design is not None:
            if not 0 <= test_design < TEST_DESIGNS:
                raise ValueError(f"test_design must be in 0..{TEST_DESIGNS - 1}, got {test_design!r}")
            self.fixed_design = self._reference(f"{task}-test{test_design}")
        self.num_actions = 3 if self.dim == 1 else (8 if self.obstacles or self.dim == 3 else 5)

    @staticmethod
    def _reference(name: str) -> np.ndarray:
        return np.asarray(reference_designs()[name]["design"], dtype=np.int64)

    # --- reset ---

    def _new_design(self) -> np.ndarray:
        if self.fixed_design is not None:
            return self.fixed_design.copy()
        if self.dim == 1:
            return random_sine(self.rng)
        return random_triangle(self.rng, self.dim, self.density)

    def reset(self, design=None, landmarks=None) -> np.ndarray:
        """Start an episode; returns the observation. `landmarks`: a plan-shaped bool mask."""
        self.design = (
            self._new_design()
            if design is None
            else np.asarray(design, dtype=np.int64).reshape((PLAN_1D,) if self.dim == 1 else (PLAN_2D, PLAN_2D))
        )
        ws = self.ws
        if self.dim == 1:
            self.grid = np.full(PLAN_1D + 2 * ws, PADDING, dtype=np.int64)
            self.grid[ws:-ws] = 0
            self.col = 0
        else:
            self.grid = np.full((PLAN_2D + 2 * ws, PLAN_2D + 2 * ws), PADDING, dtype=np.int64)
            self.grid[ws:-ws, ws:-ws] = 0
            self.row, self.col = 0, 0
        self.landmark = None
        if self.dim > 1 and (self.num_landmarks or landmarks is not None):
            if landmarks is None:
                free = np.flatnonzero(self.design.reshape(-1) == 0)
                chosen = self.rng.choice(free, self.num_landmarks, replace=False)
                landmarks = np.zeros(PLAN_2D * PLAN_2D, dtype=bool)
                landmarks[chosen] = True
            self.landmark = np.zeros(self.grid.shape, dtype=bool)
            self.landmark[ws:-ws, ws:-ws] = np.asarray(landmarks, dtype=bool).reshape(PLAN_2D, PLAN_2D)
        if self.dim == 2:
            self.max_bricks = max(int(np.count_nonzero(self.design)), 30)
        else:
            self.max_bricks = int(self.design.sum())
        self.bricks_used = 0
        self.time = 0
        return self.observation()

    # --- step (SPEC §5) ---

    def draw_stride(self) -> int:
        """d in {1, 2, 3} with probabilities `stride_probs`."""
        u = self.rng.random()
        return 1 + (u >= self.stride_thresholds[0]) + (u >= self.stride_thresholds[1])

    def step(self, action: int, stride: int | None = None):
        """One action; returns (obs, reward, terminated, truncated, info). No auto-reset."""
        action = int(action)
        if not 0 <= action < self.num_actions:
            raise ValueError(f"action must be in 0..{self.num_actions - 1}, got {action}")
        self.time += 1
        d = self.draw_stride() if stride is None else int(stride)
        if self.dim == 1:
            reward, terminated = self._step_1d(action, d)
        elif self.obstacles:
            reward, terminated = self._step_obstacles(action, d)
        else:
            reward, terminated = self._step_free(action, d)
        truncated = self.time >= self.max_steps
        info = {"stride": d}  # the IoU is `iou()`, computed on demand (at an episode's end)
        return self.observation(), reward, terminated, truncated, info

    def _step_1d(self, action: int, d: int):
        if action == 0:
            self.col = max(self.col - d, 0)
        elif action == 1:
            self.col = min(self.col + d, PLAN_1D - 1)
        else:
            return self._drop(self.ws + self.col, None)
        return 0.0, False

    def _step_free(self, action: int, d: int):
        """2D, or 3D without obstacles: moves clipped to the design area."""
        if action < 4:
            dr, dc = MOVES[action]
            self.row = min(max(self.row + d * dr, 0), PLAN_2D - 1)
            self.col = min(max(self.col + d * dc, 0), PLAN_2D - 1)
            return 0.0, False
        r, c = self.ws + self.row, self.ws + self.col
        if action > 4 or self.dim == 3:  # 3D action set: drop on a neighbour
            dr, dc = MOVES[action - 4]
            r, c = r + dr, c + dc
        if self.grid[r, c] == PADDING:
            return 0.0, False
        return self._drop(r, c)

    def neighbours_blocked(self) -> list[bool]:
        """For each direction of MOVES: is the neighbour padding or a brick (SPEC §4)?"""
        r, c = self.ws + self.row, self.ws + self.col
        return [self.grid[r + dr, c + dc] != 0 for dr, dc in MOVES]

    def _step_obstacles(self, action: int, d: int):
        """The 3D action set with the obstacle rule (3D, or 2D with the obstacles switch)."""
        stuck = all(self.neighbours_blocked())
        r, c = self.ws + self.row, self.ws + self.col
        if action < 4:
            dr, dc = MOVES[action]
            for _ in range(d):
                if self.grid[r + dr, c + dc] != 0:
                    break
                r, c = r + dr, c + dc
            self.row, self.col = r - self.ws, c - self.ws
            return 0.0, stuck
        dr, dc = MOVES[action - 4]
        if self.grid[r + dr, c + dc] == PADDING:
            return 0.0, stuck
        reward, terminated = self._drop(r + dr, c + dc)
        if stuck:
            return 0.0, True
        return reward, terminated

    def _drop(self, r: int, c: int | None):
        """A counted drop on padded cell (r, c) (1D: r is the padded column, c is None)."""
        self.bricks_used += 1
        cell = r if c is None else (r, c)
        on_landmark = self.landmark is not None and self.landmark[cell]
        if not on_landmark:
            height = int(self.grid[cell]) + 1
            self.grid[cell] = min(height, 1) if self.dim == 2 else height
        if self.bricks_used >= self.max_bricks:
            return 0.0, True
        if on_landmark:
            return 0.0, False
        target = self.design[r - self.ws] if c is None else self.design[r - self.ws, c - self.ws]
        if self.reward_scheme == "height":
            reward = -1.0 if height > target else (10.0 if height == target else 1.0)
        else:  # +5 when the brick belongs to the design (2D: the first brick on a design cell)
            reward = 5.0 if height <= target else 0.0
        return reward, False

    # --- observation and score ---

    def built(self) -> np.ndarray:
        """The design area of the grid (plan-shaped)."""
        ws = self.ws
        return self.grid[ws:-ws] if self.dim == 1 else self.grid[ws:-ws, ws:-ws]

    def observation(self) -> np.ndarray:
        """SPEC §6: window, N_b, N_s, [design], [position]."""
        size = 2 * self.ws + 1
        if self.dim == 1:
            window = self.grid[self.col : self.col + size]
        else:
            window = self.grid[self.row : self.row + size, self.col : self.col + size]
            if self.landmark is not None:
                marks = self.landmark[self.row : self.row + size, self.col : self.col + size]
                window = np.where(marks, LANDMARK, window)
        parts = [window.reshape(-1), [self.bricks_used, self.time]]
        if self.dynamic:
            parts.append(self.design.reshape(-1))
        if self.gps:
            parts.append([self.col] if self.dim == 1 else [self.row, self.col])
        return np.concatenate(parts).astype(np.float32)

    def iou(self) -> float:
        """SPEC §8 on the design area."""
        grid, design = self.built(), self.design
        if self.dim == 2:
            return float(np.sum((grid > 0) & (design > 0)) / np.sum((grid > 0) | (design > 0)))
        return float(np.sum(np.minimum(grid, design)) / np.sum(np.maximum(grid, design)))


def random_policy_steps_per_second(task: str, num_steps: int, seed: int = 0) -> float:
    """Env-steps/s of one `NumpyEnv` under a uniform-random policy, resetting when an episode
    ends, the way the reference benchmark loops (the baseline of `bench/throughput.py`)."""
    import time

    env = NumpyEnv(task, seed=seed)
    rng = np.random.default_rng(seed + 1)
    actions = env.num_actions
    start = time.perf_counter()
    env.reset()
    for _ in range(num_steps):
        _, _, terminated, truncated, _ = env.step(int(rng.random() * actions))
        if terminated or truncated:
            env.iou()  # the episode's score, as a benchmark would record it
            env.reset()
    return num_steps / (time.perf_counter() - start)
