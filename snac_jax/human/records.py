"""Human episodes on disk: one JSON object per line, appended atomically, read back, checked.

A record holds what is needed to replay the episode exactly (the switches, the seed, the design,
the actions and the stride drawn at every step) next to what was measured (IoU, bricks, reward,
duration), so a collected human baseline can be checked against the environment (`replay_iou`)
and summarised like any policy (`summarize_records`, which `snac eval --human FILE` prints). The
game and the replay build the episode's world and first state with the same two functions
(`game_world`, `start_episode`), so a replay meets the game's landmarks and design change.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from snac_jax.atomic import atomic_write
from snac_jax.config import MAX_STRIDE, PLAN_SIZE_1D, PLAN_SIZE_2D
from snac_jax.designs import NUM_TEST_DESIGNS
from snac_jax.paper import paper_column
from snac_jax.schema import HUMAN_RECORD, MODES, check
from snac_jax.tasks import format_switches, parse_switches, task_spec

RECORD_VERSION = 1


@dataclasses.dataclass(frozen=True)
class EpisodeRecord:
    task: str
    mode: str  # one of MODES
    seed: int  # the episode's seed: reset key jax.random.key(seed) (strides are recorded too)
    test_design: int | None  # dynamic tasks in eval mode: the test design played (0..9)
    design: list  # the episode's design at its start, plan-shaped nested lists of ints
    max_steps: int
    actions: list[int]
    strides: list[int]
    total_reward: float
    bricks_used: int
    terminated: bool  # out of bricks or stuck; False: the step limit ended it
    iou: float
    duration_s: float  # wall-clock seconds from the first frame to the end
    started_at: str  # ISO 8601, UTC
    player: str | None = None
    switches: str = ""  # the environment switches played with (`parse_switches` text; "" none)
    version: int = RECORD_VERSION

    @property
    def steps(self) -> int:
        return len(self.actions)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), separators=(",", ":"))

    @classmethod
    def from_dict(cls, data: Any) -> EpisodeRecord:
        """A record from one parsed line, checked against `snac_jax.schema.HUMAN_RECORD` (the
        error names the field), then against the rules that tie its fields together."""
        check(data, HUMAN_RECORD, "")
        record = cls(**data)
        record.validate()
        return record

    def validate(self) -> None:
        """What can be checked without the environment: each field against `HUMAN_RECORD`, then
        the lengths, the design's shape and the test design's presence (`verify_record`
        replays the rest)."""
        check(dataclasses.asdict(self), HUMAN_RECORD, "")
        parse_switches(self.switches)  # the keys; `make` checks the values when the record is replayed
        if len(self.actions) != len(self.strides) or not self.actions:
            raise ValueError("a record needs one stride per action and at least one action")
        if len(self.actions) > self.max_steps:
            raise ValueError(f"{len(self.actions)} actions, more than the step limit max_steps={self.max_steps}")
        spec = task_spec(self.task)
        plays_test_designs = spec.dynamic and self.mode == "eval"
        if plays_test_designs and self.test_design is None:
            raise ValueError(
                f"test_design must be an int in 0..{NUM_TEST_DESIGNS - 1}: a dynamic task's eval-mode "
                "record plays a test design"
            )
        if not plays_test_designs and self.test_design is not None:
            raise ValueError(
                f"test_design must be null: only dynamic tasks in eval mode play test designs, got {self.test_design!r}"
            )
        shape = (1, PLAN_SIZE_1D) if spec.dim == 1 else (PLAN_SIZE_2D, PLAN_SIZE_2D)
        try:
            design = np.asarray(self.design)
        except ValueError:
            design = np.zeros(0)
        if design.shape != shape or not np.issubdtype(design.dtype, np.integer):
            raise ValueError(f"design must be {shape[0]} x {shape[1]} ints for {self.task}, got shape {design.shape}")


def append_record(path: str | os.PathLike, record: EpisodeRecord) -> Path:
    """Append one line to the JSONL file at `path`, atomically.

    The file is rewritten to a temporary file beside it (old lines + the new one), synced, then
    renamed over it: a crash leaves either the old file or the new one, never a torn line.
    """
    record.validate()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    old = path.read_bytes() if path.exists() else b""
    if old and not old.endswith(b"\n"):
        old += b"\n"
    atomic_write(path, lambda f: f.write(old + record.to_json().encode() + b"\n"))
    return path


def load_records(path: str | os.PathLike) -> list[EpisodeRecord]:
    """Every record of a JSONL file; `ValueError` naming the line of a malformed one."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"no human record file at {path}")
    records = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            records.append(EpisodeRecord.from_dict(json.loads(line)))
        except ValueError as error:
            raise ValueError(f"{path}:{number}: not a valid human record ({error})") from error
    return records


def game_world(task: str, mode: str, switches: str = "", max_steps: int | None = None):
    """`(env, params)` the game plays an episode of `task` in, built by `make` (which checks every
    switch value): the task's designs, or for a dynamic task in eval mode its ten test designs
    (episode i plays design i mod 10, `start_episode`). With `design_change` a test design cannot be
    pinned (SPEC §15), so the env comes from a bank of two, as `TrainConfig.scored_world` does, and
    the ten test designs replace that bank; without it from test design 0, so no training bank is drawn."""
    from snac_jax.evaluation import test_design_params
    from snac_jax.tasks import make, parse_switches, without_training_bank

    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    overrides = {**parse_switches(switches), **({} if max_steps is None else {"max_steps": max_steps})}
    if not task_spec(task).dynamic or mode == "train":
        return make(task, **overrides)
    env, params = make(task, **overrides, **without_training_bank(task, overrides))
    return env, test_design_params(task, params)


def start_episode(env, params, seed: int, test_design: int | None):
    """`(obs, state, key_steps)` of the game's episode with `seed`: the reset key is the first half
    of `key(seed)`, the step keys fold the second with the step number. A test design is pinned as
    `reset_env` would pin a bank of one (the same key), and with `design_change` it meets the
    evaluator's fixed change (`design_change.schedule`, SPEC §15), so a person's game on test
    design i changes where every policy's does."""
    import jax

    from snac_jax import design_change

    key_reset, key_steps = jax.random.split(jax.random.key(seed))
    if test_design is None:
        obs, state = env.reset(key_reset, params)
        return obs, state, key_steps
    key = jax.random.fold_in(key_reset, 1) if env.config.num_landmarks else key_reset
    obs, state = env.reset_to_design(key, params, test_design)
    if env.config.design_change is not None:
        state = design_change.schedule(env.config, params, state, test_design)
    return obs, state, key_steps


def _game_start(record: EpisodeRecord):
    """`(env, params, obs, state)`: the world and first state the game gave the record's episode."""
    env, params = game_world(record.task, record.mode, record.switches, record.max_steps)
    obs, state, _ = start_episode(env, params, record.seed, record.test_design)
    return env, params, obs, state


def _on_design(env, params, state, design: np.ndarray):
    """`(obs, state)` with `design` in place of the state's design (its budget and volume too), so a
    replay plays the record's own design; unchanged when it is the game's."""
    from snac_jax.tasks import make_params

    if np.array_equal(np.asarray(state.design), design):
        return env.get_obs(state, params), state
    fresh = make_params(design.astype(np.int16)[None], env.config.dim)
    state = state.replace(design=fresh.designs[0], max_bricks=fresh.design_max_bricks[0], union=fresh.design_volume[0])
    return env.get_obs(state, params), state


REPLAY_CHUNK = 512
"""Replays are padded to a multiple of this many steps, so a task compiles a few times at most."""


@functools.partial(jax.jit, static_argnums=0)
def _replay_scan(env, params, obs0, state0, actions, strides):
    from snac_jax import episodes, metrics

    def decide(episode, action_stride):
        action, stride = action_stride
        return episodes.Move(action, stride=stride), episode.agent

    def record(step):
        return step.reward, step.terminated, step.truncated, metrics.iou(step.state), step.state

    first = episodes.start(obs0, state0, None)
    return episodes.scan_episode(env, params, decide, first, xs=(actions, strides), record=record)[1]


def replay_record(record: EpisodeRecord) -> dict[str, Any]:
    """Replay the record's actions and strides from the game's first state of its episode (its
    switches, seed and test design; `start_episode`) on the record's design: rewards, terminated
    and truncated (one per action), the final IoU, the bricks used and the state after the last
    action. Actions after the episode's end change nothing (`snac_jax.episodes.Step`)."""
    return _replay_from(record, *_game_start(record))


def _replay_from(record: EpisodeRecord, env, params, obs0, state0) -> dict[str, Any]:
    """`replay_record` from the game's start `_game_start(record)`, built by the caller."""
    from snac_jax.env import check_range

    obs0, state0 = _on_design(env, params, state0, np.asarray(record.design))
    steps = len(record.actions)
    check_range("actions", np.asarray(record.actions), 0, env.num_actions - 1)
    check_range("strides", np.asarray(record.strides), 1, MAX_STRIDE)
    padded = -(-steps // REPLAY_CHUNK) * REPLAY_CHUNK
    pad = lambda x: jnp.asarray(np.pad(np.asarray(x, np.int32), (0, padded - steps), constant_values=1))
    rewards, terminated, truncated, ious, states = _replay_scan(
        env, params, obs0, state0, pad(record.actions), pad(record.strides)
    )
    final = jax.tree.map(lambda x: x[steps - 1], states)
    return {
        "rewards": np.asarray(rewards[:steps]),
        "terminated": np.asarray(terminated[:steps]),
        "truncated": np.asarray(truncated[:steps]),
        "final_iou": float(ious[steps - 1]),
        "bricks_used": int(final.bricks_used),
        "final_state": final,
    }


def expected_design(record: EpisodeRecord) -> np.ndarray:
    """The design the game gives the record's episode at its start: the static task's, the test
    design played, or (dynamic tasks in training mode) the one the reset with the record's seed
    draws from the task's training designs."""
    return np.asarray(_game_start(record)[3].design)


def verify_record(record: EpisodeRecord, tolerance: float = 1e-6) -> None:
    """Replay the record and compare: `ValueError` naming the first claim the replay contradicts.

    Checked: the design is the one the game gives this episode (`expected_design`), the actions
    are the task's, the episode ends exactly at the last action (not before: later actions would
    be ignored; not after: it would be unfinished), and the claimed IoU, bricks used, total
    reward and termination are the replay's.
    """
    who = f"record of {record.task} seed {record.seed}"
    try:
        record.validate()
        start = _game_start(record)  # the world is built once, for the design check and the replay
        if not np.array_equal(np.asarray(record.design), np.asarray(start[3].design)):
            which = "its test design" if record.test_design is not None else "the design the game gives this episode"
            raise ValueError(f"its design is not {which}")
        out = _replay_from(record, *start)
    except ValueError as error:
        raise ValueError(f"{who}: {error}") from error
    done = out["terminated"] | out["truncated"]
    ended = np.flatnonzero(done)
    if ended.size and ended[0] < len(record.actions) - 1:
        raise ValueError(
            f"{who}: the episode ends at step {ended[0] + 1}, but the record goes on to {len(record.actions)} actions"
        )
    if not done[-1]:
        raise ValueError(f"{who}: the episode has not ended after its {len(record.actions)} actions")
    claims = {
        "IoU": (record.iou, out["final_iou"]),
        "bricks used": (record.bricks_used, out["bricks_used"]),
        "total reward": (record.total_reward, float(np.sum(out["rewards"], dtype=np.float64))),
        "terminated": (record.terminated, bool(out["terminated"][-1])),
    }
    for name, (claimed, replayed) in claims.items():
        if abs(float(claimed) - float(replayed)) > tolerance:
            raise ValueError(f"{who} claims {name} {claimed}, its replay gives {replayed}")


def replay_iou(record: EpisodeRecord) -> float:
    """The final IoU of replaying the record's actions and strides on its design.

    Equal to `record.iou` for every honest record (`verify_record` checks it, and the rest).
    """
    return replay_record(record)["final_iou"]


def summarize_records(records: Iterable[EpisodeRecord], *, mode: str | None = None, verify: bool = True):
    """Human episodes summarised per paper task as `snac_jax.evaluation.TaskResult`s.

    Games played with switches form their own row, named `task (switches)` with the switches'
    canonical text (`format_switches`, which the game records), so records that spell the same
    switches differently share it: they are another environment, so they neither mix with the
    plain games nor stand beside the paper's number.
    Strata are as in the protocol: the shape (1d-static), the test design (dynamic tasks in eval
    mode), or the task's training designs. `mode` keeps only one mode's episodes; `verify`
    replays every record and raises `ValueError` when it contradicts its record
    (`verify_record`).
    """
    from snac_jax.evaluation import TaskResult

    if mode is not None and mode not in MODES:
        raise ValueError(f"mode must be one of {MODES} or None, got {mode!r}")
    chosen = [r for r in records if mode is None or r.mode == mode]
    if verify:
        for r in chosen:
            verify_record(r)
    groups: dict[str, list[EpisodeRecord]] = {}
    for r in chosen:
        column, switches = paper_column(r.task), format_switches(parse_switches(r.switches))
        groups.setdefault(f"{column} ({switches})" if switches else column, []).append(r)
    results = []
    for task, group in groups.items():
        strata: dict[str, list[float]] = {}
        for r in group:
            name = r.task if r.test_design is None else f"{r.task}-test{r.test_design}"
            strata.setdefault(name, []).append(r.iou)
        arrays = {name: np.asarray(v, np.float64) for name, v in strata.items()}
        results.append(
            TaskResult.from_episodes(
                task,
                arrays,
                lengths=[r.steps for r in group],
                bricks_used=[r.bricks_used for r in group],
                returns=[r.total_reward for r in group],
                seed=-1,  # human episodes carry their own seeds
                wall_s=float(sum(r.duration_s for r in group)),
            )
        )
    return results


def human_report(
    path: str | os.PathLike,
    *,
    mode: str | None = None,
    paper_results: str | os.PathLike | None = None,
    verify: bool = True,
) -> str:
    """What `snac eval --human FILE` prints: the summary of a record file as the evaluator's
    markdown table, beside the paper's human row. Every record is replayed first (`verify`)."""
    from snac_jax.paper import load_paper_results, markdown_table, paper_row

    records = load_records(path)
    results = summarize_records(records, mode=mode, verify=verify)
    if not results:
        raise ValueError(f"{path}: no human episodes" + ("" if mode is None else f" in {mode} mode"))
    paper = paper_row(load_paper_results(paper_results), "human")
    chosen = "all modes" if mode is None else f"{mode} mode"
    header = f"human episodes from {path} ({chosen}; every record replayed: {'yes' if verify else 'no'})"
    return header + "\n\n" + markdown_table(results, paper)
