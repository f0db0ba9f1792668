"""A learner's IoU per test design of the dynamic tasks against the handcrafted policy's, read
from the committed records (nothing is trained or evaluated here).

    python bench/per_design.py --preset beyond --algorithm pqn-belief --out /tmp/pd

(`bench/results/handcrafted_report_key.json`, the default, is the handcrafted policy on every
column scored with the reporting key, as the table's cells are; `handcrafted.json`, the table's
handcrafted row, is scored with key 0 and so is refused here.)

Reads a preset's cells `<results>/table/<preset>/<algorithm>/<task>.json` (`agents.table.files.read_raw`:
one `eval` row per training seed, each with its `per_design` means) for every dynamic task that has
one, and the handcrafted policy's record (`--handcrafted`, default `<results>/handcrafted_report_key.json`,
keyed by column). Per test design: the learner's mean over seeds, its lowest and highest seed, the
handcrafted mean, their difference, and whether every seed is above the handcrafted mean, every
seed below it, or neither ("mixed"). Scores under different evaluation keys (`seed`), under
different `make` overrides or over different design sets are not comparable: each is refused
before anything is written.

Writes only under `--out` (a directory, required): `per_design.json` and `per_design.md`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.dont_write_bytecode = True  # nothing but the results is written

from bench.written import write_pair  # noqa: E402
from snac_jax.atomic import check_writable  # noqa: E402
from snac_jax.tasks import TASKS, task_spec  # noqa: E402

RESULTS = ROOT / "bench" / "results"
DYNAMIC = tuple(t for t in TASKS if task_spec(t).dynamic)
STEMS = ("per_design.json", "per_design.md")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--preset", required=True, help="a preset with cells under <results>/table/")
    parser.add_argument("--algorithm", required=True, help="an algorithm of that preset")
    parser.add_argument("--out", type=Path, required=True, help="directory for per_design.json and .md")
    parser.add_argument(
        "--results", type=Path, default=RESULTS, help=f"results directory (default {RESULTS.relative_to(ROOT)})"
    )
    parser.add_argument(
        "--handcrafted",
        type=Path,
        default=None,
        help="the handcrafted policy's record, keyed by column (default <results>/handcrafted_report_key.json)",
    )
    parser.add_argument(
        "--task",
        action="append",
        choices=DYNAMIC,
        help="only these dynamic tasks (repeatable; default all with a cell)",
    )
    return parser.parse_args(argv)


def refuse(message: str) -> SystemExit:
    """A one-line refusal, naming what would have been accepted."""
    return SystemExit("per_design.py: " + " ".join(message.split()))


def present(directory: Path) -> str:
    names = sorted(p.name for p in directory.iterdir() if p.is_dir()) if directory.is_dir() else []
    return ", ".join(names) or "none"


def cells(results: Path, preset: str, algorithm: str, tasks: list[str] | None) -> dict[str, Path]:
    """The cell of each dynamic task asked for (all with one where `tasks` is None)."""
    table = results / "table"
    if not (table / preset).is_dir():
        raise refuse(f"--preset {preset}: no such preset under {table}; presets present: {present(table)}")
    if not (table / preset / algorithm).is_dir():
        raise refuse(f"--algorithm {algorithm}: not in preset {preset}; algorithms present: {present(table / preset)}")
    found = {
        t: table / preset / algorithm / f"{t}.json"
        for t in DYNAMIC
        if (table / preset / algorithm / f"{t}.json").is_file()
    }
    missing = sorted(set(tasks or []) - set(found))
    if missing or not found:
        raise refuse(
            f"{preset}/{algorithm} has no cell of {', '.join(missing) or 'any dynamic task'}; "
            f"its dynamic cells: {', '.join(found) or 'none'}"
        )
    return {t: p for t, p in found.items() if tasks is None or t in tasks}


def compare(task: str, seeds: dict, hand: dict, where: str, hand_where: str) -> list[dict]:
    """One row per test design: the learner's seeds against the handcrafted mean. Refuses where the
    evaluation keys or the design sets differ."""
    for name, row in seeds.items():
        if row["seed"] != hand["seed"]:
            raise refuse(
                f"{where}: {name!r} is scored with evaluation key {row['seed']}, {hand_where} with "
                f"{hand['seed']}; different keys are not comparable: give --handcrafted a record scored with "
                f"key {row['seed']}"
            )
        if row.get("overrides") != hand.get("overrides"):
            raise refuse(
                f"{where}: {name!r} is scored with overrides {row.get('overrides')}, {hand_where} with "
                f"{hand.get('overrides')}; only the same conditions are comparable"
            )
        if set(row["per_design"]) != set(hand["per_design"]):
            raise refuse(
                f"{where}: {name!r} has designs {list(row['per_design'])}, {hand_where} "
                f"has {list(hand['per_design'])}; only the same designs are comparable"
            )
    rows = []
    for design in hand["per_design"]:  # the evaluator writes the designs in their index order
        values = [row["per_design"][design]["mean"] for row in seeds.values()]
        handcrafted = hand["per_design"][design]["mean"]
        mean = sum(values) / len(values)
        side = (
            "above"
            if all(v > handcrafted for v in values)
            else "below"
            if all(v < handcrafted for v in values)
            else "mixed"
        )
        rows.append(
            {
                "design": design,
                "mean": mean,
                "lowest_seed": min(values),
                "highest_seed": max(values),
                "seeds": values,
                "handcrafted": handcrafted,
                "difference": mean - handcrafted,
                "seeds_vs_handcrafted": side,
            }
        )
    return rows


def per_task(paths: dict[str, Path], handcrafted: dict, hand_path: Path) -> dict[str, dict]:
    from agents.table.files import read_raw

    tasks = {}
    for task, path in paths.items():
        if task not in handcrafted:
            raise refuse(
                f"{hand_path} has no column {task}; its columns: {', '.join(handcrafted)} (pick tasks with --task "
                f"{' --task '.join(t for t in paths if t in handcrafted) or '...'})"
            )
        try:
            raw = read_raw(path)
        except ValueError as error:
            raise refuse(str(error)) from error
        rows = compare(task, raw["eval"], handcrafted[task], str(path), f"{hand_path} [{task!r}]")
        summary = {side: sum(r["seeds_vs_handcrafted"] == side for r in rows) for side in ("above", "below", "mixed")}
        tasks[task] = {
            "cell": str(path),
            "eval_seed": handcrafted[task]["seed"],
            "training_seeds": len(raw["eval"]),
            "rows": rows,
            "summary": summary,
        }
    return tasks


def markdown(command: str, tasks: dict[str, dict]) -> str:
    lines = [f"`{command}`", ""]
    for task, t in tasks.items():
        s = t["summary"]
        lines += [
            f"## {task}",
            "",
            f"Evaluation key {t['eval_seed']}, {t['training_seeds']} training seeds; designs where "
            f"every seed is above the handcrafted policy: {s['above']}, every seed below: {s['below']}, "
            f"mixed: {s['mixed']} (of {len(t['rows'])}).",
            "",
            "| test design | learner mean | lowest seed | highest seed | handcrafted | Δ (learner − handcrafted) | seeds |",
            "|---|---:|---:|---:|---:|---:|---|",
        ]
        lines += [
            f"| {r['design']} | {r['mean']:.3f} | {r['lowest_seed']:.3f} | {r['highest_seed']:.3f} | "
            f"{r['handcrafted']:.3f} | {r['difference']:+.3f} | {r['seeds_vs_handcrafted']} |"
            for r in t["rows"]
        ]
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    from agents.training import schemas

    args = parse_args(argv)
    paths = cells(args.results, args.preset, args.algorithm, args.task)
    hand_path = args.handcrafted or args.results / "handcrafted_report_key.json"
    try:
        handcrafted = schemas.load(hand_path, schemas.EVAL_JSON)
    except (OSError, ValueError) as error:
        raise refuse(f"--handcrafted {hand_path}: {error}") from error
    tasks = per_task(paths, handcrafted, hand_path)
    try:
        for name in STEMS:
            check_writable(args.out / name)
    except ValueError as error:
        raise refuse(f"--out {args.out}: {error}") from error
    command = " ".join(["python", "bench/per_design.py", *(argv if argv is not None else sys.argv[1:])])
    table = markdown(command, tasks)
    write_pair(
        args.out,
        "per_design",
        {
            "command": command,
            "preset": args.preset,
            "algorithm": args.algorithm,
            "handcrafted": str(hand_path),
            "tasks": tasks,
        },
        table,
    )
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
