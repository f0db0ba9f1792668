"""`snac render`: record one episode of a policy as a GIF, with step, bricks and IoU on every frame.

A team is drawn as N robots in one world (`snac_jax.multi`, SPEC §13), each in its colour
(`snac_jax.rendering.robots`), its episode recorded by `snac_jax.multi.episodes.record_team_episode`:
a registered policy with `--robots N` (as `snac eval --robots`: the handcrafted ones split the plan,
`snac_jax.policies.team`), or the checkpoint of a team run (`snac train ippo --robots N`).
"""

from __future__ import annotations

import argparse
import time

from snac_jax.cli.arguments import (
    add_seed_index_argument,
    bounded_number,
    check_seed_index,
    positive_int,
    seed,
    task_id,
)
from snac_jax.tasks import TASKS


def _policy_names() -> list[str]:
    from snac_jax.policies import POLICIES

    return list(POLICIES)


def add_parser(subparsers) -> None:
    names = _policy_names()
    parser = subparsers.add_parser(
        "render",
        help="record one episode of a policy as a GIF (step, bricks and IoU in each frame)",
        description="Runs one episode (jitted) and draws every --every-th state; the last state is always drawn "
        "and held for --hold seconds.",
    )
    parser.add_argument("--task", type=task_id, required=True, help=f"one of: {', '.join(TASKS)}")
    parser.add_argument(
        "--policy",
        choices=names,
        default=None,
        help="a registered policy (default: random; with --checkpoint, the trained agent)",
    )
    parser.add_argument(
        "--checkpoint",
        default=None,
        metavar="DIR",
        help="a trained agent's checkpoint directory (a team run, snac train ippo, draws its team)",
    )
    parser.add_argument(
        "--robots",
        type=positive_int,
        default=None,
        metavar="N",
        help="with --policy: a team of N robots in one world (SPEC §13); handcrafted splits the plan among them",
    )
    add_seed_index_argument(parser)
    parser.add_argument("--out", required=True, help="the GIF to write (written atomically)")
    parser.add_argument("--seed", type=seed, default=0, help="seed of the reset, the strides and the policy")
    parser.add_argument("--max-steps", type=positive_int, default=None, help="override the task's step limit")
    parser.add_argument("--every", type=positive_int, default=1, help="draw every k-th step (default 1: all)")
    parser.add_argument("--fps", type=positive_int, default=20)
    parser.add_argument("--hold", type=float, default=1.5, help="seconds the final frame is held")
    parser.add_argument(
        "--cell", type=bounded_number(int, 4), default=None, help="pixels per cell, >= 4 (default: per dimension)"
    )
    parser.set_defaults(func=run)


def frame_indices(length: int, every: int) -> list[int]:
    """States drawn for an episode of `length` steps: 0, every, 2·every, ..., and always the last."""
    indices = list(range(0, length + 1, every))
    if indices[-1] != length:
        indices.append(length)
    return indices


def frame_bytes(env, params, cell: int | None) -> int:
    """An upper bound of one frame's bytes at `cell` pixels per cell: a frame drawn at the
    smallest cell, scaled (both sides grow in proportion to the cell; the caption does not)."""
    import jax

    from snac_jax.rendering import render
    from snac_jax.rendering.world import DEFAULT_CELL

    cell = DEFAULT_CELL[env.config.dim] if cell is None else cell
    small = render(env, env.reset(jax.random.key(0), params)[1], params, cell=4, caption=["", ""])
    return int(small.shape[0] * small.shape[1] * 3 * (cell / 4) ** 2)


def run(args: argparse.Namespace) -> int:
    import jax

    from snac_jax import make, memory, metrics
    from snac_jax.atomic import check_writable
    from snac_jax.multi.episodes import record_team_episode
    from snac_jax.policies import build_policy
    from snac_jax.recording import record_episode
    from snac_jax.rendering import render, save_gif
    from snac_jax.rendering.robots import render_robots

    if not str(args.out).lower().endswith(".gif"):
        raise ValueError(f"--out must name a .gif file, got {args.out!r}")
    if args.hold < 0:
        raise ValueError(f"--hold must be >= 0 seconds, got {args.hold}")
    if args.policy is not None and args.checkpoint is not None:
        raise ValueError("give --policy NAME or --checkpoint DIR, not both")
    if args.robots is not None and args.checkpoint is not None:
        raise ValueError("--robots goes with --policy; a checkpoint is drawn with its run's own robots")
    check_seed_index(args)
    check_writable(args.out, "--out")
    name = args.policy or (f"checkpoint {args.checkpoint}" if args.checkpoint else "random")
    overrides = {} if args.max_steps is None else {"max_steps": args.max_steps}
    robots = args.robots  # a team's robot count (None: one robot, the single-robot env)
    try:
        if args.checkpoint is not None:
            from snac_jax.plugins import load_checkpoint

            builder, run_task, _, run_overrides = load_checkpoint(args.checkpoint, args.seed_index)
            if run_task != args.task:
                raise ValueError(f"it was trained on {run_task!r}, not {args.task!r}")
            run_overrides = dict(run_overrides)
            robots = run_overrides.pop("num_robots", None)
            # the run's switches (its observation and rules); the length is --max-steps'
            overrides = {**{k: v for k, v in run_overrides.items() if k != "max_steps"}, **overrides}
        if robots is None:
            env, params = make(args.task, **overrides)
            policy = build_policy(name, env) if args.checkpoint is None else builder(env)
        else:
            from snac_jax import multi
            from snac_jax.policies.team import team_policy

            env = multi.make(args.task, num_robots=robots, **overrides)
            params = env.default_params
            policy = team_policy(name, env) if args.checkpoint is None else builder(env)
    except (ValueError, FileNotFoundError) as error:
        raise ValueError(f"policy {name!r}: {error}") from error
    one_frame = frame_bytes(env if robots is None else env.single, params, args.cell)
    memory.require(f"one frame at --cell {args.cell}", one_frame, "lower --cell")

    start = time.perf_counter()
    key = jax.random.key(args.seed)
    record = record_episode if robots is None else record_team_episode
    trajectory = record(env, params, policy, key)
    episode_s = time.perf_counter() - start
    num_frames = len(frame_indices(trajectory.length, args.every))
    # the frames, and the GIF encoder's copy of them
    memory.require(
        f"{num_frames} frames at --cell {args.cell}", 2 * num_frames * one_frame, "lower --cell or raise --every"
    )

    label = policy.name if args.seed_index is None else f"{policy.name} ({builder.label})"
    start = time.perf_counter()
    frames = []
    team = "" if robots is None else f"  {robots} robots"
    for t in frame_indices(trajectory.length, args.every):
        state = trajectory.state_at(t)
        world = state if robots is None else state.world
        lines = [
            f"{args.task}  policy {label}{team}  seed {args.seed}",
            f"step {int(world.time)}  bricks {int(world.bricks_used)}/{int(world.max_bricks)}  "
            f"IoU {float(metrics.iou(world)):.3f}",
        ]
        draw = render if robots is None else render_robots
        frames.append(draw(env, state, params, cell=args.cell, caption=lines))
    durations = [1000.0 / args.fps] * len(frames)
    durations[-1] += 1000.0 * args.hold
    path = save_gif(args.out, frames, durations_ms=durations)
    draw_s = time.perf_counter() - start

    ending = "terminated" if trajectory.terminated else "truncated"
    last = trajectory.state_at(-1) if robots is None else trajectory.state_at(-1).world
    print(
        f"{args.task}, policy {label}{'' if robots is None else f', {robots} robots'}, seed {args.seed}: "
        f"{trajectory.length} steps ({ending}), {int(last.bricks_used)} bricks, final IoU {trajectory.final_iou:.4f}"
    )
    print(
        f"wrote {path} ({len(frames)} frames, {frames[0].shape[1]}x{frames[0].shape[0]} px, "
        f"{path.stat().st_size / 1024:.0f} KiB); episode {episode_s:.1f} s, drawing {draw_s:.1f} s"
    )
    return 0
