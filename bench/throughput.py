"""Throughput of the SNAC environments: env-steps/s of jitted, vmapped random rollouts with
auto-reset, for every task and batch size, against the plain NumPy engine in the same run.

    python bench/throughput.py --out bench/results                  # all tasks, N in 1 64 1024 4096 16384
    python bench/throughput.py --out bench/results --devices 1,all  # also without sharding, to compare
    python bench/throughput.py --out /tmp/quick --quick             # every task at one small N (< 2 min)
    python bench/throughput.py --out /tmp/dense --tasks 2d-static-dense --num-envs 1024 4096

What is timed: `snac_jax.rollout.random_rollout`, one jitted `lax.scan` of `--steps` steps over
N worlds (uniform-random actions, auto-reset, episode statistics accumulated), split over the
local devices with `shard_map` (`--devices`; on a CPU one device per core). The worlds step with
`env.step_batch` (equal to `vmap(env.step)` bit for bit) and each auto-reset strategy of
`--reset` (default `auto`: the backend's own; `--reset loop select` measures both, `select` being
what `vmap(env.step)` computes). Each point is
the median of `--repeats` timed calls after one warm-up call; compilation is timed on its own.
The policy does not read observations, so XLA drops their computation, as in gymnax's own
benchmarks; a learning agent pays for them on top.

The baseline is `bench/numpy_engine.py`: one world stepped in a Python loop with NumPy, reset
when an episode ends, the way the reference implementation is written (one process, one core).

Writes only under `--out` (a directory, required): `throughput.json`, a list of rows {"task",
"num_envs", "steps_per_s", "compile_s", "numpy_steps_per_s", "ratio", ...}; `throughput.md`, the
tables; `throughput_<family>.png`, log-log steps/s against N per family; `snac_rollout_e2e.json`.
The committed tables in bench/results/ change only when `--out bench/results` says so.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.dont_write_bytecode = True  # nothing but the results is written

from snac_jax import devices  # noqa: E402  (light: does not start JAX)
from snac_jax.batched_step import RESET_STRATEGIES  # noqa: E402
from snac_jax.cli.arguments import positive_int  # noqa: E402  (light as well)

DEFAULT_NUM_ENVS = (1, 64, 1024, 4096, 16384)
FAMILIES = ("1d", "2d", "3d")


def device_counts(text: str) -> list[int]:
    """`all`, an int, or a comma list of them (`1,all`)."""
    counts = []
    for part in text.split(","):
        part = part.strip()
        if part == "all":
            counts.append(devices.available_cores())
        else:
            counts.append(positive_int(part))
    return sorted(set(counts))


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--tasks", nargs="+", default=None, help="task ids (default: all twelve)")
    parser.add_argument(
        "--num-envs", nargs="+", type=positive_int, default=None, help=f"batch sizes N (default {DEFAULT_NUM_ENVS})"
    )
    parser.add_argument(
        "--steps",
        type=positive_int,
        default=None,
        help="steps per rollout T (default 1000; covers the 1D/2D step limits)",
    )
    parser.add_argument(
        "--repeats", type=positive_int, default=3, help="timed repeats per point, median reported (>= 3)"
    )
    parser.add_argument(
        "--devices",
        type=device_counts,
        default=None,
        help="device counts to measure, e.g. 'all' (default: one per core), '1', '1,all'",
    )
    parser.add_argument(
        "--reset",
        nargs="+",
        choices=RESET_STRATEGIES,
        default=["auto"],
        help="auto-reset strategies to measure (default: auto, the backend's own); "
        "select is what vmap(env.step) computes",
    )
    parser.add_argument(
        "--numpy-steps", type=positive_int, default=None, help="steps of the NumPy baseline per task (default 20000)"
    )
    parser.add_argument("--no-e2e", action="store_true", help="skip timing `snac rollout` end to end")
    parser.add_argument("--quick", action="store_true", help="every task at N=64, T=100: a smoke run (< 2 min)")
    parser.add_argument(
        "--from-json",
        type=Path,
        default=None,
        metavar="PATH",
        help="measure nothing: rebuild the table and plots from the rows of an earlier run",
    )
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        help="directory for everything written: rows, table, plots (bench/results for the committed ones)",
    )
    args = parser.parse_args(argv)
    if args.repeats < 3:
        parser.error("--repeats must be >= 3 (the median of at least three timed calls)")
    if args.quick:
        args.num_envs = args.num_envs or [64]
        args.steps = args.steps or 100
        args.numpy_steps = args.numpy_steps or 2000
    args.num_envs = args.num_envs or list(DEFAULT_NUM_ENVS)
    args.steps = args.steps or 1000
    args.numpy_steps = args.numpy_steps or 20000
    args.devices = args.devices or [devices.available_cores()]
    return args


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def usable_devices(num_envs: int, num_devices: int) -> int:
    """The most devices, up to the number asked for, that split the worlds evenly (N = 1: one)."""
    import jax

    return max(d for d in range(1, min(num_devices, len(jax.devices())) + 1) if num_envs % d == 0)


def measure_jax(task: str, num_envs: int, num_steps: int, num_devices: int, repeats: int, reset: str = "auto") -> dict:
    import jax

    from snac_jax import make
    from snac_jax.rollout import random_rollout

    env, params = make(task)
    mesh = devices.env_mesh(usable_devices(num_envs, num_devices))
    key = jax.random.key(0)
    start = time.perf_counter()
    compiled = random_rollout.lower(key, env, params, num_envs, num_steps, mesh, reset).compile()
    compile_s = time.perf_counter() - start
    memory = compiled.memory_analysis()
    xla_mb = None
    if memory is not None:
        xla_mb = (memory.argument_size_in_bytes + memory.output_size_in_bytes + memory.temp_size_in_bytes) / 2**20
    stats = jax.block_until_ready(compiled(key, params))  # warm-up
    times = []
    for repeat in range(repeats):
        start = time.perf_counter()
        stats = jax.block_until_ready(compiled(jax.random.key(repeat + 1), params))
        times.append(time.perf_counter() - start)
    return {
        "steps_per_s": num_envs * num_steps / statistics.median(times),
        "compile_s": compile_s,
        "devices": int(mesh.devices.size),
        "episodes": int(stats.episodes),
        "xla_buffers_mb": xla_mb,
        "peak_rss_mb": peak_rss_mb(),
        "run_s": statistics.median(times),
    }


def measure_numpy(task: str, num_steps: int) -> float:
    from bench.numpy_engine import random_policy_steps_per_second

    random_policy_steps_per_second(task, min(num_steps, 500))  # warm-up (imports, caches)
    return random_policy_steps_per_second(task, num_steps)


def time_snac_rollout(extra: list[str]) -> dict:
    """`snac rollout` from process start to exit, default configuration plus `extra`."""
    command = [sys.executable, "-m", "snac_jax.cli", "rollout", *extra]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
    wall = time.perf_counter() - start
    if done.returncode:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr}")
    return {"command": "snac rollout " + " ".join(extra), "wall_s": wall, "output": done.stdout.strip()}


def load() -> str:
    try:
        return Path("/proc/loadavg").read_text().split()[0]
    except OSError:
        return "n/a"


def reset_of(row: dict) -> str:
    """The auto-reset strategy a row measured (rows written before `reset` existed name the step:
    `step_batch` reset one by one, `vmap(step)` selected)."""
    return row.get("reset") or ("loop" if row["step"] == "step_batch" else "select")


def family(task: str) -> str:
    return task[:2]


def markdown(rows: list[dict], e2e: list[dict], context: dict) -> str:
    lines = [
        "# SNAC-JAX throughput",
        "",
        f"{context['machine']}; {context['cores']} cores; jax {context['jax']}; T = {context['steps']} steps per rollout, "
        f"median of {context['repeats']} runs; load average {context['load_start']} at start, {context['load_end']} at end. "
        "Uniform-random policy, auto-reset included; env-steps/s summed over all worlds. "
        "NumPy: one world per Python loop (`bench/numpy_engine.py`), one core.",
        "",
    ]
    columns = sorted({(r["devices_requested"], reset_of(r)) for r in rows}, key=lambda c: (c[1], c[0]))
    largest = max(r["num_envs"] for r in rows)
    lines += [f"## Headline: N = {largest}", ""]
    header = (
        "| task | "
        + " | ".join(f"{d} device{'s' if d > 1 else ''}, {step} reset" for d, step in columns)
        + " | NumPy | JAX / NumPy (best) |"
    )
    lines += [header, "|" + "---|" * (len(columns) + 3)]
    for task in dict.fromkeys(r["task"] for r in rows):
        cells = []
        best = None
        for d, step in columns:
            match = [
                r
                for r in rows
                if r["task"] == task
                and r["num_envs"] == largest
                and r["devices_requested"] == d
                and reset_of(r) == step
            ]
            cells.append(f"{match[0]['steps_per_s'] / 1e6:.2f} M" if match else "")
            if match and (best is None or match[0]["steps_per_s"] > best["steps_per_s"]):
                best = match[0]
        if best:
            lines.append(
                f"| {task} | "
                + " | ".join(cells)
                + f" | {best['numpy_steps_per_s'] / 1e3:.0f} k | {best['ratio']:.0f}x |"
            )
    for fam in FAMILIES:
        fam_rows = [r for r in rows if family(r["task"]) == fam]
        if not fam_rows:
            continue
        lines += [
            "",
            f"## {fam.upper()}",
            "",
            "| task | N | devices | reset | env-steps/s | compile s | XLA buffers MB | peak RSS MB | NumPy steps/s | JAX / NumPy |",
            "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|",
        ]
        for r in fam_rows:
            xla = f"{r['xla_buffers_mb']:.0f}" if r["xla_buffers_mb"] is not None else ""
            lines.append(
                f"| {r['task']} | {r['num_envs']} | {r['devices']} | {reset_of(r)} | {r['steps_per_s']:,.0f} | {r['compile_s']:.2f} | {xla} | "
                f"{r['peak_rss_mb']:.0f} | {r['numpy_steps_per_s']:,.0f} | {r['ratio']:.1f} |"
            )
    if e2e:
        lines += [
            "",
            "## `snac rollout` end to end (process start to exit)",
            "",
            "| command | wall s | its own report |",
            "|---|---:|---|",
        ]
        for item in e2e:
            report = item["output"].replace("\n", "; ")
            lines.append(f"| `{item['command']}` | {item['wall_s']:.2f} | {report} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    for fam in FAMILIES:
        fam_rows = [r for r in rows if family(r["task"]) == fam]
        if not fam_rows:
            continue
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for i, task in enumerate(dict.fromkeys(r["task"] for r in fam_rows)):
            colour = f"C{i}"
            for d, step in sorted({(r["devices_requested"], reset_of(r)) for r in fam_rows}):
                points = sorted(
                    (r["num_envs"], r["steps_per_s"])
                    for r in fam_rows
                    if r["task"] == task and r["devices_requested"] == d and reset_of(r) == step
                )
                style = ("-" if d > 1 else "--") + ("o" if step == "loop" else "x")
                label = f"{task} ({d} dev, {step})"
                ax.plot(*zip(*points), style, color=colour, label=label, markersize=4)
            numpy_rate = next(r["numpy_steps_per_s"] for r in fam_rows if r["task"] == task)
            ax.axhline(numpy_rate, color=colour, linestyle=":", linewidth=1)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("parallel worlds N")
        ax.set_ylabel("env-steps / s")
        ax.set_title(f"{fam.upper()} tasks: JAX (lines) vs NumPy, one world per loop (dotted)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
        fig.tight_layout()
        path = out / f"throughput_{fam}.png"
        write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=120, format="png"))
        plt.close(fig)
        written.append(path)
    return written


def write_atomic(path: Path, write) -> None:
    """Write through a temporary file in the same directory, then rename: a crash never leaves
    a half-written result."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def write_text(path: Path, text: str) -> None:
    write_atomic(path, lambda tmp: Path(tmp).write_text(text))


def rebuild(args: argparse.Namespace) -> int:
    """The table and plots of the rows in `args.from_json` (and its snac_rollout_e2e.json)."""
    rows = json.loads(args.from_json.read_text())
    e2e_path = args.from_json.parent / "snac_rollout_e2e.json"
    e2e = json.loads(e2e_path.read_text()) if e2e_path.exists() else []
    loads = [r["load"] for r in rows]
    context = {
        "machine": f"{platform.processor() or platform.machine()}",
        "cores": devices.available_cores(),
        "jax": rows[0].get("jax", "?"),
        "steps": rows[0]["steps"],
        "repeats": rows[0].get("repeats", "?"),
        "load_start": loads[0],
        "load_end": loads[-1],
    }
    write_text(args.out / "throughput.md", markdown(rows, e2e, context))
    plot(rows, args.out)
    return 0


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.from_json is not None:
        return rebuild(args)
    devices.use_cpu_devices(max(args.devices))  # before anything starts JAX (gymnax does on import)
    import jax

    from snac_jax.tasks import TASKS

    tasks = args.tasks or list(TASKS)
    unknown = [t for t in tasks if t not in TASKS]
    if unknown:
        raise ValueError(f"unknown task(s) {unknown}; allowed: {', '.join(TASKS)}")

    tasks = sorted(tasks, key=lambda t: (FAMILIES.index(family(t)), TASKS.index(t)))
    context = {
        "machine": f"{platform.processor() or platform.machine()} ({jax.devices()[0].platform})",
        "cores": devices.available_cores(),
        "jax": jax.__version__,
        "steps": args.steps,
        "repeats": args.repeats,
        "load_start": load(),
    }
    print(
        f"# {len(tasks)} tasks, N in {args.num_envs}, T={args.steps}, devices {args.devices}, load {context['load_start']}",
        flush=True,
    )
    from snac_jax.batched_step import resolve_reset

    steps = list(dict.fromkeys(resolve_reset(r) for r in args.reset))
    rows = []
    measured = {}
    for task in tasks:
        numpy_rate = measure_numpy(task, args.numpy_steps)
        print(f"{task:20s} numpy {numpy_rate:12,.0f} steps/s", flush=True)
        for requested, step in [(d, s) for d in args.devices for s in steps]:
            for num_envs in args.num_envs:
                # A point that runs on as many devices as one already measured is that point
                # (N = 1 runs on one device whatever was asked), not a second compilation.
                same = (task, num_envs, usable_devices(num_envs, requested), step)
                result = (
                    measured[same]
                    if same in measured
                    else measure_jax(task, num_envs, args.steps, requested, args.repeats, step)
                )
                measured[same] = result
                row = {
                    "task": task,
                    "num_envs": num_envs,
                    "steps_per_s": result["steps_per_s"],
                    "compile_s": result["compile_s"],
                    "numpy_steps_per_s": numpy_rate,
                    "ratio": result["steps_per_s"] / numpy_rate,
                    "devices_requested": requested,
                    "step": "step_batch",
                    "reset": step,
                    **{k: v for k, v in result.items() if k not in ("steps_per_s", "compile_s")},
                    "steps": args.steps,
                    "repeats": args.repeats,
                    "jax": jax.__version__,
                    "load": load(),
                }
                rows.append(row)
                print(
                    f"{task:20s} N={num_envs:6d} dev={row['devices']} {step:10s} {row['steps_per_s']:14,.0f} steps/s  "
                    f"compile {row['compile_s']:5.2f}s  x{row['ratio']:7.1f} numpy  rss {row['peak_rss_mb']:.0f} MB  load {row['load']}",
                    flush=True,
                )
    e2e = []
    if not args.no_e2e:
        sizes = ["--num-envs", "64", "--steps", "100"] if args.quick else []
        for requested in args.devices:
            e2e.append(time_snac_rollout(sizes + ["--devices", str(requested)]))
            print(f"{e2e[-1]['command']}: {e2e[-1]['wall_s']:.2f} s end to end", flush=True)
    context["load_end"] = load()

    json_path = args.out / "throughput.json"
    write_text(json_path, json.dumps(rows, indent=1) + "\n")
    if e2e:
        write_text(args.out / "snac_rollout_e2e.json", json.dumps(e2e, indent=1) + "\n")
    write_text(args.out / "throughput.md", markdown(rows, e2e, context))
    plots = plot(rows, args.out)
    print(f"wrote {json_path}, {args.out / 'throughput.md'}, " + ", ".join(str(p) for p in plots))
    return 0


if __name__ == "__main__":
    sys.exit(main())
