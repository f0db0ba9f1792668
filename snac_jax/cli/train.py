"""`snac train ALGORITHM`: train an agent end-to-end on device, then score it with the protocol.

One sub-subcommand per algorithm (`snac train ppo ...`); they share the options of the driver
(task, budget, worlds, seeds, output directory, resume) and add their own. Each run writes
`DIR/config.json`, `DIR/metrics.jsonl`, `DIR/checkpoints/`, `DIR/curve.png`, and after the
evaluation protocol `DIR/eval.json` (the evaluator's format; one row per seed when several).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from snac_jax.cli.arguments import add_devices_argument, bounded_number, positive_int, task_id
from snac_jax.tasks import TASKS

DEFAULT_TASK = "1d-static-sin"


_positive_float = bounded_number(float, 0, strict=True)
_non_negative_float = bounded_number(float, 0)
_non_negative_int = bounded_number(int, 0)


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--task", type=task_id, default=None, help=f"default {DEFAULT_TASK}; one of: {', '.join(TASKS)}")
    parser.add_argument("--total-steps", type=positive_int, default=None, help="env steps per seed (default: tuned per task)")
    parser.add_argument("--num-envs", type=positive_int, default=None, help="parallel worlds per seed (default: tuned per task)")
    parser.add_argument("--seeds", type=positive_int, default=None, help="independent runs, vmapped (default 1)")
    parser.add_argument("--seed", type=int, default=None, help="base seed (default 0)")
    parser.add_argument("--chunks", type=positive_int, default=None, help="checkpoints/log lines over the run (default 20)")
    parser.add_argument("--out", type=Path, default=None, help="run directory (default runs/<algorithm>-<task>-<time>)")
    parser.add_argument("--resume", type=Path, default=None, metavar="DIR", help="continue the run in DIR (other options ignored)")
    parser.add_argument("--eval-episodes", type=positive_int, default=None,
                        help="episodes per design for the final evaluation (default: the paper's protocol)")
    parser.add_argument("--no-eval", action="store_true", help="skip the final evaluation")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--previous-step", action=argparse.BooleanOptionalAction, default=None,
                        help="the network also reads the previous window and its last action (default: yes)")
    add_devices_argument(parser, cpu_default="1, measured faster for training")


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser("train", help="train an agent end-to-end on device, then evaluate it")
    algorithms = parser.add_subparsers(dest="algorithm", required=True)

    ppo = algorithms.add_parser("ppo", help="PPO (feed-forward, or recurrent with --recurrent)")
    _common(ppo)
    ppo.add_argument("--recurrent", action=argparse.BooleanOptionalAction, default=None,
                     help="GRU actor-critic (default: tuned per task; recurrent on 1D)")
    ppo.add_argument("--learning-rate", type=_positive_float, default=None)
    ppo.add_argument("--rollout-steps", type=positive_int, default=None)
    ppo.add_argument("--update-epochs", type=positive_int, default=None)
    ppo.add_argument("--num-minibatches", type=positive_int, default=None)
    ppo.add_argument("--hidden-size", type=positive_int, default=None, help="encoder and head width")
    ppo.add_argument("--rnn-size", type=positive_int, default=None, help="GRU units (with --recurrent)")
    ppo.add_argument("--gamma", type=_positive_float, default=None)
    ppo.add_argument("--ent-coef", type=_non_negative_float, default=None, help="entropy coefficient (at the first update)")
    ppo.add_argument("--ent-coef-end", type=bounded_number(float, -1), default=None,
                     help="entropy coefficient at the last update, annealed linearly (default: tuned; "
                          "below 0 it pushes the policy toward its greedy version)")
    ppo.add_argument("--reward-scale", type=_positive_float, default=None, help="rewards are multiplied by this for learning")
    ppo.set_defaults(func=run, algorithm_options=("recurrent", "learning_rate", "rollout_steps", "update_epochs", "num_minibatches",
                                                  "hidden_size", "rnn_size", "gamma", "ent_coef", "ent_coef_end",
                                                  "reward_scale"))

    value_based = ("learning_rate", "rollout_steps", "gradient_steps", "batch_size", "buffer_size", "max_buffer_mb",
                   "n_step", "target_update_interval", "learning_starts", "hidden_size", "frame_stack", "max_steps")
    recurrent = ("lstm_size", "burn_in", "sequence_length")
    for name, help_text, options in (
        ("dqn", "DQN: double Q, dueling head, n-step returns, optional frame stack; replay on device", value_based),
        ("drqn", "DRQN: the DQN with an LSTM, trained on replayed sequences with burn-in", value_based + recurrent),
        ("drqn-her", "DRQN + hindsight relabelling with the episode's final grid as the design",
         value_based + recurrent + ("hindsight_fraction",)),
    ):
        sub = algorithms.add_parser(name, help=help_text)
        _common(sub)
        for option in options:
            kind = _positive_float if option in ("learning_rate", "max_buffer_mb", "hindsight_fraction") else positive_int
            if option in ("learning_starts", "burn_in", "max_steps"):
                kind = _non_negative_int
            sub.add_argument("--" + option.replace("_", "-"), type=kind, default=None)
        sub.set_defaults(func=run, algorithm_options=options)


def build_config(args: argparse.Namespace):
    from agents.config import make_config

    options = {name: getattr(args, name) for name in ("total_steps", "num_envs", "seeds", "seed", "chunks", "previous_step")}
    options.update({name: getattr(args, name) for name in args.algorithm_options})
    return make_config(args.algorithm, args.task or DEFAULT_TASK, **options)


def run(args: argparse.Namespace) -> int:
    from agents import checkpoint
    from agents.driver import build_algorithm, read_metrics, train
    from agents.plotting import plot_curve

    if args.resume is not None:
        out_dir = args.resume
        config = checkpoint.read_config(out_dir)
        if config.algorithm != args.algorithm:
            raise ValueError(f"{out_dir} holds a {config.algorithm} run, not {args.algorithm}")
    else:
        config = build_config(args)
        kind = "-rnn" if getattr(config, "recurrent", False) else ""
        out_dir = args.out or Path("runs") / f"{config.algorithm}{kind}-{config.task}-{time.strftime('%Y%m%d-%H%M%S')}"
    print(f"{config.algorithm} on {config.task}: {config.total_steps:,} env steps x {config.seeds} seed(s), "
          f"{config.num_envs} worlds; writing {out_dir}", file=sys.stderr)

    memory = getattr(build_algorithm(config), "describe_memory", None)  # replay learners: say the buffer's size
    if memory is not None:
        print(memory(), file=sys.stderr)
    from snac_jax import devices

    mesh = devices.env_mesh(args.devices, config.num_envs)
    devices.check_divisible(config.num_envs, mesh)
    print(f"worlds split over {mesh.devices.size} {mesh.devices.flat[0].platform} device(s)", file=sys.stderr)
    algorithm, state = train(config, out_dir, resume=args.resume is not None, progress=not args.no_progress, mesh=mesh)
    config = algorithm.config
    kind = " (recurrent)" if getattr(config, "recurrent", False) else ""
    plot_curve(read_metrics(out_dir), config.task, f"{config.algorithm}{kind} on {config.task}", out_dir / "curve.png")
    print(f"wrote {out_dir / 'curve.png'}", file=sys.stderr)
    if not args.no_eval:
        evaluate_run(algorithm, state, out_dir, args.eval_episodes)
    return 0


def evaluate_run(algorithm, state, out_dir: Path, episodes: int | None) -> None:
    """The protocol on each seed's greedy policy: table on stdout, `out_dir/eval.json`."""
    import jax

    from snac_jax.atomic import atomic_write_json
    from snac_jax.cli.eval import markdown_table
    from snac_jax.evaluation import evaluate_task, load_paper_results, paper_row

    config = algorithm.config
    counts = {} if episodes is None else {"static_episodes": episodes, "episodes_per_test_design": episodes}
    results = []
    for seed in range(config.seeds):
        params = jax.tree.map(lambda x: x[seed], state.params)
        result = evaluate_task(config.task, algorithm.policy(params), **counts)
        if config.seeds > 1:
            result = dataclasses.replace(result, task=f"{config.task} (seed {seed})")
        results.append(result)
    from agents.plotting import paper_column

    paper = paper_row(load_paper_results(), getattr(config, "paper_method", config.algorithm))
    paper = {r.task: paper.get(paper_column(config.task), {}) for r in results}
    print(f"{config.algorithm} on {config.task}, greedy policy; paper row: {getattr(config, 'paper_method', config.algorithm)} "
          f"(the paper's {paper_column(config.task)} column)")
    print()
    print(markdown_table(results, paper))
    atomic_write_json(out_dir / "eval.json", {r.task: r.to_json() for r in results})
    print(f"\nwrote {out_dir / 'eval.json'}")
