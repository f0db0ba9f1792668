"""Does a team build faster, and does it build as well? The handcrafted split (SPEC §13) for N
robots beside one robot, scored with the evaluation protocol (SPEC §8).

    python bench/multi_results.py --out /tmp/multi_out                      # the defaults below
    python bench/multi_results.py --out /tmp/quick --episodes 5 --tasks 2d-static-dense

Every N builds in `snac_jax.multi.make(task, num_robots=N)`: one world, one design, the task's
brick budget and step limit shared by the team (SPEC §13), so the rows compare like with like.
Each robot runs the handcrafted policy on its share of the plan (`snac_jax.policies.split`);
N = 1 is the single robot's policy on the whole plan. Episodes: the protocol's (500 on a static
task's design, 200 on each of a dynamic task's ten test designs) unless `--episodes` gives the
count per design; key `--seed` (default the reporting key, `snac_jax.evaluation.REPORT_EVAL_SEED`).

Per (task, N): mean IoU with its 95% interval (over the episodes, or with the test designs as
strata), min IoU, mean episode length (steps to finish), the fraction of episodes that ended
before the step limit (bricks spent or a robot stuck), mean bricks used.

Writes only under `--out` (a directory, required): `multi_results.json` (the rows and the
context) and `multi_results.md` (the table).
"""

from __future__ import annotations

import argparse
import sys
from functools import partial
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.dont_write_bytecode = True  # nothing but the results is written

from bench.written import device_context, write_pair  # noqa: E402
from snac_jax.atomic import check_writable  # noqa: E402  (light: does not start JAX)
from snac_jax.cli.arguments import positive_int, seed  # noqa: E402

DEFAULT_TASKS = ("2d-static-dense", "2d-dynamic-dense")
DEFAULT_ROBOTS = (1, 2, 4)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--tasks", nargs="+", default=list(DEFAULT_TASKS), help=f"task ids (default {' '.join(DEFAULT_TASKS)})"
    )
    parser.add_argument(
        "--robots", nargs="+", type=positive_int, default=list(DEFAULT_ROBOTS), help="robot counts N (default 1 2 4)"
    )
    parser.add_argument(
        "--episodes",
        type=positive_int,
        default=None,
        help="episodes per design (default: the protocol's, 500 static, 200 per test design)",
    )
    parser.add_argument(
        "--seed",
        type=seed,
        default=None,
        help="evaluation key (default: the reporting key, snac_jax.evaluation.REPORT_EVAL_SEED)",
    )
    parser.add_argument("--out", type=Path, required=True, help="directory for multi_results.json and .md")
    args = parser.parse_args(argv)
    from snac_jax import multi
    from snac_jax.tasks import TASKS

    for task in args.tasks:  # every (task, N) checked before the first episode runs
        if task not in TASKS:
            parser.error(f"unknown task {task!r}; allowed: {', '.join(TASKS)}")
        for n in args.robots:
            try:
                multi.check_num_robots(task, n)
            except ValueError as error:
                parser.error(str(error))
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        for name in ("multi_results.json", "multi_results.md"):
            check_writable(args.out / name)
    except (OSError, ValueError) as error:
        parser.error(f"--out {args.out}: {error}")
    return args


def measure(task: str, num_robots: int, episodes: int | None, eval_seed: int) -> dict:
    """One row: the protocol's numbers for the handcrafted split of `num_robots` on `task`."""
    from snac_jax.multi.evaluation import evaluate_team_task
    from snac_jax.policies.team import team_policy

    counts = {} if episodes is None else {"static_episodes": episodes, "episodes_per_test_design": episodes}
    team = evaluate_team_task(task, partial(team_policy, "handcrafted"), num_robots, seed=eval_seed, **counts)
    r = team.result
    return {
        "task": task,
        "robots": num_robots,
        "episodes": r.episodes,
        "mean_iou": r.mean,
        "ci95": r.ci95,
        "min_iou": r.min,
        "std_iou": r.std,
        "mean_length": r.mean_length,
        "finished_fraction": team.finished_fraction,
        "max_steps": team.max_steps,
        "mean_bricks_used": r.mean_bricks_used,
        "per_design": r.per_design,
        "wall_s": r.wall_s,
    }


def markdown(rows: list[dict], context: dict) -> str:
    lines = [
        f"Handcrafted split (snac_jax.policies.split), key {context['seed']}, {context['episodes']}; "
        f"{context['backend']} ({context['device']}), jax {context['jax']}.",
        "",
        "| task | robots | episodes | mean IoU | 95% CI | min IoU | mean length (steps) | length vs 1 robot "
        "| ended by termination | step limit | mean bricks |",
        "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    single = {r["task"]: r["mean_length"] for r in rows if r["robots"] == 1}
    for r in rows:
        ratio = f"{r['mean_length'] / single[r['task']]:.2f}" if r["task"] in single else "—"
        lines.append(
            f"| {r['task']} | {r['robots']} | {r['episodes']} | {r['mean_iou']:.3f} | [{r['ci95'][0]:.3f}, "
            f"{r['ci95'][1]:.3f}] | {r['min_iou']:.3f} | {r['mean_length']:.1f} | {ratio} | "
            f"{r['finished_fraction']:.3f} | {r['max_steps']} | {r['mean_bricks_used']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    args = parse_args(argv)
    from snac_jax.evaluation import REPORT_EVAL_SEED

    args.seed = REPORT_EVAL_SEED if args.seed is None else args.seed
    rows = []
    for task in args.tasks:
        for n in args.robots:
            row = measure(task, n, args.episodes, args.seed)
            rows.append(row)
            print(
                f"{task} N={n}: IoU {row['mean_iou']:.3f} [{row['ci95'][0]:.3f}, {row['ci95'][1]:.3f}], "
                f"length {row['mean_length']:.1f}, ended by termination {row['finished_fraction']:.3f} "
                f"({row['wall_s']:.1f} s)",
                flush=True,
            )
    episodes = (
        "the protocol's episodes (500 per static task, 200 per test design)"
        if args.episodes is None
        else f"{args.episodes} episodes per design"
    )
    context = {
        "command": " ".join(["python", "bench/multi_results.py", *(argv if argv is not None else sys.argv[1:])]),
        "seed": args.seed,
        "episodes": episodes,
        "episodes_per_design": args.episodes,
        **device_context(),
    }
    table = markdown(rows, context)
    write_pair(args.out, "multi_results", {"context": context, "rows": rows}, table)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
