"""`snac table`: the benchmark table, every learner on the paper's ten columns with several seeds,
in one resumable command.

    snac table --preset paper --dry-run          # the plan: budgets, where each cell stands
    snac table --preset paper                    # run it (again: finished cells are skipped)
    snac table --preset paper --report           # bench/results/table.md, table.json, table-paper.png
    snac table --report --readme README.md       # ... and the README's learner table from them
    snac table --preset ablation                 # the paper's DRQN ablation: one switch at a time

Plugged into the `snac` command through the `snac_jax.commands` entry point (pyproject.toml).
Presets: `agents/table/budgets.toml`, budgets in env steps.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from snac_jax.cli.arguments import add_devices_argument, positive_int

DEFAULT_RUNS_DIR = Path("runs") / "table"
DEFAULT_RESULTS_DIR = Path("bench") / "results"


def add_parser(subparsers) -> None:
    from agents.table.presets import BUDGETS_FILE, load_presets
    from agents.training.registry import ALGORITHMS
    from snac_jax.paper import PAPER_TASKS

    presets = load_presets()
    parser = subparsers.add_parser(
        "table",
        help="the benchmark table: every learner on the paper's columns, several seeds, resumable",
        description=__doc__.split("\n\n")[0],
    )
    add = parser.add_argument
    described = "; ".join(f"{n}: {p.description}" for n, p in presets.items())
    add("--preset", choices=sorted(presets), default="paper", help=f"budget preset ({described}), {BUDGETS_FILE.name}")
    add("--algorithms", nargs="+", metavar="ALGORITHM", choices=list(ALGORITHMS), help="default: the preset's, or all")
    columns = ", ".join(PAPER_TASKS)
    add("--tasks", nargs="+", metavar="TASK", help=f"paper columns or task ids (default: the preset's: {columns})")
    add("--arms", nargs="+", metavar="ARM", help="an ablation preset's arms to run (default: all)")
    add("--seeds", type=positive_int, help="seeds per cell, vmapped (default: the preset's)")
    add("--runs-dir", type=Path, help=f"cells go to RUNS_DIR/<preset>/<algorithm>/<task>[.<arm>]/ ({DEFAULT_RUNS_DIR})")
    add("--dry-run", action="store_true", help="print the plan and stop; with --report, check all and write nothing")
    add("--report", action="store_true", help="copy the finished cells into RESULTS_DIR/table/, write table.md etc.")
    add("--results-dir", type=Path, default=DEFAULT_RESULTS_DIR, help=f"the record (default {DEFAULT_RESULTS_DIR})")
    add("--readme", type=Path, metavar="PATH", help="with --report: also rewrite the README's learner table at PATH")
    add("--no-progress", action="store_true", help="no progress bars")
    add_devices_argument(parser, cpu_default="1, as snac train")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from agents.table.plan import format_plan, make_plan
    from agents.table.presets import load_presets
    from agents.table.readme import replace_block, write_readme
    from agents.table.report import write_report
    from agents.table.run import run_cells
    from agents.training import checkpoint
    from agents.training.registry import ALGORITHMS
    from snac_jax.paper import PAPER_TASKS

    given_runs_dir, args.runs_dir = args.runs_dir is not None, args.runs_dir or DEFAULT_RUNS_DIR
    if args.readme is not None:
        if not args.report:
            raise ValueError("--readme goes with --report (the README's table is written from the report)")
        if args.readme.is_symlink():
            raise ValueError(
                f"--readme {args.readme} is a symbolic link; give the file it points to ({args.readme.resolve()})"
            )
        if not args.readme.is_file():
            raise ValueError(f"--readme {args.readme}: no such file")
        replace_block(args.readme.read_text(), "")  # its marker lines are there, before any work
    if args.report and args.arms is not None:
        raise ValueError("--arms chooses the arms to train; --report reports every arm found (leave --arms out)")
    if args.report:
        runs_dir = args.runs_dir
        if not given_runs_dir and not runs_dir.exists():
            print(f"no runs under {runs_dir} (the default --runs-dir): the report is rebuilt from "
                  f"{args.results_dir / 'table'} alone", file=sys.stderr)  # fmt: skip
            runs_dir = None
        paths = write_report(args.preset, runs_dir, args.results_dir, dry_run=args.dry_run)
        if args.dry_run:
            for key, path in paths.items():
                print(f"would copy {key[5:]} to {path}" if key.startswith("copy:") else f"would write {path}")
            if args.readme is not None:
                print(f"would rewrite the learner table in {args.readme}")
            return 0
        if args.readme is not None:
            paths["readme"] = write_readme(args.readme, json.loads(paths["json"].read_text()))
        print("\n".join(f"wrote {path}" for path in paths.values()))
        return 0
    if not args.dry_run:
        checkpoint.check_lock_file(args.runs_dir / args.preset)  # a `snac table` at work here: refused before the plan
    preset = load_presets()[args.preset]
    algorithms = args.algorithms or list(preset.algorithms or ALGORITHMS)
    tasks = args.tasks or list(preset.tasks or PAPER_TASKS)
    cells = make_plan(preset, algorithms, tasks, args.seeds, args.runs_dir, args.arms)
    print(format_plan(cells, args.runs_dir), flush=True)
    if args.dry_run:
        return 0
    finished = run_cells(cells, progress=not args.no_progress, num_devices=args.devices)  # under that lock
    print(
        f"{finished} of {len(cells)} cells finished; `snac table --preset {args.preset} --report` writes the table",
        file=sys.stderr,
    )
    return 0
