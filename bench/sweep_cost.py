"""What a sweep in one program costs beside the same arms trained one by one, through `snac train`
as a user runs it (process start to exit, compilation and the tiny evaluation included).

    python bench/sweep_cost.py --out bench/results      # 4 arms of PPO-RNN on 1d-static-sin, ~5 min on 2 CPU cores

Runs, in this order and on the same machine: one `snac train ppo --recurrent --sweep
learning-rate=A,B,C,D` and then four `snac train ppo --recurrent --learning-rate X`, each with the
same budget (`--total-steps`, the tuned settings otherwise, one seed). The sweep's wall time is
set beside the four runs' sum and beside one run. Also reported per process: the training's own
wall time (`wall_s` of the last `metrics.jsonl` line: chunks only, no compilation).

Writes only under `--out`: `sweep_cost.json` and `sweep_cost.md`; the runs themselves live in a
scratch folder there, removed at the end.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.dont_write_bytecode = True

from bench.throughput import write_text  # noqa: E402
from snac_jax.cli.arguments import positive_int  # noqa: E402

VALUES = ("3e-4", "1e-3", "3e-3", "1e-2")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="directory for sweep_cost.json and sweep_cost.md")
    parser.add_argument("--total-steps", type=positive_int, default=524288, help="env steps per arm (default 524288)")
    parser.add_argument("--num-envs", type=positive_int, default=None, help="worlds per arm (default: the tuned value)")
    parser.add_argument("--task", default="1d-static-sin")
    return parser.parse_args(argv)


def snac_train(scratch: Path, name: str, extra: list[str], args) -> dict:
    out = scratch / name
    command = [
        sys.executable,
        "-m",
        "snac_jax.cli",
        "train",
        "ppo",
        "--recurrent",
        "--task",
        args.task,
        "--no-progress",
        "--total-steps",
        str(args.total_steps),
        "--chunks",
        "2",
        "--eval-episodes",
        "2",
        "--out",
        str(out),
        *extra,
    ]
    if args.num_envs:
        command += ["--num-envs", str(args.num_envs)]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - start
    if done.returncode:
        raise SystemExit(
            f"sweep_cost.py: error: {' '.join(command[2:])} failed: {done.stderr.strip().splitlines()[-1:]}"
        )
    metrics = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines() if line]
    return {
        "command": "snac " + " ".join(command[3:]).replace(str(scratch) + "/", ""),
        "wall_s": round(wall, 1),
        "training_s": metrics[-1]["wall_s"],
    }


def main(argv=None) -> int:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(dir=args.out, prefix=".sweep-cost-"))
    try:
        sweep = snac_train(scratch, "sweep", ["--sweep", "learning-rate=" + ",".join(VALUES)], args)
        print(f"sweep of {len(VALUES)}: {sweep['wall_s']} s", flush=True)
        singles = []
        for value in VALUES:
            singles.append(snac_train(scratch, f"lr-{value}", ["--learning-rate", value], args))
            print(f"one arm (lr {value}): {singles[-1]['wall_s']} s", flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    import jax

    total = sum(r["wall_s"] for r in singles)
    result = {
        "machine": f"{platform.processor() or platform.machine()} ({jax.devices()[0].platform})",
        "jax": jax.__version__,
        "task": args.task,
        "total_steps_per_arm": args.total_steps,
        "sweep": sweep,
        "singles": singles,
        "sweep_over_singles": sweep["wall_s"] / total,
        "sweep_over_one": sweep["wall_s"] / singles[0]["wall_s"],
    }
    write_text(args.out / "sweep_cost.json", json.dumps(result, indent=1) + "\n")
    lines = [
        "# A sweep in one program beside the arms one by one",
        "",
        f"{result['machine']}, jax {result['jax']}; PPO-RNN on {args.task}, {args.total_steps:,} env steps per arm, one "
        f"seed, the tuned settings but the learning rate; `python bench/sweep_cost.py --out DIR`.",
        "",
        "| what | wall s (process start to exit) | training s (chunks only) |",
        "|---|---:|---:|",
        f"| `--sweep learning-rate={','.join(VALUES)}` | {sweep['wall_s']} | {sweep['training_s']} |",
    ]
    lines += [f"| `--learning-rate {v}` | {r['wall_s']} | {r['training_s']} |" for v, r in zip(VALUES, singles)]
    lines += [
        f"| the four one by one | {total:.1f} | {sum(r['training_s'] for r in singles):.1f} |",
        "",
        f"The sweep took {result['sweep_over_singles']:.2f}x the wall time of the four runs one by one, and "
        f"{result['sweep_over_one']:.2f}x that of one run.",
    ]
    write_text(args.out / "sweep_cost.md", "\n".join(lines) + "\n")
    print(f"wrote {args.out / 'sweep_cost.json'} and {args.out / 'sweep_cost.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
