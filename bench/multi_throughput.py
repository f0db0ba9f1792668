"""Throughput of the multi-robot environment (SPEC §13) beside the single-robot one, in one run.

    python bench/multi_throughput.py --out /tmp/multi                          # defaults below
    python bench/multi_throughput.py --out /tmp/multi --tasks 2d-static-dense --num-envs 4096
    python bench/multi_throughput.py --out /tmp/quick --quick                  # a smoke run

What is timed: one jitted `lax.scan` of `--steps` steps of `vmap(env.step)` over `--num-envs`
worlds, uniform-random actions, auto-reset included, for the single-robot env
(`snac_jax.make`) and for `snac_jax.multi.make(task, num_robots=N)`, N in `--robots`
(default 1 2 4; 1D tasks hold at most 2). Every observation entry is summed into the scan's
carry, so the observations are computed as a learner would pay for them (a random policy that
ignored them would let XLA drop their computation). Each point is the median of `--repeats`
timed calls after one warm-up call; compilation is timed on its own.

env-steps/s counts world-steps (one per world per step, whatever N); robot-steps/s counts
env-steps times N, the actions taken. The single-robot env's env-steps and robot-steps are the
same number.

Writes only under `--out` (a directory, required): `multi_throughput.json` (the rows and the
context) and `multi_throughput.md` (the table).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.dont_write_bytecode = True  # nothing but the results is written

from bench.written import device_context, write_pair  # noqa: E402
from snac_jax.atomic import check_writable  # noqa: E402  (light: does not start JAX)
from snac_jax.cli.arguments import positive_int  # noqa: E402

DEFAULT_TASKS = ("1d-static-sin", "2d-static-dense", "2d-dynamic-dense", "3d-static-dense")
DEFAULT_ROBOTS = (1, 2, 4)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--tasks", nargs="+", default=list(DEFAULT_TASKS), help=f"task ids (default {' '.join(DEFAULT_TASKS)})"
    )
    parser.add_argument(
        "--robots",
        nargs="+",
        type=positive_int,
        default=list(DEFAULT_ROBOTS),
        help="robot counts N (default 1 2 4; counts a task's plan cannot hold are skipped)",
    )
    parser.add_argument("--num-envs", type=positive_int, default=1024, help="worlds stepped together (default 1024)")
    parser.add_argument("--steps", type=positive_int, default=500, help="steps per timed call (default 500)")
    parser.add_argument("--repeats", type=positive_int, default=3, help="timed calls per point, median reported (>= 3)")
    parser.add_argument("--quick", action="store_true", help="64 worlds, 50 steps: a smoke run")
    parser.add_argument("--out", type=Path, required=True, help="directory for multi_throughput.json and .md")
    args = parser.parse_args(argv)
    if args.repeats < 3:
        parser.error("--repeats must be >= 3 (the median of at least three timed calls)")
    if args.quick:
        args.num_envs, args.steps = 64, 50
    from snac_jax.tasks import TASKS

    unknown = [t for t in args.tasks if t not in TASKS]
    if unknown:
        parser.error(f"unknown task(s) {unknown}; allowed: {', '.join(TASKS)}")
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        for name in ("multi_throughput.json", "multi_throughput.md"):
            check_writable(args.out / name)
    except (OSError, ValueError) as error:
        parser.error(f"--out {args.out}: {error}")
    return args


def rollout(env, params, num_envs: int, num_steps: int, agents: list[str] | None):
    """A jitted function of a key: `num_steps` steps of `vmap(env.step)` over `num_envs` worlds.
    `agents` None steps a single-robot env, else the multi env with these agents."""
    import jax
    import jax.numpy as jnp

    from snac_jax.threefry import bits

    num_actions = env.num_actions

    def draw(key, count):
        return (bits(key, count) % jnp.uint32(num_actions)).astype(jnp.int32)

    reset = jax.vmap(env.reset, in_axes=(0, None))
    step = jax.vmap(env.step, in_axes=(0, 0, 0, None))

    def body(carry, key):
        state, total = carry
        key_action, key_step = jax.random.split(key)
        keys = jax.random.split(key_step, num_envs)
        if agents is None:
            obs, state, reward, terminated, truncated, _ = step(keys, state, draw(key_action, num_envs), params)
            total = total + jnp.sum(obs) + jnp.sum(reward) + jnp.sum(terminated | truncated)
        else:
            actions = draw(key_action, num_envs * len(agents)).reshape(len(agents), num_envs)
            obs, state, rewards, dones, _ = step(keys, state, {a: actions[i] for i, a in enumerate(agents)}, params)
            total = total + sum(jnp.sum(obs[a]) + jnp.sum(rewards[a]) for a in agents) + jnp.sum(dones["__all__"])
        return (state, total), None

    @jax.jit
    def run(key):
        key_reset, key_run = jax.random.split(key)
        _, state = reset(jax.random.split(key_reset, num_envs), params)
        (_, total), _ = jax.lax.scan(body, (state, jnp.zeros((), jnp.float32)), jax.random.split(key_run, num_steps))
        return total

    return run


def measure(run, num_envs: int, num_steps: int, num_robots: int, repeats: int) -> dict:
    import jax

    start = time.perf_counter()
    compiled = run.lower(jax.random.key(0)).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(jax.random.key(0)))  # warm-up
    times = []
    for repeat in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(jax.random.key(repeat + 1)))
        times.append(time.perf_counter() - start)
    env_steps = num_envs * num_steps / statistics.median(times)
    return {
        "env_steps_per_s": env_steps,
        "robot_steps_per_s": env_steps * num_robots,
        "compile_s": compile_s,
        "run_s": statistics.median(times),
    }


def markdown(rows: list[dict], context: dict) -> str:
    lines = [
        "# Multi-robot throughput (SPEC §13)",
        "",
        f"{context['machine']}; {context['backend']} ({context['device']}); jax {context['jax']}; "
        f"{context['num_envs']} worlds x {context['steps']} steps per timed call, median of {context['repeats']}. "
        "`vmap(env.step)` in a `lax.scan`, uniform-random actions, auto-reset and observations included.",
        "",
        "| task | env | env-steps/s | robot-steps/s | vs single env (env-steps) | compile s |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        single = next(r for r in rows if r["task"] == row["task"] and r["env"] == "single")
        ratio = row["env_steps_per_s"] / single["env_steps_per_s"]
        lines.append(
            f"| {row['task']} | {row['env']} | {row['env_steps_per_s'] / 1e6:.3f} M | "
            f"{row['robot_steps_per_s'] / 1e6:.3f} M | {ratio:.2f} | {row['compile_s']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    args = parse_args(argv)

    from snac_jax import make, multi

    rows = []
    for task in args.tasks:
        env, params = make(task)
        point = measure(
            rollout(env, params, args.num_envs, args.steps, None), args.num_envs, args.steps, 1, args.repeats
        )
        rows.append({"task": task, "env": "single", "num_robots": 1, **point})
        print(f"{task} single: {point['env_steps_per_s']:,.0f} env-steps/s", flush=True)
        for n in args.robots:
            if n > multi.max_robots(env.config.dim):
                continue
            team = multi.make(task, num_robots=n)
            run = rollout(team, team.default_params, args.num_envs, args.steps, team.agents)
            point = measure(run, args.num_envs, args.steps, n, args.repeats)
            rows.append({"task": task, "env": f"multi N={n}", "num_robots": n, **point})
            print(
                f"{task} N={n}: {point['env_steps_per_s']:,.0f} env-steps/s, {point['robot_steps_per_s']:,.0f} robot-steps/s",
                flush=True,
            )
    context = {**device_context(), "num_envs": args.num_envs, "steps": args.steps, "repeats": args.repeats}
    table = markdown(rows, context)
    write_pair(args.out, "multi_throughput", {"context": context, "rows": rows}, table)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
