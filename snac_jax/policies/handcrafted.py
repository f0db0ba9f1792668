"""The handcrafted baseline (paper Algorithm 1, SPEC §11) as a pure, jittable `Policy`.

It knows the design and the constants but never the true position: it keeps an *estimate* of
its plan position, updated from what it sees, and plans from that estimate. Behaviour follows
the authors' scripts (`ai4ce/SNAC`, `script/Handcraft_SLAM/`), which produced the paper's
handcrafted row, including their quirks (each one is named where it is reproduced):

Localisation (after each move; a drop keeps the estimate)
  - 2D/3D: if the window did not change, assume one cell moved (odometry). Otherwise the first
    stride of 1, 2, 3 whose shifted previous window matches the new one on their overlap; if
    none matches the estimate is kept (as in the reference; a real move always matches its own
    stride, so only a hand-made state gets there). Clip to the design area. Then, when a wall
    (-1) shows at an end of the window's middle column (row) the row (column) is recomputed
    from the number of wall cells: exact near walls.
  - 1D: the strides whose shifted window matches are counted; several matches mean odometry
    (one cell), one match gives the stride, none keeps the estimate. What the new window is
    compared with is the 1D variant:
      * `"no-map"` (`slam_1d_no_map.py`, the one the reference test scripts import): the
        previous window, shifted. Drops are decided from the observed height of the own cell.
        It reproduces the paper's 1D row, so it is the default.
      * `"map"` (`slam_1d.py` with `saved_heights`): the robot's own record of the bricks it
        laid, read at the candidate cells; it also decides drops from that record. It scores
        lower, near the "with map" figures written at the end of the reference test scripts.
    Both variants' scores against the paper: bench/results/handcrafted.md.
    A reference quirk kept: moving 2 cells onto the left end is recognised (strides 2 and 3 both
    end there), the same test on the right end looks one cell past it and never fires.

Planning
  - 1D: drop while the own cell (by the estimate) is below the design. Otherwise move toward the
    nearest empty cell (height 0) in the window; a tie, or no empty cell, uses the preferred
    direction, which flips when the robot sees two wall cells on one side.
  - 2D: among window cells that are empty and need a brick (by the design at the estimate), take
    the nearest (Manhattan); at distance 0 drop, else move toward one chosen at random among
    the nearest (a diagonal target picks the horizontal or vertical move at random). With no
    candidate, a random move from a prior that turns away from every wall in view.
  - 3D (and any task with the neighbour-drop action set): the robot drops on a neighbour. The
    nearest candidates are visited in (distance, row, column) order: an adjacent one is built
    on, but only when more than one move stays open (a brick-free neighbour; padding counts as
    open in the reference), else the robot takes the first open move; a farther one is walked
    toward when that move is open, else the next candidate is tried; the prior move (or a
    random open one) is the fallback.

The extensions (SPEC §14-15): with `design_change` the policy reads the design from each
observation, so it re-plans on the design in force from the change on (the bricks already laid
stay; it never removes any). With `landmark_action` it never places a landmark: its localiser
needs walls, not marks. A landmark (-2) in its window is never a candidate, since a drop there
would be spent for nothing. As one robot of a team (SPEC §13, `team=True`, 2D/3D) its localiser
leaves out the window cells that show another robot (-3), before the move or after it, and
after a move that every stride explains counts the median stride (`odometry_stride`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from snac_jax.config import ACTIONS_1D, DOWN, LEFT, MAX_STRIDE, MOVE_DIRECTIONS, RIGHT, UP, EnvConfig
from snac_jax.env import SNACEnv
from snac_jax.multi.rules import ROBOT_VALUE
from snac_jax.observation import layout as observation_layout
from snac_jax.policy import Policy
from snac_jax.transition import PADDING

VARIANTS_1D = ("no-map", "map")
"""1D variants of the reference (`slam_1d.py`, `slam_1d_no_map.py`); see the module docstring."""

_FAR = 10_000  # a distance no window cell reaches: "not a candidate"

# Move actions by direction (the same indices in every action table: moves come first).
_MOVE_LEFT, _MOVE_RIGHT, _MOVE_DOWN, _MOVE_UP = (MOVE_DIRECTIONS.index(d) for d in (LEFT, RIGHT, DOWN, UP))


@struct.dataclass
class HandcraftedState:
    """What the handcrafted robot remembers between steps (one episode, one env)."""

    design: jax.Array  # int32, the design padded like the world but with zeros
    estimate: jax.Array  # int32 (2,), believed plan position (row, col); row 0 in 1D
    last_window: jax.Array  # float32 window seen before the last action
    last_action: jax.Array  # int32; a drop at the start (nothing to localise yet)
    preference: jax.Array  # 1D: int32 preferred move (0 left, 1 right); 2D/3D: float32 (4,) move prior
    built: jax.Array | None = None  # 1D "map" variant: own record of laid bricks, padded with -1


# --- pieces shared by the dimensions -------------------------------------------------------------


def _move_directions(config: EnvConfig) -> list[tuple[int, int]]:
    """(d_row, d_col) of the move actions, in action order (moves come first in every table)."""
    return [(dr, dc) for is_drop, dr, dc in config.actions if not is_drop]


def _shift_matches(config: EnvConfig, old: jax.Array, new: jax.Array, team: bool = False) -> jax.Array:
    """bool (num_moves, MAX_STRIDE): does `new` equal `old` moved by k cells along each move?

    After a move of k cells in (dr, dc), new[i, j] shows the cell old[i + k*dr, j + k*dc]; the
    two windows are compared where both exist (and, in a team, show no other robot: `_agree`).
    """
    rows, cols = config.window_shape
    table = []
    for dr, dc in _move_directions(config):
        per_stride = []
        for k in range(1, MAX_STRIDE + 1):
            r0, r1 = max(0, -k * dr), rows - max(0, k * dr)
            c0, c1 = max(0, -k * dc), cols - max(0, k * dc)
            new_part = new[r0:r1, c0:c1]
            old_part = old[r0 + k * dr : r1 + k * dr, c0 + k * dc : c1 + k * dc]
            per_stride.append(_agree(new_part, old_part, team))
        table.append(jnp.stack(per_stride))
    return jnp.stack(table)


def _agree(a: jax.Array, b: jax.Array, team: bool) -> jax.Array:
    """Do windows (or window parts) `a` and `b` show the same cells? In a team (SPEC §13) a cell
    where another robot stands in either (`ROBOT_VALUE`) is not compared: the robot moved, or
    dropped a brick, between the two views, and says nothing of where the viewer moved. A single
    robot never sees that value, so for it this is plain equality."""
    same = a == b
    if team:
        same = same | (a == ROBOT_VALUE) | (b == ROBOT_VALUE)
    return jnp.all(same)


def _window_of(config: EnvConfig, padded: jax.Array, plan_position: jax.Array) -> jax.Array:
    """The window of a padded plan-sized array centred on `plan_position` (top-left = position)."""
    return jax.lax.dynamic_slice(padded, (plan_position[0], plan_position[1]), config.window_shape)


def _clip_to_plan(config: EnvConfig, position: jax.Array) -> jax.Array:
    return jnp.clip(position, 0, jnp.asarray(config.plan_shape) - 1)


def _window_from_obs(config: EnvConfig, obs: jax.Array) -> jax.Array:
    return observation_layout(config).window_cells(obs)


# --- 1D ------------------------------------------------------------------------------------------

_LEFT, _RIGHT, _DROP_1D = _MOVE_LEFT, _MOVE_RIGHT, ACTIONS_1D.index((1, 0, 0))


def _localise_1d(config: EnvConfig, variant: str, state: HandcraftedState, window: jax.Array) -> jax.Array:
    moved = state.last_action != _DROP_1D
    sign = jnp.where(state.last_action == _LEFT, -1, 1)
    col = state.estimate[1]
    strides = jnp.arange(1, MAX_STRIDE + 1)
    if variant == "map":
        # Compare with the own brick record at each candidate cell (clipped to the plan).
        candidates = jnp.clip(col + strides * sign, 0, config.plan_shape[1] - 1)
        matches = jax.vmap(lambda c: jnp.all(_window_of(config, state.built, jnp.stack([0, c])) == window))(candidates)
    else:
        matches = _shift_matches(config, state.last_window, window)[jnp.clip(state.last_action, 0, 1)]
    # The reference's end test: 2 cells onto an end where strides 2 and 3 coincide. Its right
    # "end" is one past the last cell, so only the left end ever fires (kept as in the reference).
    lands_on_end = (col + 2 * sign == 0) | (col + 2 * sign == config.plan_shape[1])
    onto_end = lands_on_end & ~matches[0] & matches[1]
    first_match = jnp.where(matches[0], 1, jnp.where(matches[1], 2, jnp.where(matches[2], 3, 0)))
    stride = jnp.where(onto_end, 2, jnp.where(jnp.sum(matches) > 1, 1, first_match))
    new_col = jnp.clip(col + stride * sign, 0, config.plan_shape[1] - 1)
    return jnp.where(moved, state.estimate.at[1].set(new_col), state.estimate)


def _plan_1d(config: EnvConfig, variant: str, state: HandcraftedState, window: jax.Array):
    ws = config.half_window
    row = window[0]
    design_here = state.design[0, state.estimate[1] + ws]
    height_here = state.built[0, state.estimate[1] + ws] if variant == "map" else row[ws]
    needs_brick = height_here < design_here

    # Preferred direction flips at a wall: all cells on one side of the robot are padding.
    preference = jnp.where(
        jnp.all(row[ws + 1 :] == PADDING), _LEFT, jnp.where(jnp.all(row[:ws] == PADDING), _RIGHT, state.preference)
    )
    # Nearest empty cell, looking 1, 2, ... cells to each side; a tie keeps the preference.
    right_empty = row[ws + 1 :] == 0
    left_empty = row[:ws][::-1] == 0
    seen = right_empty | left_empty
    nearest = jnp.argmax(seen)
    toward = jnp.where(
        right_empty[nearest] & left_empty[nearest], preference, jnp.where(right_empty[nearest], _RIGHT, _LEFT)
    )
    move = jnp.where(jnp.any(seen), toward, preference)
    action = jnp.where(needs_brick, _DROP_1D, move)
    # The reference updates its preference only when it decides to move.
    preference = jnp.where(needs_brick, state.preference, preference)
    return action.astype(jnp.int32), preference


# --- 2D and 3D -----------------------------------------------------------------------------------


def odometry_stride(stride_probs: jax.Array) -> jax.Array:
    """The median stride of `stride_probs` (strides 1..MAX_STRIDE): the first whose cumulative
    probability reaches one half. 2 for the tasks' uniform strides, 1 for (1, 0, 0)."""
    return (1 + jnp.argmax(jnp.cumsum(jnp.asarray(stride_probs)) >= 0.5 - 1e-6)).astype(jnp.int32)


def _localise_grid(
    config: EnvConfig, state: HandcraftedState, window: jax.Array, team: bool = False, odometry: jax.Array | None = None
) -> jax.Array:
    num_moves = len(_move_directions(config))
    moved = state.last_action < num_moves
    directions = jnp.asarray(_move_directions(config), dtype=jnp.int32)
    move_index = jnp.clip(state.last_action, 0, num_moves - 1)
    matches = _shift_matches(config, state.last_window, window, team)[move_index]
    unchanged = _agree(window, state.last_window, team)
    stride = jnp.where(unchanged | matches[0], 1, jnp.where(matches[1], 2, jnp.where(matches[2], 3, 0)))
    if odometry is not None:
        # A team's robot (`odometry_stride`): a window that every stride explains says nothing of
        # the stride, so it takes the median stride, not the reference's 1 (which, with strides
        # 1-3 equally likely, lags behind on every move across a featureless stretch).
        stride = jnp.where(unchanged | jnp.all(matches), odometry, stride)
    estimate = _clip_to_plan(config, state.estimate + stride * directions[move_index])

    # Absolute fix from a wall at an end of the middle column / middle row.
    ws = config.half_window
    height, width = config.plan_shape
    middle_col, middle_row = window[:, ws] == PADDING, window[ws, :] == PADDING
    row = jnp.where(
        middle_col[0],
        ws - 1 - jnp.sum(middle_col[1:ws]),
        jnp.where(middle_col[-1], height - ws + jnp.sum(middle_col[ws + 1 : -1]), estimate[0]),
    )
    col = jnp.where(
        middle_row[0],
        ws - 1 - jnp.sum(middle_row[1:ws]),
        jnp.where(middle_row[-1], width - ws + jnp.sum(middle_row[ws + 1 : -1]), estimate[1]),
    )
    return jnp.where(moved, jnp.stack([row, col]).astype(jnp.int32), state.estimate)


def _update_prior(prior: jax.Array, window: jax.Array) -> jax.Array:
    """The move prior turns away from every wall in view (a whole window edge of padding).

    Set in the reference's order (left, top, right, bottom walls); the robot starts in a corner,
    so both pairs are set before the prior is first used.
    """
    wall = window == PADDING
    left, top, right, bottom = (jnp.all(wall[:, 0]), jnp.all(wall[0, :]), jnp.all(wall[:, -1]), jnp.all(wall[-1, :]))
    prior = jnp.where(left, prior.at[_MOVE_LEFT].set(0.0).at[_MOVE_RIGHT].set(0.5), prior)
    prior = jnp.where(top, prior.at[_MOVE_DOWN].set(0.5).at[_MOVE_UP].set(0.0), prior)
    prior = jnp.where(right, prior.at[_MOVE_LEFT].set(0.5).at[_MOVE_RIGHT].set(0.0), prior)
    prior = jnp.where(bottom, prior.at[_MOVE_DOWN].set(0.0).at[_MOVE_UP].set(0.5), prior)
    return prior


def _candidates(config: EnvConfig, state: HandcraftedState, window: jax.Array):
    """Window cells that are not full yet where the design (at the estimate) wants bricks, and
    their Manhattan distance from the robot (`_FAR` for the others), plus row/col offsets."""
    ws = config.half_window
    design_window = _window_of(config, state.design, state.estimate)
    needs_brick = (window >= 0) & (window < design_window)
    d_row, d_col = np.indices(config.window_shape) - ws
    distance = jnp.where(needs_brick, np.abs(d_row) + np.abs(d_col), _FAR)
    return distance, jnp.asarray(d_row), jnp.asarray(d_col)


def _move_toward(d_row: jax.Array, d_col: jax.Array, vertical_first: jax.Array) -> jax.Array:
    """The move toward a cell at (d_row, d_col); a diagonal one moves vertically when asked."""
    horizontal = jnp.where(d_col > 0, _MOVE_RIGHT, _MOVE_LEFT)
    vertical = jnp.where(d_row > 0, _MOVE_DOWN, _MOVE_UP)
    return jnp.where(
        d_row == 0, horizontal, jnp.where(d_col == 0, vertical, jnp.where(vertical_first, vertical, horizontal))
    )


def _plan_own_cell_drop(config: EnvConfig, state: HandcraftedState, window: jax.Array, key: jax.Array):
    """2D: drop on the own cell, else walk toward a random one of the nearest candidates."""
    key_target, key_diagonal, key_prior = jax.random.split(key, 3)
    prior = _update_prior(state.preference, window)
    distance, d_row, d_col = _candidates(config, state, window)
    nearest = jnp.min(distance)
    target = jax.random.categorical(key_target, jnp.where(distance == nearest, 0.0, -jnp.inf).reshape(-1))
    toward = _move_toward(d_row.reshape(-1)[target], d_col.reshape(-1)[target], jax.random.bernoulli(key_diagonal))
    random_move = jax.random.categorical(key_prior, jnp.log(prior))
    drop = len(config.actions) - 1  # the table's drop, not a landmark placement after it
    action = jnp.where(nearest == _FAR, random_move, jnp.where(nearest == 0, drop, toward))
    return action.astype(jnp.int32), prior


def _plan_neighbour_drop(config: EnvConfig, state: HandcraftedState, window: jax.Array, key: jax.Array):
    """3D: build on an adjacent candidate while more than one move stays open, else walk."""
    key_diagonal, key_prior, key_open = jax.random.split(key, 3)
    ws = config.half_window
    prior = _update_prior(state.preference, window)
    moves = _move_directions(config)
    neighbours = jnp.stack([window[ws + dr, ws + dc] for dr, dc in moves])
    # The reference counts only bricks as blocking (padding stays "open"); without the obstacle
    # rule nothing blocks.
    open_moves = ~(neighbours > 0) if config.obstacles else jnp.ones(len(moves), bool)
    num_open = jnp.sum(open_moves)

    # Fallback: a move from the prior, replaced by a random open move when that one is blocked.
    prior_move = jax.random.categorical(key_prior, jnp.log(prior))
    random_open = jax.random.categorical(key_open, jnp.where(open_moves, 0.0, -jnp.inf))
    fallback = jnp.where(open_moves[prior_move] | (num_open == 0), prior_move, random_open)

    distance, d_row, d_col = _candidates(config, state, window)
    distance = jnp.where(distance == 0, _FAR, distance)  # the own cell cannot be built on
    rows, cols = config.window_shape
    order = (distance * rows * cols + jnp.arange(rows * cols).reshape(rows, cols)).reshape(-1)

    # An adjacent candidate comes first in (distance, row, col) order and decides alone.
    adjacent = jnp.argmin(jnp.where(distance.reshape(-1) == 1, order, jnp.iinfo(jnp.int32).max))
    has_adjacent = jnp.any(distance == 1)
    drop_actions = {(dr, dc): a for a, (is_drop, dr, dc) in enumerate(config.actions) if is_drop}
    drop_table = np.zeros(rows * cols, dtype=np.int32)
    for (dr, dc), a in drop_actions.items():
        drop_table[(ws + dr) * cols + (ws + dc)] = a
    first_open = jnp.argmax(open_moves)
    adjacent_action = jnp.where(
        num_open > 1, jnp.asarray(drop_table)[adjacent], jnp.where(num_open == 1, first_open, fallback)
    )

    # Farther candidates: the first whose move toward it is open.
    proposed = _move_toward(d_row, d_col, jax.random.bernoulli(key_diagonal, shape=d_row.shape)).reshape(-1)
    usable = (distance.reshape(-1) < _FAR) & open_moves[proposed]
    chosen = jnp.argmin(jnp.where(usable, order, jnp.iinfo(jnp.int32).max))
    far_action = jnp.where(jnp.any(usable), proposed[chosen], fallback)

    action = jnp.where(has_adjacent, adjacent_action, far_action)
    return action.astype(jnp.int32), prior


# --- the policy ----------------------------------------------------------------------------------


def _build(config: EnvConfig, variant: str, team: bool = False) -> Policy:
    neighbour_drop = config.dim > 1 and any(is_drop and (dr, dc) != (0, 0) for is_drop, dr, dc in config.actions)
    drop_action = [a for a, (is_drop, _, _) in enumerate(config.actions) if is_drop][0]

    def init(key: jax.Array, design: jax.Array) -> HandcraftedState:
        (pr, pc) = config.pad
        built = None
        if config.dim == 1 and variant == "map":
            built = jnp.pad(jnp.zeros(config.plan_shape, jnp.int32), ((pr, pr), (pc, pc)), constant_values=PADDING)
        return HandcraftedState(
            design=jnp.pad(design.astype(jnp.int32), ((pr, pr), (pc, pc))),
            estimate=jnp.zeros(2, jnp.int32),
            last_window=jnp.zeros(config.window_shape, jnp.float32),
            last_action=jnp.asarray(drop_action, jnp.int32),
            preference=jnp.asarray(_RIGHT, jnp.int32) if config.dim == 1 else jnp.zeros(4, jnp.float32),
            built=built,
        )

    def act(params, state: HandcraftedState, obs: jax.Array, key: jax.Array):
        window = _window_from_obs(config, obs)
        if config.design_change is not None:
            # The design may change mid-episode (SPEC §15): re-plan on the one the observation shows.
            (pr, pc) = config.pad
            shown = observation_layout(config).design_cells(obs).astype(jnp.int32)
            state = state.replace(design=jnp.pad(shown, ((pr, pr), (pc, pc))))
        if config.dim == 1:
            state = state.replace(estimate=_localise_1d(config, variant, state, window))
            action, preference = _plan_1d(config, variant, state, window)
            built = state.built
            if built is not None:
                cell = state.estimate[1] + config.half_window
                built = built.at[0, cell].add(jnp.where(action == _DROP_1D, 1, 0))
        else:
            odometry = odometry_stride(params) if team else None
            state = state.replace(estimate=_localise_grid(config, state, window, team, odometry))
            plan = _plan_neighbour_drop if neighbour_drop else _plan_own_cell_drop
            action, preference = plan(config, state, window, key)
            built = state.built
        return action, state.replace(last_window=window, last_action=action, preference=preference, built=built)

    suffix = "-map" if config.dim == 1 and variant == "map" else ""
    return Policy(init=init, act=act, params=None, name=f"handcrafted{suffix}")


@functools.cache
def _cached(config: EnvConfig, variant: str, team: bool = False) -> Policy:
    # One Policy (the same init/act objects) per configuration, so jitted evaluators that take
    # them as static arguments compile once per configuration.
    return _build(config, variant, team)


def handcrafted_policy(env: SNACEnv, variant: str = "no-map", *, team: bool = False) -> Policy:
    """The handcrafted baseline for `env`'s task. `variant` selects the 1D version:
    `"no-map"` (the paper's table) or `"map"`; 2D and 3D have one version.

    `team=True` is one robot of a team (`snac_jax.policies.split`, SPEC §13), in 2D/3D: its
    localiser leaves out the window cells that show another robot (`_agree`), and after a move
    that every stride explains it counts the median stride of `env`'s stride distribution
    (`odometry_stride`, its `params`) rather than one cell. In 1D (where leaving robots out
    scored lower) it is the single robot's policy."""
    if variant not in VARIANTS_1D:
        raise ValueError(f"variant must be one of {VARIANTS_1D}, got {variant!r}")
    team = bool(team) and env.config.dim > 1
    policy = _cached(env.config, variant if env.config.dim == 1 else "no-map", team)
    # The stride distribution is the env's params, not its configuration: the params of the policy.
    return policy._replace(params=jnp.asarray(env.default_params.stride_probs)) if team else policy


def handcrafted_policy_map(env: SNACEnv) -> Policy:
    """The 1D variant with its own brick map (`slam_1d.py`); 2D/3D as `handcrafted_policy`."""
    return handcrafted_policy(env, "map")
