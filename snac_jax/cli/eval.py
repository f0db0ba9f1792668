"""`snac eval`: the evaluation protocol (SPEC §8) for a registered policy, beside the paper's row.

Policies come from the registry in `snac_jax.policies` (name -> builder), so a learned agent
plugs in by registering a builder; options such as `--checkpoint` are handed to the builder.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from snac_jax.atomic import atomic_write_json, check_writable
from snac_jax.cli.arguments import add_devices_argument, add_seed_index_argument, check_seed_index, positive_int, seed
from snac_jax.evaluation import EPISODES_PER_TEST_DESIGN, REPORT_EVAL_SEED, STATIC_EPISODES, TUNING_EVAL_SEED
from snac_jax.paper import PAPER_TASKS
from snac_jax.policies import POLICIES
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
        "--checkpoint", type=Path, default=None, metavar="DIR",
        help="a `snac train` run directory: evaluate its trained policy (on its task unless --task is given)",
    )
    add_seed_index_argument(parser)
    parser.add_argument(
        "--human", type=Path, default=None, metavar="FILE",
        help="summarise the episodes `snac play` recorded in FILE (each is replayed and checked first)",
    )
    parser.add_argument(
        "--task", type=_task, default=None, help="'all' (default: the paper's ten columns), a paper column or a task id"
    )
    parser.add_argument(
        "--episodes",
        type=positive_int,
        default=None,
        help=f"episodes per design: static tasks (each 1D shape) and each dynamic test design "
        f"(default: the paper's {STATIC_EPISODES} static, {EPISODES_PER_TEST_DESIGN} per test design)",
    )
    parser.add_argument("--seed", type=seed, default=TUNING_EVAL_SEED,
                        help=f"evaluation key (default {TUNING_EVAL_SEED}, the tuning one; reported results use "
                             f"{REPORT_EVAL_SEED}, snac_jax.evaluation.REPORT_EVAL_SEED)")
    parser.add_argument("--json", type=Path, default=None, help="write the results here (atomically)")
    parser.add_argument(
        "--paper-results", type=Path, default=None, help="paper_results.json to compare with (default: the packaged copy)"
    )
    add_devices_argument(parser)
    parser.set_defaults(func=run)


def _environment_tasks(task: str) -> tuple[str, ...]:
    from snac_jax.evaluation import environment_tasks

    return tuple(t for column in (PAPER_TASKS if task == "all" else (task,)) for t in environment_tasks(column))


def run(args: argparse.Namespace) -> int:
    from snac_jax.evaluation import evaluate_task
    from snac_jax.paper import load_paper_results, markdown_table, paper_cell, paper_column, paper_row
    from snac_jax.policies import policy_builder

    sources = [args.policy, args.checkpoint, args.human]
    if sum(source is not None for source in sources) != 1:
        raise ValueError("give exactly one of --policy NAME, --checkpoint DIR or --human FILE")
    check_seed_index(args)
    if args.json is not None:
        check_writable(args.json, "--json")  # before the evaluation, not after it
    if args.human is not None:
        from snac_jax.human.records import human_report

        print(human_report(args.human, paper_results=args.paper_results))
        return 0
    if args.checkpoint is not None:
        from snac_jax.plugins import load_checkpoint

        builder, run_task, method, run_overrides = load_checkpoint(args.checkpoint, args.seed_index)
        args.task = args.task or run_task
        others = [t for t in _environment_tasks(args.task) if t != run_task]
        if others:
            raise ValueError(f"checkpoint {args.checkpoint} was trained on {run_task!r}; it cannot be evaluated on "
                             f"{', '.join(others)} (leave out --task to evaluate it on its own)")
        policy_name = f"checkpoint {args.checkpoint}, training seed index {args.seed_index or 0}"
    else:
        builder, method, policy_name = policy_builder(args.policy), POLICIES[args.policy].paper_method, args.policy
        run_overrides = {}
    paper = paper_row(load_paper_results(args.paper_results), method)
    args.task = args.task or "all"
    tasks = PAPER_TASKS if args.task == "all" else (args.task,)
    episodes = {}
    if args.episodes is not None:
        episodes = {"static_episodes": args.episodes, "episodes_per_test_design": args.episodes}

    if run_overrides:
        print(f"with the run's training settings {run_overrides} (the protocol's numbers assume the task's own)",
              file=sys.stderr)
    results = []
    start = time.perf_counter()
    for task in tasks:
        result = evaluate_task(task, builder, seed=args.seed, num_devices=args.devices, **episodes, **run_overrides)
        results.append(result)
        print(f"{task}: mean IoU {result.mean:.3f} over {result.episodes} episodes ({result.wall_s:.1f} s)", file=sys.stderr)
    total_s = time.perf_counter() - start

    columns = "".join(f"; {t} beside the paper's {paper_column(t)} column" for t in tasks if paper_column(t) != t)
    print(f"policy {policy_name} (paper row: {method or 'none'}{columns}), seed {args.seed}")
    print()
    print(markdown_table(results, {r.task: paper_cell(paper, r.task) for r in results}))
    print()
    print(f"wall time {total_s:.1f} s (compile included)")
    if args.json is not None:
        atomic_write_json(args.json, {r.task: r.to_json() for r in results})
        print(f"wrote {args.json}")
    return 0
