"""IPPO's rows of `bench/results/multi.md`: the `multi` preset's committed cells, robots against
IoU and steps to finish, read from the record (nothing is trained or evaluated here).

    python bench/multi_ippo.py --out /tmp/multi_ippo

Each cell of `snac table --preset multi` (`bench/results/table/multi/ippo/<task>.<arm>.json`,
written by `snac table --preset multi --report`) holds one `eval.json` row per training seed,
scored by the team protocol with the reporting key. Per (task, robots): the mean IoU over seeds
with its 95% bootstrap interval across seeds (`agents.table.statistics.cell_summary`, as the
table), the per-seed IoUs, the mean episode length (steps to finish; the mean over seeds of each
seed's mean) and its ratio to one robot's, and the mean bricks laid.

Writes only under `--out` (a directory, required): `multi_ippo.json` and `multi_ippo.md`.
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

RECORD = ROOT / "bench" / "results" / "table" / "multi" / "ippo"


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--record", type=Path, default=RECORD, help=f"the preset's committed cells (default {RECORD.relative_to(ROOT)})"
    )
    parser.add_argument("--out", type=Path, required=True, help="directory for multi_ippo.json and .md")
    args = parser.parse_args(argv)
    if not args.record.is_dir() or not sorted(args.record.glob("*.json")):
        parser.error(f"--record {args.record}: no cells there; run snac table --preset multi, then --report")
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        for name in ("multi_ippo.json", "multi_ippo.md"):
            check_writable(args.out / name)
    except (OSError, ValueError) as error:
        parser.error(f"--out {args.out}: {error}")
    return args


def row(path: Path) -> dict:
    """One cell's row, from its raw copy (checked against its schema on the way in)."""
    from agents.table.statistics import cell_summary
    from agents.training import schemas

    raw = schemas.load(path, schemas.RAW_CELL_JSON)
    seeds = list(raw["eval"].values())
    iou = cell_summary([s["mean"] for s in seeds])
    return {
        "task": raw["cell"]["task"],
        "robots": int(raw["config"]["robots"]),
        "cell": path.name,
        "env_steps": raw["cell"]["budget"]["env_steps"],
        "seeds": len(seeds),
        "mean_iou": iou["mean"],
        "ci95": iou["ci95"],
        "seed_iou": iou["seeds"],
        "mean_length": sum(s["mean_length"] for s in seeds) / len(seeds),
        "seed_length": [s["mean_length"] for s in seeds],
        "mean_bricks_used": sum(s["mean_bricks_used"] for s in seeds) / len(seeds),
        "eval_seed": raw["cell"]["eval_seed"],
    }


def markdown(rows: list[dict]) -> str:
    lines = [
        "| task | robots | team steps/seed | mean IoU [95% CI across seeds] | per seed | mean length (steps) "
        "| length vs 1 robot | per seed | mean bricks |",
        "|---|---:|---:|---|---|---:|---:|---|---:|",
    ]
    single = {r["task"]: r["mean_length"] for r in rows if r["robots"] == 1}
    for r in rows:
        ratio = f"{r['mean_length'] / single[r['task']]:.2f}" if r["task"] in single else "—"
        lines.append(
            f"| {r['task']} | {r['robots']} | {r['env_steps'] / 1e6:g}M | {r['mean_iou']:.3f} [{r['ci95'][0]:.3f}, "
            f"{r['ci95'][1]:.3f}] | {', '.join(f'{v:.3f}' for v in r['seed_iou'])} | {r['mean_length']:.1f} | {ratio} "
            f"| {', '.join(f'{v:.0f}' for v in r['seed_length'])} | {r['mean_bricks_used']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    args = parse_args(argv)
    rows = sorted((row(path) for path in sorted(args.record.glob("*.json"))), key=lambda r: (r["task"], r["robots"]))
    table = markdown(rows)
    command = " ".join(["python", "bench/multi_ippo.py", *(argv if argv is not None else sys.argv[1:])])
    write_pair(args.out, "multi_ippo", {"command": command, "record": str(args.record), "rows": rows}, table)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
