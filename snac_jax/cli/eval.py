"""`snac eval`: the evaluation protocol (SPEC §8) for a registered policy, beside the paper's row.

Policies come from the registry in `snac_jax.policies` (name -> builder), so a learned agent
plugs in by registering a builder; options such as `--checkpoint` are handed to the builder.

A team (`--robots N`, or the checkpoint of a team run such as `snac train ippo`) is scored with
the same protocol in `snac_jax.multi`'s world (SPEC §13, `snac_jax.multi.evaluation`): one world,
one design, one brick budget and one step limit for the whole team, so the IoU and the episode
length compare across N.
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

from snac_jax.atomic import atomic_write_json, check_writable
from snac_jax.cli.arguments import add_devices_argument, add_seed_index_argument, check_seed_index, positive_int, seed
from snac_jax.evaluation import EPISODES_PER_TEST_DESIGN, REPORT_EVAL_SEED, STATIC_EPISODES, TUNING_EVAL_SEED
from snac_jax.paper import PAPER_TASKS
from snac_jax.policies import POLICIES
from snac_jax.policies.team import TEAM_POLICIES, team_policy
from snac_jax.tasks import TASKS

TASK_CHOICES = ("all", *PAPER_TASKS, *(t for t in TASKS if t not in PAPER_TASKS))


def _task(text: str) -> str:
    if text not in TASK_CHOICES:
        raise argparse.ArgumentTypeError(f"unknown task {text!r}; allowed: {', '.join(TASK_CHOICES)}")
    return text


def _policy(text: str) -> str:
    if text not in POLICIES:
        raise argparse.ArgumentTypeError(f"unknown policy {text!r}; registered policies: {', '.join(POLICIES)}")
    return text


def add_parser(subparsers) -> None:
    policies = "; ".join(f"{name}: {entry.help}" for name, entry in POLICIES.items())
    parser = subparsers.add_parser(
        "eval",
        help="score a policy with the paper's protocol; markdown table beside the paper's numbers",
        description=f"Policies: {policies}.",
    )
    parser.add_argument("--policy", type=_policy, default=None, help=f"one of: {', '.join(POLICIES)}")
    parser.add_argument(
        "--checkpoint",
        type=Path,
        default=None,
        metavar="DIR",
        help="a `snac train` run directory: evaluate its trained policy (on its task unless --task is given); "
        "a team run (snac train ippo) is scored as its team, with its own robots and switches",
    )
    add_seed_index_argument(parser)
    parser.add_argument(
        "--human",
        type=Path,
        default=None,
        metavar="FILE",
        help="summarise the episodes `snac play` recorded in FILE (each is replayed and checked first)",
    )
    parser.add_argument(
        "--task", type=_task, default=None, help="'all' (default: the paper's ten columns), a paper column or a task id"
    )
    parser.add_argument(
        "--switches",
        default=None,
        metavar="KEY=VALUE,...",
        help="with --policy: score on tasks built with these switches (SPEC §9), the syntax of "
        "`snac train --switches`, e.g. gps=true,stride_probs=1/0/0 (a checkpoint keeps its run's own)",
    )
    parser.add_argument(
        "--robots",
        type=positive_int,
        default=None,
        metavar="N",
        help=f"with --policy ({', '.join(TEAM_POLICIES)}): score a team of N robots in one world (snac_jax.multi, "
        "SPEC §13); handcrafted splits the plan among them (snac_jax.policies.split)",
    )
    parser.add_argument(
        "--episodes",
        type=positive_int,
        default=None,
        help=f"episodes per design: static tasks (each 1D shape) and each dynamic test design "
        f"(default: the paper's {STATIC_EPISODES} static, {EPISODES_PER_TEST_DESIGN} per test design)",
    )
    parser.add_argument(
        "--seed",
        type=seed,
        default=TUNING_EVAL_SEED,
        help=f"evaluation key (default {TUNING_EVAL_SEED}, the tuning one; reported results use "
        f"{REPORT_EVAL_SEED}, snac_jax.evaluation.REPORT_EVAL_SEED)",
    )
    parser.add_argument("--json", type=Path, default=None, help="write the results here (atomically)")
    parser.add_argument(
        "--paper-results",
        type=Path,
        default=None,
        help="paper_results.json to compare with (default: the packaged copy)",
    )
    add_devices_argument(parser)
    parser.set_defaults(func=run)


def _environment_tasks(task: str) -> tuple[str, ...]:
    from snac_jax.evaluation import environment_tasks

    return tuple(t for column in (PAPER_TASKS if task == "all" else (task,)) for t in environment_tasks(column))


# --- the command ---------------------------------------------------------------------------------


def _check_worlds(env_tasks, robots: int | None, switches: dict[str, Any]) -> None:
    """Build every world the evaluation will use, so a switch value out of range or a robot
    count a task does not hold is a one-line error before anything runs (a dynamic task is
    pinned to a test design here, which draws no training bank)."""
    from snac_jax import multi
    from snac_jax.tasks import make, without_training_bank

    for env_task in env_tasks:
        pin = without_training_bank(env_task, switches)
        if robots is None:
            make(env_task, **switches, **pin)
        else:
            multi.make(env_task, num_robots=robots, **switches, **pin)


def _check_sources(args: argparse.Namespace) -> None:
    sources = [args.policy, args.checkpoint, args.human]
    if sum(source is not None for source in sources) != 1:
        raise ValueError("give exactly one of --policy NAME, --checkpoint DIR or --human FILE")
    if args.checkpoint is not None:
        for flag, value in (("--switches", args.switches), ("--robots", args.robots)):
            if value is not None:
                raise ValueError(f"{flag}: a checkpoint is scored with its run's own switches and robots; leave it out")
    if args.human is not None and (args.switches is not None or args.robots is not None):
        raise ValueError("--switches and --robots apply to --policy or --checkpoint, not to --human")
    if args.robots is not None and args.devices not in (None, 1):
        raise ValueError(f"--devices {args.devices}: a team's episodes run on one device; leave it out with --robots")
    if args.robots is not None and args.policy not in TEAM_POLICIES:
        raise ValueError(f"--robots runs a team of one of: {', '.join(TEAM_POLICIES)}; got --policy {args.policy}")


def run(args: argparse.Namespace) -> int:
    from snac_jax.evaluation import evaluate_task
    from snac_jax.multi.evaluation import evaluate_team_task
    from snac_jax.paper import load_paper_results, markdown_table, paper_cell, paper_column, paper_row
    from snac_jax.policies import policy_builder
    from snac_jax.tasks import parse_switches

    _check_sources(args)
    check_seed_index(args)
    if args.json is not None:
        check_writable(args.json, "--json")  # before the evaluation, not after it
    if args.human is not None:
        from snac_jax.human.records import human_report

        print(human_report(args.human, paper_results=args.paper_results))
        return 0
    robots = args.robots
    if args.checkpoint is not None:
        from snac_jax.plugins import load_checkpoint

        builder, run_task, method, run_overrides = load_checkpoint(args.checkpoint, args.seed_index)
        run_overrides = dict(run_overrides)
        robots = run_overrides.pop("num_robots", None)  # a team run's loader names its robots
        args.task = args.task or run_task
        others = [t for t in _environment_tasks(args.task) if t != run_task]
        if others:
            raise ValueError(
                f"checkpoint {args.checkpoint} was trained on {run_task!r}; it cannot be evaluated on "
                f"{', '.join(others)} (leave out --task to evaluate it on its own)"
            )
        policy_name = f"checkpoint {args.checkpoint}, {builder.label}"
    else:
        run_overrides = parse_switches(args.switches or "")
        method, policy_name = POLICIES[args.policy].paper_method, args.policy
        builder = policy_builder(args.policy) if robots is None else partial(team_policy, args.policy)
    args.task = args.task or "all"
    tasks = PAPER_TASKS if args.task == "all" else (args.task,)
    if args.checkpoint is None:
        _check_worlds(_environment_tasks(args.task), robots, run_overrides)
    episodes = {}
    if args.episodes is not None:
        episodes = {"static_episodes": args.episodes, "episodes_per_test_design": args.episodes}

    if run_overrides:
        where = "the run's training settings" if args.checkpoint is not None else "the switches"
        print(f"with {where} {run_overrides} (the protocol's numbers assume the task's own)", file=sys.stderr)
    results, rows = [], []
    start = time.perf_counter()
    for task in tasks:
        if robots is None:
            result = evaluate_task(task, builder, seed=args.seed, num_devices=args.devices, **episodes, **run_overrides)
            rows.append(result)
        else:
            result = evaluate_team_task(task, builder, robots, seed=args.seed, **episodes, **run_overrides)
            rows.append(result.result)
            print(
                f"{task}: {result.finished_fraction:.3f} of the episodes ended with the bricks spent or a robot "
                f"stuck rather than at the step limit ({result.max_steps})",
                file=sys.stderr,
            )
        results.append(result)
        print(
            f"{task}: mean IoU {rows[-1].mean:.3f} over {rows[-1].episodes} episodes ({rows[-1].wall_s:.1f} s)",
            file=sys.stderr,
        )
    total_s = time.perf_counter() - start

    if robots is None and not run_overrides:
        paper = paper_row(load_paper_results(args.paper_results), method)
        cells = {r.task: paper_cell(paper, r.task) for r in rows}
        columns = "".join(f"; {t} beside the paper's {paper_column(t)} column" for t in tasks if paper_column(t) != t)
        print(f"policy {policy_name} (paper row: {method or 'none'}{columns}), seed {args.seed}")
    elif robots is None:
        cells = {}  # the paper scored the tasks as they are, not with these settings
        print(f"policy {policy_name}, with {run_overrides} (no paper row), seed {args.seed}")
    else:
        cells = {}  # the paper has one robot
        print(
            f"policy {policy_name}, a team of {robots} robot(s) in one world (SPEC §13; the paper has one robot: "
            f"no paper row), seed {args.seed}"
        )
    print()
    print(markdown_table(rows, cells))
    print()
    print(f"wall time {total_s:.1f} s (compile included)")
    if args.json is not None:
        scored = (
            {r.task: r.to_json() for r in rows} if robots is None else {r.result.task: r.to_json() for r in results}
        )
        if run_overrides:  # what the numbers were scored with travels with them
            scored = {task: {**entry, "overrides": run_overrides} for task, entry in scored.items()}
        atomic_write_json(args.json, scored)
        print(f"wrote {args.json}")
    return 0
