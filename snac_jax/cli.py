"""The `snac` command line."""

from __future__ import annotations

import argparse
import sys
import time

from snac_jax.tasks import TASKS


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an int >= 1, got {text}")
    return value


def _task(text: str) -> str:
    if text not in TASKS:
        raise argparse.ArgumentTypeError(f"unknown task {text!r}; allowed: {', '.join(TASKS)}")
    return text


def cmd_rollout(args: argparse.Namespace) -> int:
    import jax

    from snac_jax import make
    from snac_jax.rollout import random_rollout

    env, params = make(args.task)
    key = jax.random.key(args.seed)
    start = time.perf_counter()
    compiled = random_rollout.lower(key, env, params, args.num_envs, args.steps).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    stats = jax.block_until_ready(compiled(key, params))
    run_s = time.perf_counter() - start
    env_steps = args.num_envs * args.steps
    print(f"task {args.task}: {args.num_envs} envs x {args.steps} steps, uniform-random policy")
    print(f"compile {compile_s:.2f} s; run {run_s:.2f} s; {env_steps / run_s:,.0f} env-steps/s")
    print(
        f"episodes ended: {int(stats.episodes)}; final IoU mean {stats.iou_mean:.4f}, "
        f"min {float(stats.iou_min):.4f}, max {float(stats.iou_max):.4f}"
        if int(stats.episodes)
        else "episodes ended: 0 (run more steps to finish an episode)"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="snac", description="SNAC mobile-construction benchmark in JAX")
    sub = parser.add_subparsers(dest="command", required=True)

    rollout = sub.add_parser("rollout", help="jitted, vmapped uniform-random rollout; prints env-steps/s")
    rollout.add_argument("--task", type=_task, default="2d-static-dense", help=f"one of: {', '.join(TASKS)}")
    rollout.add_argument("--num-envs", type=_positive_int, default=4096)
    rollout.add_argument("--steps", type=_positive_int, default=1000)
    rollout.add_argument("--seed", type=int, default=0)
    rollout.set_defaults(func=cmd_rollout)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
