"""The one device check: how fast snac-jax steps and learns on the machine it runs on.

    python bench/device_check.py --out /tmp/device        # on a lent GPU: at most ~8 minutes on one H100
    python bench/device_check.py --out /tmp/quick --quick  # a smoke run: under 3 minutes on a 2-core CPU
                                                           # (four tasks, 64 worlds, tiny trainings)

What it measures, in this order (each part on JAX's default device, one device, no sharding):

1. **Stepping**: env-steps/s of `snac_jax.rollout.random_rollout` (one jitted scan of
   `env.step_batch`, uniform-random actions, auto-reset) for every task at 4k, 65k and 1M worlds,
   with T = the task's step limit, so every world finishes at least one episode and resets count;
   both auto-reset strategies (`loop`, `select`) and which one `auto` picks here. A point whose
   short calibration run predicts more than `--point-s` seconds is not run in full: its row says
   so and keeps the calibration's rate, marked as such (the `loop` strategy on a GPU at 1M
   worlds would take many minutes).
2. **Learning**: env-steps/s with learning of PPO-RNN and PQN-RNN (their tuned settings for
   1d-static-sin, the README's task, but `num_envs`) at 1k, 8k and 32k worlds, one seed, median
   of `--repeats` timed chunks after compilation.
   Then a sweep (`snac train --sweep`): one compiled chunk of 8 learning-rate arms beside one
   arm, PPO-RNN at 1k worlds, the ratio the claim "8 arms cost about one" reads.
3. **The README's default run**: `snac train ppo` as a subprocess, its wall time and greedy IoU.
4. **The Gymnasium vector env** (`SNACVectorEnv`, one host round trip per step) beside the jitted
   scan of the same task and batch, the ratio the goal "within 2x" reads.

Every median is of `--repeats` timed calls after a warm-up; compilation is timed apart. After each
measurement `device.json` (every row, with the device, jax version and commit) and `device.md`
(the tables) are rewritten atomically under `--out`, so a run cut short still leaves what it
measured. `--budget-s` stops starting new measurements once spent (rows left out say why).
Writes only under `--out` (the README run's scratch directory lives there and is removed).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.dont_write_bytecode = True  # nothing but the results is written

from bench.throughput import write_text  # noqa: E402  (atomic writes; does not start JAX)
from snac_jax.cli.arguments import positive_int  # noqa: E402

FULL = {"worlds": (4096, 65536, 1048576), "learn_worlds": (1024, 8192, 32768), "learn_updates": 5, "sweep_worlds": 1024}
QUICK = {
    "worlds": (64,),
    "learn_worlds": (32,),
    "learn_updates": 2,
    "sweep_worlds": 32,
    "tasks": ("1d-static-sin", "2d-dynamic-dense", "3d-static-sparse", "3d-dynamic-sparse"),
}
LEARNERS = ("ppo", "pqn")
LEARN_TASK = "1d-static-sin"
STRATEGIES = ("loop", "select")
CALIBRATION_STEPS = 16
PARTS = ("step", "learn", "readme", "gymnasium")


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--out", type=Path, required=True, help="directory for device.json and device.md (nothing else is written)"
    )
    parser.add_argument(
        "--quick", action="store_true", help="small batches and a tiny training: a smoke run of every part"
    )
    parser.add_argument("--tasks", nargs="+", default=None, help="tasks to step (default: all twelve)")
    parser.add_argument("--repeats", type=positive_int, default=3, help="timed calls per point, median reported (>= 3)")
    parser.add_argument(
        "--point-s", type=float, default=20.0, help="longest predicted run of one stepping point (default 20)"
    )
    parser.add_argument(
        "--budget-s",
        type=float,
        default=None,
        help="start no measurement after this many seconds (default 450; --quick 150)",
    )
    parser.add_argument(
        "--skip", nargs="+", default=[], choices=PARTS, help="parts to leave out (at most three of the four)"
    )
    args = parser.parse_args(argv)
    if args.repeats < 3:
        parser.error("--repeats must be >= 3 (the median of at least three timed calls)")
    if args.point_s <= 0:
        parser.error(f"--point-s must be > 0, got {args.point_s}")
    if args.budget_s is None:
        args.budget_s = 150.0 if args.quick else 450.0
    elif not args.budget_s > 0:  # NaN fails too
        parser.error(f"--budget-s must be > 0 seconds, got {args.budget_s:g}")
    if set(args.skip) >= set(PARTS):
        parser.error(
            f"--skip {' '.join(args.skip)} leaves nothing to measure; skip at most three of {', '.join(PARTS)}"
        )
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} is a file; give a directory for device.json and device.md")
    return args


class Report:
    """The rows measured so far, rewritten to `device.json` and `device.md` after each one."""

    def __init__(self, out: Path, context: dict, start: float, budget_s: float):
        self.out, self.context, self.start, self.budget_s = out, context, start, budget_s
        self.parts: dict[str, list[dict]] = {part: [] for part in PARTS}

    def time_left(self) -> bool:
        return time.perf_counter() - self.start < self.budget_s

    def add(self, part: str, row: dict) -> None:
        self.parts[part].append(row)
        print(f"[{part}] " + ", ".join(f"{k}={_short(v)}" for k, v in row.items()), flush=True)
        self.context["elapsed_s"] = round(time.perf_counter() - self.start, 1)
        write_text(self.out / "device.json", json.dumps({"context": self.context, **self.parts}, indent=1) + "\n")
        write_text(self.out / "device.md", markdown(self.context, self.parts))


def _short(value):
    return f"{value:,.0f}" if isinstance(value, float) and value > 1000 else value


def _median_seconds(fn, args, repeats: int, warm: bool = False) -> float:
    import jax

    if not warm:
        jax.block_until_ready(fn(*args))  # warm-up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure_stepping(report: Report, tasks: list[str], worlds: tuple[int, ...], args) -> None:
    import jax

    from snac_jax import make
    from snac_jax.batched_step import resolve_reset
    from snac_jax.rollout import random_rollout

    auto = resolve_reset("auto")
    for task in tasks:
        env, params = make(task)
        steps = int(params.max_steps_in_episode)
        for num_envs in worlds:
            for reset in STRATEGIES:
                row = {"task": task, "num_envs": num_envs, "reset": reset, "auto": reset == auto, "steps": steps}
                if not report.time_left():
                    report.add("step", {**row, "skipped": "budget spent"})
                    continue
                key = jax.random.key(0)
                try:
                    start = time.perf_counter()
                    calibrate = random_rollout.lower(
                        key, env, params, num_envs, CALIBRATION_STEPS, None, reset
                    ).compile()
                    row["compile_s"] = round(time.perf_counter() - start, 2)
                    calibration_s = _median_seconds(calibrate, (key, params), args.repeats)
                    predicted = calibration_s * steps / CALIBRATION_STEPS
                    if predicted > args.point_s:
                        report.add(
                            "step",
                            {
                                **row,
                                "skipped": f"predicted {predicted:.0f} s > --point-s {args.point_s:g}",
                                "calibration_steps_per_s": num_envs * CALIBRATION_STEPS / calibration_s,
                            },
                        )
                        continue
                    full = random_rollout.lower(key, env, params, num_envs, steps, None, reset).compile()
                    # The calibration's 16 steps end no episode, so they miss what `loop` pays per reset:
                    # the first full call is timed too, and a point whose repeats would pass --point-s
                    # reports that one call.
                    start = time.perf_counter()
                    episodes = int(jax.block_until_ready(full(key, params)).episodes)
                    first_s = time.perf_counter() - start
                    if first_s * args.repeats > args.point_s:
                        report.add(
                            "step",
                            {
                                **row,
                                "steps_per_s": num_envs * steps / first_s,
                                "run_s": round(first_s, 4),
                                "episodes": episodes,
                                "calls": 1,
                            },
                        )
                        continue
                    seconds = _median_seconds(full, (key, params), args.repeats, warm=True)
                except Exception as error:  # out of memory on this device: the row says so, the check goes on
                    report.add(
                        "step", {**row, "skipped": f"{type(error).__name__}: {str(error).splitlines()[0][:160]}"}
                    )
                    continue
                report.add(
                    "step",
                    {
                        **row,
                        "steps_per_s": num_envs * steps / seconds,
                        "run_s": round(seconds, 4),
                        "episodes": episodes,
                    },
                )


def measure_learning(report: Report, worlds: tuple[int, ...], updates: int, repeats: int) -> None:
    import jax

    from agents.training.driver import initial_state
    from agents.training.registry import build_algorithm, make_config

    for algorithm_name in LEARNERS:
        for num_envs in worlds:
            row = {"algorithm": f"{algorithm_name}-rnn", "task": LEARN_TASK, "num_envs": num_envs, "updates": updates}
            if not report.time_left():
                report.add("learn", {**row, "skipped": "budget spent"})
                continue
            config = make_config(algorithm_name, LEARN_TASK, recurrent=True, num_envs=num_envs, seeds=1)
            algorithm = build_algorithm(config)
            state = initial_state(algorithm, None)
            train = jax.jit(jax.vmap(lambda s, p: algorithm.train_chunk(s, p, updates)[0], in_axes=(0, None)))
            start = time.perf_counter()
            train = train.lower(state, algorithm.env_params).compile()
            compile_s = time.perf_counter() - start
            seconds = _median_seconds(train, (state, algorithm.env_params), repeats)
            report.add(
                "learn",
                {
                    **row,
                    "rollout_steps": config.rollout_steps,
                    "compile_s": round(compile_s, 2),
                    "env_steps_per_s": updates * config.steps_per_update / seconds,
                },
            )


def measure_sweep(report: Report, num_envs: int, updates: int, repeats: int, arms: int = 8) -> None:
    """Seconds per chunk of `updates` PPO-RNN updates for one arm and for a sweep of `arms`
    learning rates, each compiled once, one seed per arm."""
    import jax

    from agents.training.driver import initial_state, per_run
    from agents.training.registry import build_algorithm, make_config
    from agents.training.sweep import parse_sweep

    row = {"algorithm": "ppo-rnn", "task": LEARN_TASK, "num_envs": num_envs, "arms": arms, "updates": updates}
    if not report.time_left():
        report.add("learn", {**row, "skipped": "budget spent"})
        return
    config = make_config("ppo", LEARN_TASK, recurrent=True, num_envs=num_envs, seeds=1)
    algorithm = build_algorithm(config)
    swept = parse_sweep(["learning_rate=" + ",".join(f"{1e-4 * (i + 1):g}" for i in range(arms))], config)
    seconds = {}
    for name, grid in (("one", None), ("sweep", swept)):
        state = initial_state(algorithm, None, grid)
        chunk = jax.jit(
            per_run(algorithm, grid, lambda learner, s, p: learner.train_chunk(s, p, updates)[0], (0, None))
        )
        chunk = chunk.lower(state, algorithm.env_params).compile()
        seconds[name] = _median_seconds(chunk, (state, algorithm.env_params), repeats)
    steps = updates * config.steps_per_update
    report.add(
        "learn",
        {
            **row,
            "one_arm_env_steps_per_s": steps / seconds["one"],
            "sweep_env_steps_per_s": arms * steps / seconds["sweep"],
            "sweep_over_one_arm_time": seconds["sweep"] / seconds["one"],
        },
    )


def measure_readme_run(report: Report, quick: bool) -> None:
    """`snac train ppo` as the README's first command runs it (a tiny budget with `--quick`)."""
    row = {"command": "snac train ppo" + (" (tiny budget)" if quick else "")}
    if not report.time_left():
        report.add("readme", {**row, "skipped": "budget spent"})
        return
    scratch = Path(tempfile.mkdtemp(dir=report.out, prefix=".readme-run-"))
    tiny = ["--total-steps", "2048", "--num-envs", "16", "--eval-episodes", "2", "--chunks", "1"] if quick else []
    command = [
        sys.executable,
        "-m",
        "snac_jax.cli",
        "train",
        "ppo",
        "--no-progress",
        "--out",
        str(scratch / "run"),
        *tiny,
    ]
    try:
        start = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
        wall = time.perf_counter() - start
        if done.returncode:
            report.add("readme", {**row, "skipped": f"exit {done.returncode}: {done.stderr.strip().splitlines()[-1:]}"})
            return
        evaluation = json.loads((scratch / "run" / "eval.json").read_text())
        result = next(iter(evaluation.values()))
        report.add(
            "readme", {**row, "wall_s": round(wall, 1), "iou_mean": result["mean"], "episodes": result["episodes"]}
        )
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def measure_gymnasium(report: Report, num_envs: int, steps: int, repeats: int) -> None:
    """`SNACVectorEnv.step` in a Python loop against the jitted scan of the same worlds."""
    import jax
    import numpy as np

    from snac_jax import make
    from snac_jax.gymnasium import SNACVectorEnv
    from snac_jax.rollout import random_rollout

    task = "2d-static-dense"
    row = {"task": task, "num_envs": num_envs, "steps": steps}
    if not report.time_left():
        report.add("gymnasium", {**row, "skipped": "budget spent"})
        return
    vector = SNACVectorEnv(task, num_envs)
    vector.reset(seed=0)
    actions = (
        np.random.default_rng(0).integers(0, vector.single_action_space.n, size=(steps, num_envs)).astype(np.int32)
    )

    def loop():
        for a in actions:
            vector.step(a)

    loop()  # compiles
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        loop()
        times.append(time.perf_counter() - start)
    vector_rate = num_envs * steps / statistics.median(times)
    env, params = make(task)
    key = jax.random.key(0)
    scan = random_rollout.lower(key, env, params, num_envs, steps).compile()
    scan_rate = num_envs * steps / _median_seconds(scan, (key, params), repeats)
    report.add(
        "gymnasium",
        {
            **row,
            "vector_env_steps_per_s": vector_rate,
            "scan_steps_per_s": scan_rate,
            "scan_over_vector": scan_rate / vector_rate,
        },
    )


def markdown(context: dict, parts: dict[str, list[dict]]) -> str:
    lines = [
        "# Device check",
        "",
        f"{context['device']} ({context['platform']}); jax {context['jax']}; commit {context['commit']}; "
        f"{context['date']}; `{context['command']}`; {context.get('elapsed_s', 0):.0f} s in all. "
        f"Medians of {context['repeats']} timed calls; `auto` resets by `{context['auto_reset']}` here.",
        "",
    ]

    def rate(value) -> str:
        return f"{value / 1e6:,.2f} M" if value is not None else ""

    if parts["step"]:
        lines += [
            "## Stepping: env-steps/s, uniform-random actions, T = the step limit (resets counted)",
            "",
            "| task | worlds | loop | select | auto picks | episodes ended |",
            "|---|---:|---:|---:|---|---:|",
        ]
        points = {}
        for row in parts["step"]:
            points.setdefault((row["task"], row["num_envs"]), {})[row["reset"]] = row
        for (task, num_envs), by_reset in points.items():
            cells = []
            for reset in STRATEGIES:
                row = by_reset.get(reset, {})
                if "steps_per_s" in row:
                    cells.append(rate(row["steps_per_s"]) + (" (one call)" if row.get("calls") == 1 else ""))
                elif "calibration_steps_per_s" in row:
                    cells.append(
                        f"({rate(row['calibration_steps_per_s'])} over {CALIBRATION_STEPS} steps; {row['skipped']})"
                    )
                else:
                    cells.append(row.get("skipped", ""))
            episodes = next((r["episodes"] for r in by_reset.values() if "episodes" in r), "")
            lines.append(
                f"| {task} | {num_envs:,} | {cells[0]} | {cells[1] if len(cells) > 1 else ''} | "
                f"{context['auto_reset']} | {episodes} |"
            )
    if parts["learn"]:
        lines += [
            "",
            f"## Learning: env-steps/s with learning ({LEARN_TASK}, tuned settings but the worlds, one seed)",
            "",
            "| learner | worlds | rollout steps | compile s | env-steps/s |",
            "|---|---:|---:|---:|---:|",
        ]
        for row in parts["learn"]:
            if "arms" in row:
                continue
            lines.append(
                f"| {row['algorithm']} | {row['num_envs']:,} | {row.get('rollout_steps', '')} | "
                f"{row.get('compile_s', '')} | {rate(row.get('env_steps_per_s')) or row.get('skipped', '')} |"
            )
        for row in (r for r in parts["learn"] if "arms" in r):
            lines += [
                "",
                f"A sweep of {row['arms']} learning rates ({row['algorithm']}, {row['num_envs']:,} worlds, one seed "
                "per arm) in one compiled chunk: "
                + (
                    f"{row['sweep_over_one_arm_time']:.2f}x the time of one arm "
                    f"({rate(row['sweep_env_steps_per_s'])} env-steps/s over all arms, one arm alone "
                    f"{rate(row['one_arm_env_steps_per_s'])})"
                    if "sweep_env_steps_per_s" in row
                    else row["skipped"]
                ),
            ]
    for row in parts["readme"]:
        lines += [
            "",
            "## The README's default run",
            "",
            f"`{row['command']}`: "
            + (
                f"{row['wall_s']} s from start to exit, greedy IoU {row['iou_mean']:.3f} "
                f"over {row['episodes']} episodes"
                if "wall_s" in row
                else row["skipped"]
            ),
        ]
    for row in parts["gymnasium"]:
        lines += ["", "## Gymnasium vector env beside the jitted scan", ""]
        lines.append(
            f"{row['task']}, {row['num_envs']:,} worlds x {row['steps']} steps: "
            + (
                f"SNACVectorEnv {rate(row['vector_env_steps_per_s'])}, scan {rate(row['scan_steps_per_s'])} env-steps/s "
                f"(scan / vector env = {row['scan_over_vector']:.1f})"
                if "scan_steps_per_s" in row
                else row["skipped"]
            )
        )
    return "\n".join(lines) + "\n"


def commit() -> str:
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True, cwd=ROOT
        ).stdout
        return head + (" (with uncommitted changes)" if dirty.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        from importlib.metadata import version

        return f"unknown (no git checkout; snac-jax {version('snac-jax')})"


def main(argv=None) -> int:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    import jax

    from snac_jax.batched_step import resolve_reset
    from snac_jax.tasks import TASKS

    sizes = QUICK if args.quick else FULL
    tasks = args.tasks or list(sizes.get("tasks", TASKS))
    unknown = [t for t in tasks if t not in TASKS]
    if unknown:
        print(
            f"device_check.py: error: unknown task(s) {', '.join(unknown)}; allowed: {', '.join(TASKS)}",
            file=sys.stderr,
        )
        return 2
    device = jax.devices()[0]
    context = {
        "device": getattr(device, "device_kind", str(device)) or platform.processor(),
        "platform": device.platform,
        "cores": os.cpu_count(),
        "jax": jax.__version__,
        "commit": commit(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "command": "python bench/device_check.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "repeats": args.repeats,
        "auto_reset": resolve_reset("auto"),
        "quick": args.quick,
    }
    report = Report(args.out, context, start, args.budget_s)
    print(
        f"# device check on {context['device']} ({context['platform']}), jax {context['jax']}, budget {args.budget_s:.0f} s",
        flush=True,
    )
    if "step" not in args.skip:
        measure_stepping(report, tasks, sizes["worlds"], args)
    if "learn" not in args.skip:
        measure_learning(report, sizes["learn_worlds"], sizes["learn_updates"], args.repeats)
        measure_sweep(report, sizes["sweep_worlds"], sizes["learn_updates"], args.repeats)
    if "readme" not in args.skip:
        measure_readme_run(report, args.quick)
    if "gymnasium" not in args.skip:
        measure_gymnasium(report, 64 if args.quick else 4096, 50 if args.quick else 200, args.repeats)
    print(f"wrote {args.out / 'device.json'} and {args.out / 'device.md'} in {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
