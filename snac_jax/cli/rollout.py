"""`snac rollout`: a jitted, vmapped uniform-random rollout that reports env-steps/s."""

from __future__ import annotations

import argparse
import time

from snac_jax.batched_step import RESET_STRATEGIES
from snac_jax.cli.arguments import add_devices_argument, bounded_number, positive_int, seed, task_id
from snac_jax.tasks import MAX_INT32, TASKS


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("rollout", help="jitted, vmapped uniform-random rollout; prints env-steps/s")
    parser.add_argument("--task", type=task_id, default="2d-static-dense", help=f"one of: {', '.join(TASKS)}")
    parser.add_argument("--num-envs", type=positive_int, default=4096)
    parser.add_argument(
        "--steps",
        type=bounded_number(int, 1, maximum=MAX_INT32),
        default=1000,
        help="steps per world (a scan's length: at most 2**31-1)",
    )
    parser.add_argument("--seed", type=seed, default=0)
    parser.add_argument(
        "--reset",
        choices=RESET_STRATEGIES,
        default="auto",
        help="how ended worlds are reset: loop (one by one, fast on a CPU), select (every world's "
        "fresh state, selected: fast on a GPU), auto (loop on a CPU, select elsewhere; default)",
    )
    add_devices_argument(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import jax

    from snac_jax import devices, make
    from snac_jax.batched_step import resolve_reset
    from snac_jax.rollout import random_rollout

    mesh = devices.env_mesh(args.devices, args.num_envs)
    devices.check_divisible(args.num_envs, mesh)
    env, params = make(args.task)
    key = jax.random.key(args.seed)
    start = time.perf_counter()
    reset = resolve_reset(args.reset, mesh.devices.flat[0].platform)
    compiled = random_rollout.lower(key, env, params, args.num_envs, args.steps, mesh, reset).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    stats = jax.block_until_ready(compiled(key, params))
    run_s = time.perf_counter() - start
    num_devices = mesh.devices.size
    print(
        f"task {args.task}: {args.num_envs} envs x {args.steps} steps, uniform-random policy, "
        f"{num_devices} {mesh.devices.flat[0].platform} device{'s' if num_devices > 1 else ''}, {reset} reset"
    )
    print(f"compile {compile_s:.2f} s; run {run_s:.2f} s; {args.num_envs * args.steps / run_s:,.0f} env-steps/s")
    if int(stats.episodes):
        print(
            f"episodes ended: {int(stats.episodes)}; final IoU mean {stats.iou_mean:.4f}, "
            f"min {float(stats.iou_min):.4f}, max {float(stats.iou_max):.4f}"
        )
    else:
        print("episodes ended: 0 (run more steps to finish an episode)")
    return 0
