"""`snac play`: a person plays a SNAC task in a pygame window (the paper's human baseline)."""

from __future__ import annotations

import argparse
import sys

from snac_jax.cli.arguments import positive_int, seed, task_id
from snac_jax.human.game import LANDMARK_KEY
from snac_jax.tasks import SWITCHES, TASKS

DEFAULT_RECORD = "runs/human.jsonl"


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "play",
        help="play a task yourself in a pygame window; episodes are appended to a JSONL file",
        description="Same view as the agent (the window around the robot, the counters, the design in dynamic "
        "tasks) and the same stride noise. Training mode shows rewards, evaluation mode only steps and bricks; "
        "the IoU is shown when an episode ends. Summarise the file with `snac eval --human FILE`.",
    )
    parser.add_argument("--task", type=task_id, required=True, help=f"one of: {', '.join(TASKS)}")
    parser.add_argument("--mode", choices=("train", "eval"), default="train")
    parser.add_argument("--seed", type=seed, default=0, help="episode i uses seed + i")
    parser.add_argument(
        "--record",
        default=DEFAULT_RECORD,
        metavar="FILE",
        help=f"JSONL file the finished episodes are appended to (default {DEFAULT_RECORD})",
    )
    parser.add_argument("--player", default=None, help="a name stored with each episode")
    parser.add_argument("--max-steps", type=positive_int, default=None, help="override the task's step limit")
    parser.add_argument(
        "--switches",
        default="",
        metavar="KEY=VALUE,...",
        help="environment switches, the syntax of `snac train --switches` (keys: " + ", ".join(SWITCHES) + "; "
        "SPEC §9, §14, §15), stored with each episode so its replay rebuilds the same world; e.g. "
        f"landmark_action=4 lets you place up to 4 landmarks an episode with the {LANDMARK_KEY.upper()} key "
        "(2D/3D), design_change=100/300 changes a dynamic task's design once, between those steps "
        "(in eval mode at the evaluator's fixed step for each test design)",
    )
    parser.add_argument("--episodes", type=positive_int, default=None, help="quit after this many episodes")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from snac_jax.human.game import GameSession
    from snac_jax.human.window import run_window

    session = GameSession(  # a bad --switches is a one-line ValueError here, before the window
        args.task,
        mode=args.mode,
        seed=args.seed,
        max_steps=args.max_steps,
        switches=args.switches,
        record_path=args.record,
        player=args.player,
    )
    try:
        run_window(session, max_episodes=args.episodes)
    finally:  # even when the window fails, no finished episode is lost
        unsaved = len(session.unsaved)
        fallback = _save_unsaved(session)
    for record in session.records:
        print(f"episode seed {record.seed}: {record.steps} steps, {record.bricks_used} bricks, IoU {record.iou:.3f}")
    saved = len(session.records) - unsaved
    print(f"{saved} episode(s) appended to {args.record}", file=sys.stderr if not saved else sys.stdout)
    if unsaved:
        print(
            f"snac play: error: {unsaved} episode(s) could not be appended to {args.record} "
            f"({session.save_error}); they were written to {fallback}",
            file=sys.stderr,
        )
        return 1
    return 0


def _save_unsaved(session) -> str | None:
    """Write the episodes the record file could not take elsewhere; as a last resort print them
    (one JSON line each) so that they can be pasted into a record file."""
    try:
        return str(session.save_unsaved())
    except OSError as error:
        for record in session.unsaved:
            print(record.to_json())
        return f"standard output above (the temporary folder failed too: {error})"
