"""How a trained policy uses the landmark-placement action (SPEC §14): how many landmarks it
places, when, whether on design cells, and where on the plan.

    python bench/landmark_use.py --run runs/table/landmark-action/ppo/2d-static-sparse.landmark-action --out OUT

Each training seed's greedy policy (`agents.training.trained.checkpoint_policy`; of a sweep, the seeds of
the arm `--arm` names, which a sweep requires) plays the evaluation protocol's episodes (SPEC §8):
`--episodes` on a static task's design (default 100), or on each of a dynamic task's ten test
designs (default 20), with the run's switches and the report key (`REPORT_EVAL_SEED`) unless
`--eval-seed` says otherwise. The episodes are those `evaluate_task` runs with the same key and
counts (`snac_jax.evaluation.protocol_episodes`: the same designs and episode keys; the same loop,
`snac_jax.episodes.run_to_end`), so the final IoUs here equal the protocol's; only the policy's
placements are tallied on the way.

Writes only under `--out`: `landmark_use.json` (a summary per seed and pooled, and every
episode's placements) and `landmark_use.png` (where the landmarks landed, summed over episodes,
one panel per seed and one pooled). A static task's panels carry its design's outline; a dynamic
task's episodes have different designs, so its panels show plan positions without an outline.
A step is counted from 0: a placement at step 0 is the episode's first action.
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

from snac_jax import episodes, landmark_action, metrics  # noqa: E402
from snac_jax.cli.arguments import positive_int, seed  # noqa: E402
from snac_jax.evaluation import (
    REPORT_EVAL_SEED,
    ProtocolEpisodes,
    protocol_decide,
    protocol_episodes,
    protocol_start,  # noqa: E402
    require_episode_memory,
)
from snac_jax.tasks import make, task_spec  # noqa: E402

STATIC_EPISODES = 100
EPISODES_PER_TEST_DESIGN = 20


@struct.dataclass
class Tally:
    """One episode's placements so far. Slot i is the i-th placement that landed (step -1: none)."""

    attempts: jax.Array  # int32, steps whose action was the placement, landed or not
    steps: jax.Array  # int32 (K,), the step each placement was taken at
    rows: jax.Array  # int32 (K,), plan row of the cell it landed on
    cols: jax.Array  # int32 (K,)
    on_design: jax.Array  # bool (K,), the cell is a design cell of the design in force then


def empty_tally(k: int) -> Tally:
    minus = jnp.full((k,), -1, jnp.int32)
    return Tally(jnp.zeros((), jnp.int32), minus, minus, minus, jnp.zeros((k,), bool))


def tally_step(config, tally: Tally, state, action) -> Tally:
    """`tally` after `action` is taken in `state` (the state before the step).

    Whether it lands is `landmark_action.place` applied to that state: a placement does not move
    the robot or change the grid, so the state before the step has the cell it lands on and
    the cell's brick and landmark, and the env's own rule decides."""
    attempt = action == config.place_landmark_action
    landed = landmark_action.place(config, state, action).landmarks_left < state.landmarks_left
    slot = config.landmark_action - state.landmarks_left  # placements landed before this one
    row, col = state.position[0], state.position[1]

    def fill(values, value):
        return values.at[slot].set(jnp.where(landed, value, values[slot]), mode="drop")

    return Tally(
        attempts=tally.attempts + attempt.astype(jnp.int32),
        steps=fill(tally.steps, state.time),
        rows=fill(tally.rows, row),
        cols=fill(tally.cols, col),
        on_design=fill(tally.on_design, state.design[row, col] > 0),
    )


@struct.dataclass
class LandmarkEpisodes:
    """Per-episode outcomes (leading axis: episodes)."""

    iou: jax.Array  # float32, final IoU
    length: jax.Array  # int32, steps taken
    placed: jax.Array  # int32, K - landmarks_left at the end: the env's own count
    new_cells: jax.Array  # bool plan-shaped, landmark cells at the end that were none at reset
    design_index: jax.Array  # int32
    tally: Tally


@partial(jax.jit, static_argnames=("env", "init", "act"))
def _rollout(env, init, act, policy_params, env_params, keys, design_indices) -> LandmarkEpisodes:
    """The protocol's episodes (`protocol_start`, `protocol_decide`), tallying placements on the way."""
    config = env.config
    (h, w), (pr, pc) = config.plan_shape, config.pad

    decide = protocol_decide(
        act, policy_params, lambda episode, action, tally: tally_step(config, tally, episode.state, action)
    )

    def run(key, design_index):
        first = protocol_start(env, env_params, init, key, design_index, empty_tally(config.landmark_action))
        final, state = episodes.run_to_end(env, env_params, decide, first), first.state
        new = final.state.landmarks & ~state.landmarks
        return LandmarkEpisodes(
            iou=metrics.iou(final.state),
            length=final.state.time,
            placed=config.landmark_action - final.state.landmarks_left,
            new_cells=new[pr : pr + h, pc : pc + w],
            design_index=design_index,
            tally=final.agent[2],
        )

    return jax.vmap(run)(keys, design_indices)


def run_landmark_episodes(env, policy, setup: ProtocolEpisodes) -> LandmarkEpisodes:
    """The protocol's episodes `setup` (`protocol_episodes`), all in one jitted, vmapped call
    (host arrays back)."""
    if not env.config.landmark_action:
        raise ValueError("the env has no landmark placement action: make it with landmark_action=K (SPEC §14)")
    require_episode_memory(env, setup.params, policy, setup.num_episodes)
    indices = jnp.asarray(setup.design_indices)
    return jax.device_get(_rollout(env, policy.init, policy.act, policy.params, setup.params, setup.keys, indices))


def run_indices(run: Path, swept, seeds: int, arm: int | None, seed_index: int | None) -> list[tuple[int, int]]:
    """`(seed, index into the run's trained policies)` for each policy analysed: every seed of the
    run, or of `arm` of the sweep `swept` (arm a, seed s is index a * seeds + s), or the one
    `seed_index`. `swept`: `agents.training.sweep.load(run)`, None for a run of one arm.

    A sweep's arms are different settings, so pooling them would describe no one policy: a sweep
    needs `--arm`, and a run of one arm refuses it."""
    if swept is None and arm is not None:
        raise ValueError(f"--arm {arm} given, but {run} is not a sweep (it trained one arm): leave --arm out")
    if swept is not None and (arm is None or not 0 <= arm < swept.num_arms):
        got = "none given" if arm is None else f"got {arm}"
        raise ValueError(f"{run} is a sweep of {swept.num_arms} arms: --arm must be in 0..{swept.num_arms - 1} ({got})")
    if seed_index is not None and not 0 <= seed_index < seeds:
        raise ValueError(f"--seed-index must be in 0..{seeds - 1} for {run}, got {seed_index}")
    first = 0 if arm is None else arm * seeds
    return [(s, first + s) for s in (range(seeds) if seed_index is None else [seed_index])]


# --- what is reported ----------------------------------------------------------------------------


def _mean(values) -> float | None:
    values = np.asarray(values, np.float64)
    return float(values.mean()) if values.size else None


def episode_rows(result: LandmarkEpisodes, names: list[str]) -> list[dict]:
    rows = []
    for i in range(result.iou.shape[0]):
        t = jax.tree.map(lambda x: np.asarray(x[i]), result.tally)
        used = t.steps >= 0
        rows.append(
            {
                "design": names[int(result.design_index[i])],
                "iou": float(result.iou[i]),
                "length": int(result.length[i]),
                "attempts": int(t.attempts),
                "placed": int(result.placed[i]),
                "steps": t.steps[used].tolist(),
                "cells": np.stack([t.rows[used], t.cols[used]], 1).tolist(),
                "on_design": t.on_design[used].tolist(),
            }
        )
    return rows


def summarize(rows: list[dict], k: int) -> dict:
    """The per-seed (or pooled) numbers from `episode_rows`."""
    placed = np.array([r["placed"] for r in rows])
    iou = np.array([r["iou"] for r in rows])
    on_design = [flag for r in rows for flag in r["on_design"]]
    firsts = [r["steps"][0] for r in rows if r["steps"]]
    used = placed > 0
    return {
        "episodes": len(rows),
        "mean_iou": _mean(iou),
        "mean_placed": _mean(placed),
        "mean_attempts": _mean([r["attempts"] for r in rows]),
        "fraction_with_placement": _mean(used),
        "placements": int(placed.sum()),
        "fraction_on_design": _mean(on_design),
        "mean_first_step": _mean(firsts),
        "iou_with_placement": {"mean": _mean(iou[used]), "episodes": int(used.sum())},
        "iou_without_placement": {"mean": _mean(iou[~used]), "episodes": int((~used).sum())},
        "placed_histogram": np.bincount(placed, minlength=k + 1).tolist(),
    }


def plot_heatmaps(maps: dict[str, np.ndarray], outline: np.ndarray | None, title: str, path: Path) -> None:
    """One panel per entry of `maps` (plan-shaped counts), the design's outline on each if given."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from snac_jax.atomic import atomic_write

    fig, axes = plt.subplots(1, len(maps), figsize=(3.6 * len(maps) + 0.6, 3.8), squeeze=False)
    for ax, (name, counts) in zip(axes[0], maps.items()):
        image = ax.imshow(counts, cmap="magma", interpolation="nearest", vmin=0, vmax=max(1, int(counts.max())))
        if outline is not None and outline.any():
            ax.contour(outline.astype(float), levels=[0.5], colors="cyan", linewidths=1.2)
        ax.set_title(f"{name}: {int(counts.sum())} landmarks", fontsize="small")
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04)
    fig.suptitle(title, fontsize="small")
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    plt.close(fig)


# --- the command ---------------------------------------------------------------------------------


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--run", type=Path, required=True, help="a `snac train` run directory trained with landmark_action"
    )
    parser.add_argument("--out", type=Path, required=True, help="directory for landmark_use.json and landmark_use.png")
    parser.add_argument(
        "--seed-index",
        type=int,
        default=None,
        help="one training seed (default: every seed of the run, or of its --arm)",
    )
    parser.add_argument(
        "--arm",
        type=int,
        default=None,
        help="the arm of a sweep run to analyse (required for a sweep; a run of one arm has none)",
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
        default=REPORT_EVAL_SEED,
        help=f"evaluation key (default {REPORT_EVAL_SEED}, the report key)",
    )
    return parser.parse_args(argv)


def analyse(args: argparse.Namespace) -> dict:
    from agents.training import sweep, trained
    from agents.training.checkpoint import read_config
    from snac_jax.atomic import atomic_write_json, check_writable
    from snac_jax.tasks import parse_switches

    config = read_config(args.run)
    k = parse_switches(config.switches).get("landmark_action", 0)
    if not k:
        raise ValueError(
            f"{args.run} was trained without landmark_action (switches {config.switches!r}): "
            "its policy has no placement action to analyse"
        )
    swept = sweep.load(args.run)
    indices = run_indices(args.run, swept, config.seeds, args.arm, args.seed_index)
    json_path = check_writable(args.out / "landmark_use.json", "--out")
    dynamic = task_spec(config.task).dynamic
    count = args.episodes or (EPISODES_PER_TEST_DESIGN if dynamic else STATIC_EPISODES)
    env, params = make(config.task, **config.env_overrides)
    setup = protocol_episodes(
        config.task, params, args.eval_seed, static_episodes=count, episodes_per_test_design=count
    )
    names = list(setup.names)
    seeds, maps, rows_all = {}, {}, []
    shared = None  # the seeds of one arm share the network: the first's functions compile once for all
    for seed_number, index in indices:
        policy = trained.checkpoint_policy(env, args.run, index)
        if shared is None:
            shared = policy
        else:
            policy = policy._replace(init=shared.init, act=shared.act)
        result = run_landmark_episodes(env, policy, setup)
        if not np.array_equal(np.asarray(result.placed), (np.asarray(result.tally.steps) >= 0).sum(1)):
            raise AssertionError("the tally of landed placements disagrees with the env's landmarks_left")
        rows = episode_rows(result, names)
        rows_all += rows
        seeds[str(seed_number)] = {**summarize(rows, k), "episodes_detail": rows}
        maps[f"seed {seed_number}"] = np.asarray(result.new_cells).sum(0)
        print(
            f"seed {seed_number}: {seeds[str(seed_number)]['mean_placed']:.2f} placed per episode, "
            f"IoU {seeds[str(seed_number)]['mean_iou']:.3f}",
            file=sys.stderr,
        )
    if len(maps) > 1:
        maps["pooled"] = sum(maps.values())
    outline = None if dynamic else np.asarray(setup.params.designs[0]) > 0
    report = {
        "run": str(args.run),
        "task": config.task,
        "algorithm": config.algorithm,
        "switches": config.switches,
        "arm": args.arm,
        "arm_settings": None if swept is None else swept.arm_settings(args.arm),
        "landmark_action": k,
        "eval_seed": args.eval_seed,
        "episodes_per_design": count,
        "designs": names,
        "step_origin": 0,
        "on_design": "against the design in force at the placement's step",
        "heatmap": "landmark cells per plan position, summed over episodes; "
        + ("outline: the task's design" if outline is not None else "no outline: designs vary by episode"),
        "pooled": summarize(rows_all, k),
        "seeds": seeds,
    }
    atomic_write_json(json_path, report)
    arm = "" if swept is None else f", arm {args.arm} ({swept.label(args.arm)})"
    title = f"{config.algorithm} on {config.task} ({config.switches}){arm}, eval seed {args.eval_seed}"
    plot_heatmaps(maps, outline, title, args.out / "landmark_use.png")
    return report


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        report = analyse(args)
    except ValueError as error:
        print(f"landmark_use.py: error: {error}", file=sys.stderr)
        return 2
    pooled = report["pooled"]
    print(
        f"{pooled['episodes']} episodes: {pooled['mean_placed']:.2f} landmarks placed per episode, "
        f"{pooled['fraction_with_placement']:.0%} of episodes place one; wrote {args.out}/landmark_use.json, "
        f"{args.out}/landmark_use.png"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
