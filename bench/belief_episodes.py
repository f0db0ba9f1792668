"""The worst episodes of a `pqn-belief` policy, drawn with the belief it held at each step.

    python bench/belief_episodes.py --run runs/x/pqn-belief/2d-dynamic-sparse --out OUT

Where a target stays out of reach, the question is whether the robot knew where it was. The
greedy policy of one training seed (`--seed-index`, default 0; of a sweep, of the arm `--arm`
names, which a sweep requires) plays the evaluation protocol's episodes (SPEC §8): `--episodes`
on a static task's design (default 50), or on each of a dynamic task's ten test designs
(default 20), with the run's switches and the report key (`REPORT_EVAL_SEED`) unless
`--eval-seed` says otherwise. They are the protocol's episodes
(`snac_jax.evaluation.protocol_episodes`: the same designs and keys), scored by the evaluator's
own `run_episodes`; the `--worst` lowest final IoUs (ties: the lower episode index) are played
again step by step with the same keys, their beliefs kept, and each replay's final IoU must equal
the evaluator's, so the drawn episode is the scored one.

At each step the belief is the one the Q head reads when the policy acts
(`PQNBelief.held_belief`): the product of its row and column marginals. The actions are the
policy's own `act`.

Writes only under `--out`, per drawn episode `worst<rank>_episode<index>.gif` (every step) and
`.png` (its last frame), and `belief_episodes.json`, which also counts how the played episodes
ended (bricks spent, step limit, stuck): a tail of early endings is told apart. It tallies every
played episode's drops too (`drop_tally`): a brick off the design is lost localisation only where
the belief that dropped it thought it on the design. A frame is the
world (`snac_jax.rendering`) beside a heat map of the belief over the plan (colour: probability
over the frame's largest; a cyan box: the true position; a green dot: the argmax), with a
caption: step, IoU so far, P(true position) under the belief, and the argmax's distance from the
truth in cells (|row difference| + |column difference|: the moves between them). Entry t of a
frame sequence (and of the JSON's per-step lists) is the world after t steps and the belief after
reading its observation: entries 0..length-1 are the beliefs that chose the episode's actions, the
last (t = length) the belief after the final observation, on which no action is taken.
"""

from __future__ import annotations

import argparse
import sys
from functools import partial
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from flax import struct  # noqa: E402

from bench.landmark_use import run_indices  # noqa: E402
from snac_jax import episodes, metrics  # noqa: E402
from snac_jax.cli.arguments import positive_int, seed  # noqa: E402
from snac_jax.evaluation import (
    REPORT_EVAL_SEED,
    protocol_decide,
    protocol_episodes,
    protocol_start,
    require_episode_memory,
    run_episodes,
)  # noqa: E402
from snac_jax.state import EnvState  # noqa: E402
from snac_jax.tasks import make, task_spec  # noqa: E402

ALGORITHM = "pqn-belief"
STATIC_EPISODES = 50
EPISODES_PER_TEST_DESIGN = 20
WORST = 3
TRUTH = (0, 220, 255)  # the box around the true position on the heat map
ARGMAX = (40, 230, 40)  # the dot on the belief's argmax: green, seen on dark and pale cells
# magma-like anchors from no belief to the frame's largest: dark, purple, orange, pale yellow
HEAT_ANCHORS = np.array([[0, 0, 4], [80, 18, 123], [183, 55, 121], [252, 137, 97], [252, 253, 191]], np.float64)


@struct.dataclass
class Recorded:
    """Played episodes (leading axis: episodes); index t of a step axis is after t steps."""

    states: EnvState  # (episodes, max_steps + 1, ...), cut at each episode's length when drawn
    beliefs: jax.Array  # float32 (episodes, max_steps + 1, rows, cols), the belief after reading obs t
    iou: jax.Array  # float32, final IoU
    length: jax.Array  # int32, steps taken


@partial(jax.jit, static_argnames=("env", "init", "act", "held", "num_steps"))
def _record(env, init, act, held, policy_params, env_params, keys, design_indices, num_steps: int) -> Recorded:
    """The protocol's episodes (`protocol_start`, `protocol_decide`), in a scan of `num_steps`
    steps (the step limit) that keeps every state, with the belief `held` reads before each action
    kept in the agent's state at the step's index."""
    config = env.config
    rows, cols = config.plan_shape

    def keep_belief(episode: episodes.Episode, action, beliefs):
        return beliefs.at[episode.state.time].set(held(policy_params, episode.agent[1], episode.obs))

    decide = protocol_decide(act, policy_params, keep_belief)

    def run(key, design_index):
        beliefs = jnp.zeros((num_steps + 1, rows, cols), jnp.float32)
        first = protocol_start(env, env_params, init, key, design_index, beliefs)
        state = first.state
        final, states = episodes.scan_episode(
            env, env_params, decide, first, num_steps=num_steps, record=lambda step: step.state
        )
        _, policy_state, beliefs = final.agent
        beliefs = beliefs.at[final.state.time].set(held(policy_params, policy_state, final.obs))
        states = jax.tree.map(lambda s, rest: jnp.concatenate([s[None], rest]), state, states)
        return Recorded(states=states, beliefs=beliefs, iou=metrics.iou(final.state), length=final.state.time)

    return jax.vmap(run)(keys, design_indices)


def worst_episodes(iou: np.ndarray, count: int) -> np.ndarray:
    """Indices of the `count` lowest IoUs, lowest first; among equal IoUs the lower index first."""
    return np.argsort(np.asarray(iou), kind="stable")[:count]


def episode_endings(length, bricks_used, max_bricks, max_steps: int) -> dict[str, int]:
    """How many episodes ended each way (SPEC §4-5), from per-episode steps taken, bricks laid and
    the design's brick budget: its bricks spent (terminated), else the step limit (truncated),
    else stuck (terminated with bricks and steps left: the obstacle rule's only other ending).
    Fixed budgets only: a design changed within the episode (SPEC §15) moves its budget."""
    spent = np.asarray(bricks_used) >= np.asarray(max_bricks)
    limit = ~spent & (np.asarray(length) >= max_steps)
    return {"bricks spent": int(spent.sum()), "step limit": int(limit.sum()), "stuck": int((~spent & ~limit).sum())}


OFF_DESIGN = 0.5  # a drop the belief itself calls off the design: P(its target is a design cell) below this
EARLY = 20  # the first steps, near the start corner where the filter knows the position
TALLY_BATCH = 50  # episodes recorded at once for the drops' tally (each keeps every state)


def episode_drops(grids, positions, bricks_used, beliefs, designs, pad, length: int) -> np.ndarray:
    """Each counted drop of one episode (SPEC §5) as a row `(step, on_design, p_design)`: the step
    it was taken at (1-based), whether its brick changed a cell the design in force fills (-1: it
    changed no cell, a 2D drop on a brick already there), and the chance the belief that chose it
    gave its target being a design cell: the belief over positions moved by the drop's offset from
    the robot (its own cell, or a neighbour in 3D), off the plan counting as off the design.
    Index t of every per-step input is after t steps."""
    rows, cols = designs.shape[1:]
    out = []
    for t in range(1, length + 1):
        if bricks_used[t] == bricks_used[t - 1]:
            continue
        changed = np.argwhere(grids[t] != grids[t - 1])
        if len(changed) == 0:
            out.append((t, -1, float("nan")))
            continue
        filled = np.zeros((rows + 2, cols + 2), bool)  # one cell of margin: a neighbour drop's offset
        filled[1:-1, 1:-1] = np.asarray(designs[t - 1]) > 0  # the design a change (SPEC §15) put in force
        cell = changed[0] - np.asarray(pad)
        d_row, d_col = (int(v) for v in cell - positions[t - 1])
        moved = filled[1 + d_row : 1 + d_row + rows, 1 + d_col : 1 + d_col + cols]
        out.append((t, int(filled[1 + cell[0], 1 + cell[1]]), float((beliefs[t - 1] * moved).sum())))
    return np.asarray(out, np.float64).reshape(-1, 3)


def drop_tally(drops: list[np.ndarray]) -> dict[str, int]:
    """The counted drops of many episodes (`episode_drops` rows): how many bricks missed the
    design, how many of those the belief itself placed off the design (`OFF_DESIGN`), how many
    fell in the first `EARLY` steps, and how many on-design drops the belief placed off it."""
    rows = np.concatenate([d for d in drops if len(d)] or [np.zeros((0, 3))])
    off, on = rows[rows[:, 1] == 0], rows[rows[:, 1] == 1]
    return {
        "drops": len(rows),
        "on a brick already there": int((rows[:, 1] == -1).sum()),
        "off the design": len(off),
        "off the design, believed off": int((off[:, 2] < OFF_DESIGN).sum()),
        f"off the design, in the first {EARLY} steps": int((off[:, 0] <= EARLY).sum()),
        "on the design, believed off": int((on[:, 2] < OFF_DESIGN).sum()),
    }


def belief_numbers(belief: np.ndarray, position) -> tuple[float, int, tuple[int, int]]:
    """(P(true position), |row| + |col| distance of the argmax from it, the argmax) of one
    plan-shaped belief; the argmax is the first largest entry in row-major order."""
    row, col = int(position[0]), int(position[1])
    top = np.unravel_index(int(np.argmax(belief)), belief.shape)
    return float(belief[row, col]), abs(int(top[0]) - row) + abs(int(top[1]) - col), (int(top[0]), int(top[1]))


# --- pictures ------------------------------------------------------------------------------------


def heat_colours(values: np.ndarray) -> np.ndarray:
    """uint8 RGB of values in [0, 1] along `HEAT_ANCHORS` (linear between anchors)."""
    x = np.clip(values, 0.0, 1.0) * (len(HEAT_ANCHORS) - 1)
    low = np.minimum(np.floor(x).astype(int), len(HEAT_ANCHORS) - 2)
    t = (x - low)[..., None]
    return np.round(HEAT_ANCHORS[low] * (1 - t) + HEAT_ANCHORS[low + 1] * t).astype(np.uint8)


def belief_panel(config, belief: np.ndarray, position, top: tuple[int, int], cell: int) -> np.ndarray:
    """The heat map of `belief` on the plan, framed by the plan's padding so that it lines up with
    the world's grid; a 1D plan's single row is drawn `4 * cell` tall."""
    from snac_jax.rendering import CAPTION_BG
    from snac_jax.rendering.draw import box, disc, upscale

    largest = float(belief.max())
    image = upscale(heat_colours(belief / largest if largest > 0 else belief), cell)
    tall = 4 if belief.shape[0] == 1 else 1
    image = np.repeat(image, tall, axis=0)
    row, col = int(position[0]), int(position[1])
    box(image, row * cell * tall, col * cell, (row + 1) * cell * tall, (col + 1) * cell, max(2, cell // 7), TRUTH)
    disc(image, top[0] * cell * tall + cell * tall // 2, top[1] * cell + cell // 2, cell * 0.22, ARGMAX)
    pr, pc = config.pad if config.dim != 1 else (0, config.pad[1])
    framed = np.empty((image.shape[0] + 2 * pr * cell, image.shape[1] + 2 * pc * cell, 3), np.uint8)
    framed[:] = CAPTION_BG
    framed[pr * cell : pr * cell + image.shape[0], pc * cell : pc * cell + image.shape[1]] = image
    return framed


def frame(env, params, state, belief: np.ndarray, design: str) -> tuple[np.ndarray, float, int]:
    """One picture: the world beside the belief's heat map, captioned; and its P(true), distance."""
    from snac_jax.rendering import DEFAULT_CELL, add_caption, caption_lines, render
    from snac_jax.rendering.draw import hstack

    cell = DEFAULT_CELL[env.config.dim]
    p_true, distance, top = belief_numbers(belief, state.position)
    world = render(env, state, params, cell=cell, caption=False)
    picture = hstack([world, belief_panel(env.config, belief, state.position, top, cell)], gap=cell)
    lines = caption_lines(env, state) + [
        f"design {design}  P(true position) {p_true:.3f}  argmax {distance} cells off",
        f"right: belief (colour / its max {float(belief.max()):.3f}), cyan box: true position, green dot: argmax",
    ]
    return add_caption(picture, lines), p_true, distance


# --- the command ---------------------------------------------------------------------------------


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a `snac train pqn-belief` run directory")
    parser.add_argument("--out", type=Path, required=True, help="directory for the GIFs, PNGs and belief_episodes.json")
    parser.add_argument("--seed-index", type=int, default=0, help="the training seed whose policy plays (default 0)")
    parser.add_argument(
        "--arm", type=int, default=None, help="the arm of a sweep run (required for a sweep; a run of one arm has none)"
    )
    parser.add_argument("--worst", type=positive_int, default=WORST, help=f"episodes drawn (default {WORST})")
    parser.add_argument(
        "--episodes",
        type=positive_int,
        default=None,
        help=f"episodes on a static design / per dynamic test design "
        f"(default {STATIC_EPISODES} / {EPISODES_PER_TEST_DESIGN})",
    )
    parser.add_argument(
        "--eval-seed",
        type=seed,
        default=REPORT_EVAL_SEED,
        help=f"evaluation key (default {REPORT_EVAL_SEED}, the report key)",
    )
    parser.add_argument("--fps", type=float, default=8.0, help="GIF frames per second (default 8)")
    return parser.parse_args(argv)


def analyse(args: argparse.Namespace) -> dict:
    from agents.training import sweep, trained
    from agents.training.checkpoint import read_config
    from agents.training.registry import build_algorithm
    from snac_jax.atomic import atomic_write_json, check_writable
    from snac_jax.rendering import save_gif, save_png

    config = read_config(args.run)
    if config.algorithm != ALGORITHM:
        raise ValueError(f"{args.run} is a {config.algorithm} run; only {ALGORITHM} runs carry a belief to draw")
    if not args.fps > 0:
        raise ValueError(f"--fps must be > 0, got {args.fps}")
    swept = sweep.load(args.run)
    [(seed_number, index)] = run_indices(args.run, swept, config.seeds, args.arm, args.seed_index)
    json_path = check_writable(args.out / "belief_episodes.json", "--out")
    dynamic = task_spec(config.task).dynamic
    count = args.episodes or (EPISODES_PER_TEST_DESIGN if dynamic else STATIC_EPISODES)
    env, params = make(config.task, **config.env_overrides)
    setup = protocol_episodes(
        config.task, params, args.eval_seed, static_episodes=count, episodes_per_test_design=count
    )
    if args.worst > setup.num_episodes:
        raise ValueError(f"--worst must be in 1..{setup.num_episodes} (the episodes played), got {args.worst}")
    policy = trained.checkpoint_policy(env, args.run, index)
    algorithm = build_algorithm(config if swept is None else swept.arm_config(config, args.arm))

    scored = jax.device_get(run_episodes(env, setup.params, policy, setup.key, setup.design_indices))
    chosen = worst_episodes(scored.iou, args.worst)
    drops, kept, drawn, batch_size = [], {}, set(chosen.tolist()), min(TALLY_BATCH, setup.num_episodes)
    require_episode_memory(env, setup.params, policy, batch_size)
    for start in range(0, setup.num_episodes, batch_size):  # every played episode's drops, against its belief
        played_here = np.arange(start, min(start + batch_size, setup.num_episodes))
        batch = np.resize(played_here, batch_size)  # a short last batch filled out with its own episodes: one compile
        played = jax.device_get(
            _record(
                env,
                policy.init,
                policy.act,
                algorithm.held_belief,
                policy.params,
                setup.params,
                setup.keys[batch],
                jnp.asarray(setup.design_indices[batch]),
                int(setup.params.max_steps_in_episode),
            )
        )
        for i, episode in enumerate(played_here.tolist()):
            one = jax.tree.map(lambda x: x[i], played)
            drops.append(
                episode_drops(
                    one.states.grid,
                    one.states.position,
                    one.states.bricks_used,
                    one.beliefs,
                    one.states.design,
                    env.config.pad,
                    int(one.length),
                )
            )
            if episode in drawn:
                kept[episode] = one  # the drawn episodes, kept from the tally's recording
    recorded = jax.tree.map(lambda *parts: np.stack(parts), *[kept[episode] for episode in chosen.tolist()])
    if not np.array_equal(np.asarray(recorded.iou), np.asarray(scored.iou)[chosen]):
        raise AssertionError(
            f"the replayed episodes {chosen.tolist()} end at IoU {np.asarray(recorded.iou).tolist()}, "
            f"the evaluator's at {np.asarray(scored.iou)[chosen].tolist()}"
        )

    rows = []
    for rank, episode in enumerate(chosen.tolist()):
        length = int(recorded.length[rank])
        design = setup.names[int(setup.design_indices[episode])]
        frames, p_true, distance = [], [], []
        for t in range(length + 1):
            state = jax.tree.map(lambda x: x[rank, t], recorded.states)
            picture, p, d = frame(env, setup.params, state, np.asarray(recorded.beliefs[rank, t], np.float64), design)
            frames.append(picture)
            p_true.append(p)
            distance.append(d)
        stem = f"worst{rank + 1}_episode{episode}"
        durations = [1000.0 / args.fps] * len(frames)
        durations[-1] = max(durations[-1], 2000.0)  # hold the last frame
        save_gif(args.out / f"{stem}.gif", frames, durations_ms=durations)
        save_png(args.out / f"{stem}.png", frames[-1])
        rows.append(
            {
                "rank": rank + 1,
                "episode": episode,
                "design": design,
                "iou": float(recorded.iou[rank]),
                "length": length,
                "gif": f"{stem}.gif",
                "png": f"{stem}.png",
                "p_true": p_true,
                "argmax_distance": distance,
            }
        )
        print(
            f"worst {rank + 1}: episode {episode} on {design}, IoU {rows[-1]['iou']:.3f}, {length} steps, "
            f"final P(true position) {p_true[-1]:.3f}",
            file=sys.stderr,
        )

    report = {
        "run": str(args.run),
        "task": config.task,
        "algorithm": config.algorithm,
        "switches": config.switches,
        "seed_index": seed_number,
        "arm": args.arm,
        "arm_settings": None if swept is None else swept.arm_settings(args.arm),
        "eval_seed": args.eval_seed,
        "episodes_per_design": count,
        "episodes_played": setup.num_episodes,
        "mean_iou": float(np.mean(scored.iou)),
        "endings": None
        if env.config.design_change is not None
        else episode_endings(
            scored.length,
            scored.bricks_used,
            np.asarray(setup.params.design_max_bricks)[np.asarray(scored.design_index)],
            int(setup.params.max_steps_in_episode),
        ),
        "drops": drop_tally(drops),
        "drops_note": f"every counted drop of the played episodes; believed off: the belief that chose it gave "
        f"its target under {OFF_DESIGN} chance of being a design cell",
        "belief": "row marginal x column marginal",
        "steps": "entry t: after t steps; entries 0..length-1 chose the actions, entry length read the final "
        "observation",
        "argmax_distance": "|row difference| + |column difference| in cells, argmax to the true position",
        "episodes": rows,
    }
    atomic_write_json(json_path, report)
    return report


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        report = analyse(args)
    except ValueError as error:
        print(f"belief_episodes.py: error: {error}", file=sys.stderr)
        return 2
    endings = report["endings"]
    ended = "" if endings is None else "; ended: " + ", ".join(f"{name} {count}" for name, count in endings.items())
    print("drops: " + ", ".join(f"{name} {count}" for name, count in report["drops"].items()))
    print(
        f"{len(report['episodes'])} of {report['episodes_played']} episodes drawn (mean IoU "
        f"{report['mean_iou']:.3f}{ended}); wrote {args.out}/belief_episodes.json and a GIF and PNG per episode"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
