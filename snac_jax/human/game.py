"""The human-play game without the window: key bindings, one session of episodes, the screen.

Everything here is testable without a display. `snac_jax.human.window` only turns pygame key
events into key names, passes them to `GameSession.press` and shows `GameSession.frame()`.

The player gets exactly the agent's information (paper, human baseline): the window around the
robot, the step and brick counters, and the design in dynamic tasks (it is part of their
observation) — drawn from the observation vector itself. Strides are drawn by the environment as
for any agent. Training mode also shows the reward of the last step and the episode's total;
evaluation mode hides rewards. The IoU appears when the episode ends.
"""

from __future__ import annotations

import datetime
import os
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from snac_jax.atomic import check_writable
from snac_jax.config import DOWN, LEFT, RIGHT, UP, EnvConfig
from snac_jax.designs import NUM_TEST_DESIGNS
from snac_jax.human.records import MODES, EpisodeRecord, append_record, game_world, start_episode
from snac_jax.rendering import CAPTION_BG, CAPTION_FG, draw_text, render_observation
from snac_jax.tasks import MAX_SEED, format_switches, parse_switches, task_spec

_DIRECTION_WORDS = {LEFT: "left", RIGHT: "right", DOWN: "down", UP: "up"}
_MOVE_KEYS = _DIRECTION_WORDS  # pygame names the arrow keys by their direction
_DROP_KEYS = {(0, 0): "space", LEFT: "a", RIGHT: "d", DOWN: "s", UP: "w"}
NEXT_EPISODE_KEYS = ("return", "enter")
QUIT_KEYS = ("escape", "q")

_TEXT_LINES = 5
_LINE_HEIGHT = 20
_MIN_WIDTH = 460


LANDMARK_KEY = "l"
"""The landmark placement (SPEC §14): a letter no move or drop uses (W/A/S/D drop in 3D)."""


def key_bindings(config: EnvConfig) -> dict[str, int]:
    """Key name (pygame's `key.name`) -> action index, derived from the task's action table.

    Arrow keys move (up = row - d, as rows grow downward on screen); space drops on the own cell
    (1D, 2D); with the neighbour-drop action set (3D, or 2D with obstacles) W/A/S/D drop on the
    neighbour above/left/below/right; L places a landmark where `landmark_action` is on.
    """
    bindings = {}
    for action, (is_drop, d_row, d_col) in enumerate(config.actions):
        table = _DROP_KEYS if is_drop else _MOVE_KEYS
        bindings[table[(d_row, d_col)]] = action
    if config.place_landmark_action is not None:
        bindings[LANDMARK_KEY] = config.place_landmark_action
    return bindings


def key_legend(config: EnvConfig) -> str:
    """One line naming the keys of this task, shown on screen."""
    bindings = key_bindings(config)
    moves = "arrows: move" if config.dim > 1 else "left/right: move"
    mark = f"   {LANDMARK_KEY.upper()}: landmark" if LANDMARK_KEY in bindings else ""
    if "space" in bindings:
        return f"{moves}   space: drop{mark}   esc: quit"
    drops = " ".join(
        f"{key.upper()}={_DIRECTION_WORDS[(d_row, d_col)]}"
        for key, action in bindings.items()
        if key != LANDMARK_KEY
        for is_drop, d_row, d_col in [config.actions[action]]
        if is_drop
    )
    return f"{moves}   drop: {drops}{mark}   esc: quit"


def canonical_switches(text: str) -> str:
    """`text` checked by `parse_switches` (a one-line error naming the allowed keys) and written
    back by `format_switches`: keys in a fixed order, values normalised (`04` is `4`, `True` is
    `true`), so games with the same switches share one row of `snac eval --human` however they
    were typed. Records hold this text."""
    return format_switches(parse_switches(text))


class GameSession:
    """A sequence of episodes of one task played through key presses.

    Episode `i` uses seed `seed + i` (modulo 2**32; `records.start_episode` turns it into the reset
    key and the step keys, the stride of step t from `fold_in` with t + 1). In evaluation mode a
    dynamic task cycles through its ten test designs (episode i plays test design i mod 10), as the
    protocol does, with its fixed design change where `design_change` is on (SPEC §15).
    `switches` are the environment switches in the text of `snac train --switches`
    (`parse_switches`; `landmark_action=K` binds the L key, SPEC §14); they are stored with each
    record, so its replay rebuilds the same environment.
    Each finished episode is appended to `record_path` (if given) as an `EpisodeRecord`. The path
    is checked when the session starts; an episode whose append fails later (disk full,
    permissions changed) is kept in `unsaved` and never dropped: `save_unsaved` writes it
    elsewhere.
    """

    def __init__(
        self,
        task: str,
        mode: str = "train",
        seed: int = 0,
        *,
        max_steps: int | None = None,
        switches: str = "",
        record_path: str | Path | None = None,
        player: str | None = None,
        clock=time.monotonic,
    ):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed <= MAX_SEED:
            raise ValueError(f"seed must be an int in 0..{MAX_SEED}, got {seed!r}")
        self.task, self.mode, self.seed = task, mode, seed
        self.player = player
        self.record_path = None if record_path is None else check_writable(record_path, "record file")
        self.unsaved: list[EpisodeRecord] = []
        self.save_error: str | None = None
        self._clock = clock
        self.switches = canonical_switches(switches)
        self._max_steps = max_steps
        # `make` checks every switch value here, before a window opens. A dynamic task's training
        # design bank takes seconds to draw: the ten test designs give the env, the bank comes on first use.
        dynamic = task_spec(task).dynamic
        self.env, params = game_world(task, "eval" if dynamic else mode, self.switches, max_steps)
        self._eval_params = params if dynamic else None
        self._train_params = None if dynamic else params
        self.config = self.env.config
        self.bindings = key_bindings(self.config)
        self._step = jax.jit(self.env.step_env)
        self.episode_index = -1
        self.records: list[EpisodeRecord] = []
        self.new_episode()

    # --- episodes ------------------------------------------------------------------------------

    @property
    def test_design(self) -> int | None:
        if self.mode == "eval" and self.config.dynamic:
            return self.episode_index % NUM_TEST_DESIGNS
        return None

    def new_episode(self) -> None:
        self.episode_index += 1
        if self.test_design is None:
            if self._train_params is None:
                _, self._train_params = game_world(self.task, "train", self.switches, self._max_steps)
            self.params = self._train_params
        else:
            self.params = self._eval_params
        self.episode_seed = (self.seed + self.episode_index) % (MAX_SEED + 1)
        self.obs, self.state, self._key_steps = start_episode(
            self.env, self.params, self.episode_seed, self.test_design
        )
        self._start_design = np.asarray(self.state.design).astype(int).tolist()
        self.actions: list[int] = []
        self.strides: list[int] = []
        self.last_reward: float | None = None
        self.total_reward = 0.0
        self.over = False
        self.terminated = False
        self.final_iou: float | None = None
        self._started = self._clock()
        self._started_at = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")

    def press(self, key_name: str) -> bool:
        """Handle one key; True when it stepped the environment. Unbound keys do nothing."""
        if self.over or key_name not in self.bindings:
            return False
        self.act(self.bindings[key_name])
        return True

    def act(self, action: int) -> None:
        """One environment step with `action`; ends and records the episode when it ends."""
        if self.over:
            raise ValueError("the episode is over: start a new one with new_episode()")
        if not 0 <= action < self.config.num_actions:
            raise ValueError(f"action must be in 0..{self.config.num_actions - 1}, got {action}")
        key = jax.random.fold_in(self._key_steps, len(self.actions) + 1)
        self.obs, self.state, reward, terminated, info = self._step(key, self.state, action, self.params)
        self.actions.append(int(action))
        self.strides.append(int(info["stride"]))
        self.last_reward = float(reward)
        self.total_reward += self.last_reward
        truncated = int(self.state.time) >= int(self.params.max_steps_in_episode)
        if bool(terminated) or truncated:
            self.over, self.terminated = True, bool(terminated)
            self.final_iou = float(info["final_iou"])
            self._finish()

    def _finish(self) -> None:
        record = EpisodeRecord(
            task=self.task,
            mode=self.mode,
            seed=self.episode_seed,
            test_design=self.test_design,
            design=self._start_design,
            max_steps=int(self.params.max_steps_in_episode),
            actions=list(self.actions),
            strides=list(self.strides),
            total_reward=self.total_reward,
            bricks_used=int(self.state.bricks_used),
            terminated=self.terminated,
            iou=self.final_iou,
            duration_s=round(self._clock() - self._started, 3),
            started_at=self._started_at,
            player=self.player,
            switches=self.switches,
        )
        self.records.append(record)
        if self.record_path is not None:
            try:
                append_record(self.record_path, record)
            except OSError as error:
                self.unsaved.append(record)
                self.save_error = f"could not append to {self.record_path}: {error}"
                print(f"snac play: {self.save_error}; the episode is kept and saved elsewhere at exit", file=sys.stderr)

    def save_unsaved(self, folder: str | Path | None = None) -> Path | None:
        """Append the episodes `record_path` could not take to a new file in `folder` (default:
        the temporary folder); its path, or None when nothing was unsaved."""
        if not self.unsaved:
            return None
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        path = Path(folder or tempfile.gettempdir()) / f"snac-play-unsaved-{stamp}-{os.getpid()}.jsonl"
        for record in self.unsaved:
            append_record(path, record)
        self.unsaved = []
        return path

    # --- the screen ----------------------------------------------------------------------------

    def status_lines(self) -> list[str]:
        """The text under the view: counters (rewards only in training mode), keys, messages."""
        steps = f"step {int(self.state.time)}/{int(self.params.max_steps_in_episode)}"
        bricks = f"bricks {int(self.state.bricks_used)}/{int(self.state.max_bricks)}"
        design = "" if self.test_design is None else f"   test design {self.test_design}"
        lines = [f"{self.task}   {self.mode} mode   episode {self.episode_index + 1}{design}", f"{steps}   {bricks}"]
        if self.mode == "train":
            last = "-" if self.last_reward is None else f"{self.last_reward:+g}"
            lines[1] += f"   reward {last}   total {self.total_reward:+g}"
        lines.append(key_legend(self.config))
        if self.over:
            why = "out of bricks or stuck" if self.terminated else "step limit"
            unsaved = "   NOT SAVED (see the terminal)" if self.records[-1] in self.unsaved else ""
            lines.append(f"Episode over ({why}): IoU {self.final_iou:.3f}{unsaved}")
            lines.append("enter: next episode   esc: quit")
        return lines

    def frame(self) -> np.ndarray:
        """The whole screen as uint8 RGB (H, W, 3); its shape never changes within a session."""
        drop_labels = {
            (d_row, d_col): key.upper()
            for key, action in self.bindings.items()
            if key != LANDMARK_KEY
            for is_drop, d_row, d_col in [self.config.actions[action]]
            if is_drop and (d_row, d_col) != (0, 0)
        }
        view = render_observation(self.env, self.obs, labels=drop_labels)
        width = max(view.shape[1], _MIN_WIDTH)
        screen = np.empty((view.shape[0] + _TEXT_LINES * _LINE_HEIGHT + 8, width, 3), np.uint8)
        screen[:] = CAPTION_BG
        screen[: view.shape[0], : view.shape[1]] = view
        top = view.shape[0] + 4
        items = [(6, top + i * _LINE_HEIGHT, line, CAPTION_FG) for i, line in enumerate(self.status_lines())]
        return draw_text(screen, items, size=14)
