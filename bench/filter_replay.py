"""How well the mapping filter would know where the robot is, on the episodes of a trained
`pqn-belief` policy, beside the belief the policy itself held.

    python bench/filter_replay.py --run runs/x/pqn-belief/2d-dynamic-sparse --out OUT

Why: where a run trained with the mapping filter (`brick_map`) holds a poor belief, two causes
are mixed: the filter itself going wrong as bricks accumulate, and the training that the
filter's belief steers. Here the policy is fixed (the run's greedy
policy, with its own belief, plays the evaluation protocol's episodes, SPEC §8) and the mapping
filter runs beside it on exactly what the policy's filter read at each step
(`PQNBelief.filter_inputs`: the move head's distribution, the last action, the window), once per
`--weights` entry (the bricks' log-likelihood times the weight, `mapping_filter_step`'s
`evidence_weight`; 0: the padding alone, on the joint belief; `--occupancy`: the 3D map as
`brick_occupancy` keeps it). No variant acts, so every one is scored on the same steps.

Scored per variant, over every step t of every episode (t = 0 to the episode's length: the
belief after reading observation t): the mean of -log P(true position) (P floored at 1e-6),
the share of steps whose argmax is the true position, and both over the thirds of the step
limit (the bricks accumulate along an episode) and per training seed. The policy's own belief
(`held`, the product of its filter's row and column marginals, or a `brick_map` run's joint
belief) is scored the same way. Default key: the tuning key (`TUNING_EVAL_SEED`), as this
chooses a setting.

Writes only `--out`/filter_replay.json; prints a table.
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

from bench.landmark_use import run_indices  # noqa: E402
from snac_jax import episodes, metrics  # noqa: E402
from snac_jax.cli.arguments import positive_int, seed  # noqa: E402
from snac_jax.evaluation import TUNING_EVAL_SEED, protocol_decide, protocol_episodes, protocol_start  # noqa: E402
from snac_jax.tasks import make, task_spec  # noqa: E402

ALGORITHM = "pqn-belief"
WEIGHTS = (0.0, 0.03, 0.1, 0.3, 1.0)
STATIC_EPISODES = 30
EPISODES_PER_TEST_DESIGN = 3
FLOOR = 1e-6  # P(true position) below this counts as this: one lost episode does not swamp the mean
PARTS = 3  # the step limit cut into thirds


@partial(jax.jit, static_argnames=("env", "init", "act", "held", "inputs", "num_steps"))
def _record(env, init, act, held, inputs, policy_params, env_params, keys, design_indices, num_steps: int):
    """The protocol's episodes, keeping per step the filter's inputs, the true position and the
    held belief's P(true position) and argmax hit; index t holds observation t's."""
    rows, cols = env.config.plan_shape

    def at(index, tree, value):
        return jax.tree.map(lambda whole, part: whole.at[index].set(part), tree, value)

    def keep(episode: episodes.Episode, record):
        policy_state, obs, position = episode.agent[1], episode.obs, episode.state.position
        belief = held(policy_params, policy_state, obs)
        hit = jnp.argmax(belief.reshape(-1)) == position[0] * cols + position[1]
        return at(
            episode.state.time,
            record,
            (inputs(policy_params, policy_state, obs), position, belief[position[0], position[1]], hit),
        )

    decide = protocol_decide(act, policy_params, lambda episode, action, record: keep(episode, record))

    def run(key, design_index):
        first = protocol_start(env, env_params, init, key, design_index, None)
        step_shapes = jax.eval_shape(
            lambda: (
                inputs(policy_params, first.agent[1], first.obs),
                first.state.position,
                jnp.float32(0),
                jnp.bool_(False),
            )
        )
        record = jax.tree.map(lambda s: jnp.zeros((num_steps + 1,) + s.shape, s.dtype), step_shapes)
        first = first.replace(agent=first.agent[:2] + (record,))
        final = episodes.run_to_end(env, env_params, decide, first)
        record = keep(final, final.agent[2])
        return record, final.state.time, metrics.iou(final.state)

    return jax.vmap(run)(keys, design_indices)


@partial(jax.jit, static_argnames=("rows", "cols", "drops", "capped"))
def _observe(inputs, position, weight, rows: int, cols: int, drops: tuple, capped: bool):
    """The mapping filter at `weight` along each recorded episode: P(true position) and the argmax
    hit per step, `(episodes, steps)`."""
    from agents.research.belief_map import mapping_filter_step, start_joint

    def one(inputs, position):
        def step(state, x):
            (reset, p_cells, sign, last_action, window), true = x
            state = mapping_filter_step(state, reset, p_cells, sign, last_action, window, drops, capped, weight)
            belief = state[0][0]
            return state, (belief[true[0], true[1]], jnp.argmax(belief.reshape(-1)) == true[0] * cols + true[1])

        empty = jnp.zeros((1, rows, cols))
        return jax.lax.scan(step, (start_joint(rows, cols)[None], empty, empty), (inputs, position))[1]

    return jax.vmap(one)(inputs, position)


def score(p_true: np.ndarray, hit: np.ndarray, length: np.ndarray, num_steps: int) -> dict:
    """-log P(true) (floored) and the argmax hit rate over steps 0..length of each episode, in all
    and per third of the step limit (None where no episode reached that third)."""
    steps = np.arange(p_true.shape[1])[None, :]
    valid = steps <= np.asarray(length)[:, None]
    nll = -np.log(np.maximum(np.asarray(p_true, np.float64), FLOOR))
    hit = np.asarray(hit, np.float64)
    edges = np.linspace(0, num_steps + 1, PARTS + 1)

    def summary(mask):
        return (
            {"nll": float(nll[mask].mean()), "argmax_hit": float(hit[mask].mean()), "steps": int(mask.sum())}
            if mask.any()
            else None
        )

    return {
        "all": summary(valid),
        "thirds": [summary(valid & (steps >= low) & (steps < high)) for low, high in zip(edges[:-1], edges[1:])],
    }


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a `snac train pqn-belief` run with its filter")
    parser.add_argument("--out", type=Path, required=True, help="directory for filter_replay.json")
    parser.add_argument("--seed-index", type=int, default=None, help="one training seed (default: every seed)")
    parser.add_argument("--arm", type=int, default=None, help="the arm of a sweep run (required for a sweep)")
    parser.add_argument(
        "--weights",
        type=float,
        nargs="+",
        default=list(WEIGHTS),
        help=f"evidence weights of the bricks (default {' '.join(map(str, WEIGHTS))})",
    )
    parser.add_argument(
        "--occupancy",
        action="store_true",
        help="in 3D, the replayed maps hold whether a cell has a brick, not how many "
        "(pqn-belief's brick_occupancy); 2D's always do",
    )
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
        default=TUNING_EVAL_SEED,
        help=f"evaluation key (default {TUNING_EVAL_SEED}, the tuning key)",
    )
    return parser.parse_args(argv)


def replay(args: argparse.Namespace) -> dict:
    from agents.research.belief_map import drop_table
    from agents.training import sweep, trained
    from agents.training.checkpoint import read_config
    from agents.training.registry import build_algorithm
    from snac_jax.atomic import atomic_write_json, check_writable

    config = read_config(args.run)
    if config.algorithm != ALGORITHM:
        raise ValueError(f"{args.run} is a {config.algorithm} run; only {ALGORITHM} runs have a filter to replay")
    bad = [w for w in args.weights if not 0 <= w <= 10]
    if bad:
        raise ValueError(f"--weights must be in 0..10, got {bad[0]}")
    swept = sweep.load(args.run)
    indices = run_indices(args.run, swept, config.seeds, args.arm, args.seed_index)
    algorithm = build_algorithm(config if swept is None else swept.arm_config(config, args.arm))
    if not algorithm.config.belief_filter:
        raise ValueError(f"{args.run} trained the learned belief (belief_filter=false): it has no filter to replay")
    json_path = check_writable(args.out / "filter_replay.json", "--out")
    env, params = make(config.task, **config.env_overrides)
    count = args.episodes or (EPISODES_PER_TEST_DESIGN if task_spec(config.task).dynamic else STATIC_EPISODES)
    setup = protocol_episodes(
        config.task, params, args.eval_seed, static_episodes=count, episodes_per_test_design=count
    )
    rows, cols = env.config.plan_shape
    num_steps = int(setup.params.max_steps_in_episode)
    drops, capped = drop_table(env.config), env.config.dim == 2 or args.occupancy

    inputs, positions, held_p, held_hit, lengths, ious = [], [], [], [], [], []
    for _, index in indices:
        policy = trained.checkpoint_policy(env, args.run, index)
        record, length, iou = jax.device_get(
            _record(
                env,
                policy.init,
                policy.act,
                algorithm.held_belief,
                algorithm.filter_inputs,
                policy.params,
                setup.params,
                setup.keys,
                jnp.asarray(setup.design_indices),
                num_steps,
            )
        )
        (step_inputs, position, p_true, hit) = record
        inputs.append(step_inputs)
        positions.append(position)
        held_p.append(p_true)
        held_hit.append(hit)
        lengths.append(length)
        ious.append(iou)
    inputs = jax.tree.map(lambda *parts: np.concatenate(parts), *inputs)
    position, length = np.concatenate(positions), np.concatenate(lengths)

    seed_of = np.repeat([s for s, _ in indices], [len(part) for part in lengths])

    def scored(p_true, hit) -> dict:
        """`score` over every episode, and per training seed (its "all" part)."""
        per_seed = {
            str(s): score(p_true[seed_of == s], hit[seed_of == s], length[seed_of == s], num_steps)["all"]
            for s, _ in indices
        }
        return {**score(p_true, hit, length, num_steps), "per_seed": per_seed}

    variants = {"held": scored(np.concatenate(held_p), np.concatenate(held_hit))}
    for weight in args.weights:
        p_true, hit = jax.device_get(_observe(inputs, position, jnp.float32(weight), rows, cols, drops, capped))
        variants[f"mapping, weight {weight:g}"] = scored(np.asarray(p_true), np.asarray(hit))
    report = {
        "run": str(args.run),
        "task": config.task,
        "switches": config.switches,
        "brick_map": algorithm.config.brick_map,
        "occupancy": capped,
        "seed_indices": [s for s, _ in indices],
        "arm": args.arm,
        "eval_seed": args.eval_seed,
        "episodes_per_design": count,
        "episodes": int(length.size),
        "mean_iou": float(np.mean(np.concatenate(ious))),
        "mean_length": float(np.mean(length)),
        "nll": f"mean over steps 0..length of -log P(true position), P floored at {FLOOR:g}",
        "thirds": f"steps [0, {num_steps + 1}) cut into {PARTS} equal parts",
        "held": "the belief the policy read (its filter's row x column marginals, or a brick_map run's joint belief)",
        "variants": variants,
    }
    atomic_write_json(json_path, report)
    return report


def table(report: dict) -> str:
    lines = [
        "| belief | NLL | NLL per seed | argmax on the truth | per seed | NLL by third of the step limit |",
        "|---|---:|---|---:|---|---|",
    ]
    for name, row in report["variants"].items():
        thirds = ", ".join("—" if t is None else f"{t['nll']:.2f}" for t in row["thirds"])
        seeds = list(row["per_seed"].values())
        nll = ", ".join(format(s["nll"], ".2f") for s in seeds)
        hit = ", ".join(format(s["argmax_hit"], ".3f") for s in seeds)
        whole = row["all"]
        lines.append(f"| {name} | {whole['nll']:.2f} | {nll} | {whole['argmax_hit']:.3f} | {hit} | {thirds} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        report = replay(args)
    except ValueError as error:
        print(f"filter_replay.py: error: {error}", file=sys.stderr)
        return 2
    print(f"{report['episodes']} episodes (mean IoU {report['mean_iou']:.3f}, mean length {report['mean_length']:.0f})")
    print(table(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
