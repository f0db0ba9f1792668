"""`snac train ALGORITHM`: train an agent end-to-end on device, then score it with the protocol.

Plugged into the `snac` command through the `snac_jax.commands` entry point. Every field of an
algorithm's config (`agents.training.config.option`) becomes a flag of its sub-subcommand, with the field's
type, bounds and help: nothing here lists hyperparameters. Each run writes `DIR/config.json`,
`DIR/metrics.jsonl`, `DIR/checkpoints/`, `DIR/curve.png`, and after the evaluation protocol
`DIR/eval.json` (the evaluator's format; one row per seed when several).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import shlex
import sys
import time
from pathlib import Path

from snac_jax.cli.arguments import add_devices_argument, add_process_arguments, positive_int, task_id
from snac_jax.tasks import TASKS

DEFAULT_TASK = "1d-static-sin"


def flag_type(spec):
    """An argparse type that parses a field's value and checks it against its declaration."""

    def parse(text: str):
        try:
            value = spec.kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {spec.describe()}, got {text!r}") from None
        try:
            spec.check(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {spec.describe()}, got {text!r}") from None
        return value

    parse.__name__ = spec.describe()
    return parse


def add_config_flags(parser: argparse.ArgumentParser, config_cls) -> tuple[str, ...]:
    """One flag per command-line field of `config_cls`; returns the field names."""
    from agents.training.config import field_specs

    names = []
    for spec in field_specs(config_cls).values():
        if not spec.cli:
            continue
        flag = "--" + spec.name.replace("_", "-")
        help_text = f"{spec.help} (default: tuned per task, else {spec.default!r})"
        if spec.kind is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=help_text)
        else:
            parser.add_argument(
                flag, type=flag_type(spec), default=None, metavar=spec.kind.__name__.upper(), help=help_text
            )
        names.append(spec.name)
    return tuple(names)


def add_parser(subparsers) -> None:
    from agents.training.registry import ALGORITHMS, config_class
    from agents.training.trackers import TRACKERS

    parser = subparsers.add_parser("train", help="train an agent end-to-end on device, then evaluate it")
    algorithms = parser.add_subparsers(dest="algorithm", required=True)
    for name, entry in ALGORITHMS.items():
        sub = algorithms.add_parser(name, help=entry.summary)
        sub.add_argument(
            "--task", type=task_id, default=None, help=f"default {DEFAULT_TASK}; one of: {', '.join(TASKS)}"
        )
        sub.add_argument(
            "--out", type=Path, default=None, help="run directory (default runs/<algorithm>-<task>-<time>)"
        )
        sub.add_argument(
            "--resume",
            type=Path,
            default=None,
            metavar="DIR",
            help="continue the run in DIR as its config.json describes (only --eval-episodes, --[no-]eval, "
            "--no-progress, --log and --devices may be given; the first two default to the run's own)",
        )
        sub.add_argument(
            "--eval-episodes",
            type=positive_int,
            default=None,
            help="episodes per design for the final evaluation (default: the paper's protocol)",
        )
        sub.add_argument(
            "--eval",
            dest="no_eval",
            action="store_false",
            default=None,
            help="run the final evaluation (the default; on --resume, even if the run was started without)",
        )
        sub.add_argument("--no-eval", dest="no_eval", action="store_true", help="skip the final evaluation")
        sub.add_argument("--no-progress", action="store_true", help="no progress bar")
        sub.add_argument(
            "--log",
            choices=tuple(TRACKERS),
            default=None,
            help="also send each chunk's metrics (as in metrics.jsonl) to TensorBoard (DIR/tensorboard/) "
            "or wandb (the [wandb] extra; WANDB_MODE=offline keeps it on disk)",
        )
        sub.add_argument(
            "--sweep",
            action="append",
            default=None,
            metavar="NAME=V1,V2",
            help="train every value (the grid of all --sweep options, x --seeds) in one compiled program; "
            "each arm's config, metrics and evaluation under DIR/arms/<i>/; float settings only",
        )
        add_devices_argument(sub, cpu_default="1, measured faster for training")
        add_process_arguments(sub)
        options = add_config_flags(sub, config_class(name))
        sub.set_defaults(func=run_command, config_options=options)


def build_config(args: argparse.Namespace):
    from agents.training.registry import make_config

    options = {name: getattr(args, name) for name in args.config_options}
    return make_config(args.algorithm, args.task or DEFAULT_TASK, **options)


RUN_OPTIONS = ("eval_episodes", "no_eval")
"""Options of `snac train` kept with the run (`run.json`): a resume uses them unless given again."""


def _options_fixed_by_the_run(args: argparse.Namespace) -> list[str]:
    """The flags given with --resume that the run's config.json already decides."""
    names = ["task", "out", "sweep", *args.config_options]
    return ["--" + name.replace("_", "-") for name in names if getattr(args, name) is not None]


def training_memory_bytes(algorithm) -> int:
    """An estimate of the device memory a run needs, from shapes alone: the seed-batched runner
    state twice (a chunk's input and output), and the rollout batch of one update three times
    (the batch, its shuffled minibatches, their gradients) when the algorithm has PPO's
    `rollout(state, env_params) -> (state, batch, stats)`."""
    import jax

    from agents.training.driver import seed_keys
    from snac_jax.memory import tree_bytes

    init = jax.vmap(algorithm.init)
    state = jax.eval_shape(init, seed_keys(algorithm.config))
    needed = 2 * tree_bytes(state)
    rollout = getattr(algorithm, "rollout", None)
    if rollout is not None:
        try:
            batch = jax.eval_shape(jax.vmap(rollout, in_axes=(0, None)), state, algorithm.env_params)[1]
        except (TypeError, ValueError, IndexError):  # a `rollout` of another form than PPO's
            batch = None
        needed += 3 * tree_bytes(batch)
    return needed


def _require_evaluation_memory(algorithm, episodes: int | None) -> None:
    """The final evaluation's episodes must fit too (its policy state is small beside a world)."""
    from snac_jax.designs import NUM_TEST_DESIGNS
    from snac_jax.evaluation import EPISODES_PER_TEST_DESIGN, STATIC_EPISODES, require_episode_memory
    from snac_jax.policy import uniform_random_policy

    env = getattr(algorithm, "env", None)
    if env is None:
        return
    if env.config.dynamic:
        count = NUM_TEST_DESIGNS * (episodes or EPISODES_PER_TEST_DESIGN)
    else:
        count = episodes or STATIC_EPISODES
    require_episode_memory(env, algorithm.env_params, uniform_random_policy(env.num_actions), count)


def run_command(args: argparse.Namespace) -> int:
    """`run`, with Ctrl-C answered by one line: what the run directory keeps and the command that
    resumes it (the driver lets a chunk's checkpoint finish first), and exit status 130."""
    args.run_directory = None
    try:
        return run(args)
    except KeyboardInterrupt:
        import jax

        if jax.process_index() == 0:
            print(interruption_message(args.algorithm, args.run_directory), file=sys.stderr)
        return 130


def interruption_message(algorithm: str, out_dir: Path | None) -> str:
    """One line on a run interrupted while `snac train` worked on `out_dir` (None: not chosen yet)."""
    from agents.training import checkpoint
    from agents.training.driver import chunk_sizes

    said = f"snac train {algorithm}: interrupted"
    if out_dir is None or not (out_dir / checkpoint.CONFIG_FILE).is_file():
        return f"{said} before the run started; nothing to resume (start it again)"
    command = f"snac train {algorithm} --resume {shlex.quote(str(out_dir))}"
    try:
        config = checkpoint.read_config(out_dir)
        total = len(chunk_sizes(config.num_updates, config.chunks))
        last = checkpoint.latest_chunk(out_dir)
    except ValueError:
        return f"{said}; continue the run with: {command}"
    if last is None:
        return f"{said} before its first checkpoint; the run is resumable from its start: {command}"
    if last + 1 >= total:
        return f"{said} after training (all {total} chunks checkpointed); the run is resumable: {command}"
    return f"{said}; {last + 1} of {total} chunks are done and checkpointed, and the run is resumable: {command}"


def run(args: argparse.Namespace) -> int:
    import jax

    from agents.training import checkpoint, sweep, trackers
    from agents.training.driver import read_metrics, train
    from agents.training.plotting import plot_curve
    from agents.training.registry import build_algorithm
    from agents.training.sharding import host_value, training_mesh
    from snac_jax import devices, memory

    resume = args.resume is not None
    given = {"eval_episodes": args.eval_episodes, "no_eval": args.no_eval}
    trackers.check(args.log)  # before any work
    if resume:
        fixed = _options_fixed_by_the_run(args)
        if fixed:
            raise ValueError(
                f"--resume continues the run as {args.resume / checkpoint.CONFIG_FILE} describes; "
                f"{', '.join(fixed)} cannot change it (start a new run in a new directory instead)"
            )
        out_dir = args.resume
        config = checkpoint.read_config(out_dir)
        if config.algorithm != args.algorithm:
            raise ValueError(f"{out_dir} holds a {config.algorithm} run, not {args.algorithm}")
        stored = checkpoint.read_run_options(out_dir)
        options = {name: given[name] if given[name] is not None else stored.get(name) for name in RUN_OPTIONS}
        swept = sweep.load(out_dir, config)
    else:
        config = build_config(args)
        swept = _parse_sweep(args, config)
        kind = "-rnn" if getattr(config, "recurrent", False) else ""
        out_dir = args.out or Path("runs") / f"{config.algorithm}{kind}-{config.task}-{time.strftime('%Y%m%d-%H%M%S')}"
        if jax.process_index() == 0:
            checkpoint.check_new_run_directory(out_dir)  # before any work
        options = given
    args.run_directory = out_dir  # what an interruption names (`run_command`)
    options["no_eval"] = bool(options["no_eval"])
    steps = config.num_updates * config.steps_per_update
    rounded = (
        ""
        if steps == config.total_steps
        else (f" (total_steps {config.total_steps:,} rounded to whole updates of {config.steps_per_update:,})")
    )
    arms = 1 if swept is None else swept.num_arms
    grid = "" if swept is None else f" x {arms} arms ({', '.join(swept.names)})"
    print(
        f"{config.algorithm} on {config.task}: {steps:,} env steps{rounded} x {config.seeds} seed(s){grid}, "
        f"{config.num_envs} worlds; writing {out_dir}",
        file=sys.stderr,
    )

    algorithm = build_algorithm(config)
    describe = getattr(algorithm, "describe_memory", None)  # replay learners: say the buffer's size
    if describe is not None:
        print(describe(), file=sys.stderr)
    memory.require(
        f"training {config.seeds} seed(s){grid} x {config.num_envs:,} worlds",
        arms * training_memory_bytes(algorithm),
        "use fewer worlds (--num-envs), shorter rollouts, fewer seeds or fewer arms",
    )
    if not options["no_eval"]:
        _require_evaluation_memory(algorithm, options["eval_episodes"])  # now, not after the training
    mesh = training_mesh(args.devices, config.num_envs)
    devices.check_divisible(config.num_envs, mesh)
    print(f"worlds split over {mesh.devices.size} {mesh.devices.flat[0].platform} device(s)", file=sys.stderr)
    writer = jax.process_index() == 0  # across processes, process 0 writes the run directory
    with checkpoint.lock_run(out_dir) if writer else contextlib.nullcontext():
        algorithm, state = train(
            config,
            out_dir,
            resume=resume,
            progress=not args.no_progress,
            mesh=mesh,
            run_options=None if resume else options,
            swept=swept,
            log=args.log,
        )
        if not writer:
            return 0
        if resume:
            checkpoint.write_run_options(out_dir, options)
        state = state.replace(params=host_value(state.params))
        if swept is not None:
            evaluate_sweep(config, swept, state, out_dir, None if options["no_eval"] else options)
            return 0
        config = algorithm.config
        kind = " (recurrent)" if getattr(config, "recurrent", False) else ""
        plot_curve(
            read_metrics(out_dir), config.task, f"{config.algorithm}{kind} on {config.task}", out_dir / "curve.png"
        )
        print(f"wrote {out_dir / 'curve.png'}", file=sys.stderr)
        if not options["no_eval"]:
            evaluate_run(algorithm, state, out_dir, options["eval_episodes"])
    return 0


def _parse_sweep(args: argparse.Namespace, config):
    """The run's grid from `--sweep` (None without one), refused in one line where a value would
    change shapes or is also given as its own flag; traced once to check the learner takes it."""
    from agents.training.sweep import check_traceable, parse_sweep

    if not args.sweep:
        return None
    swept = parse_sweep(args.sweep, config)
    both = [name for name in swept.names if getattr(args, name, None) is not None]
    if both:
        flag = "--" + both[0].replace("_", "-")
        raise ValueError(f"{flag} and --sweep {both[0]}=... both set {both[0]}; give it once")
    check_traceable(config, swept)
    return swept


def evaluate_sweep(config, swept, state, out_dir: Path, options: dict | None) -> None:
    """Each arm's curve and, with `options`, its evaluation under `arms/<i>/`, then one table of
    the arms (the mean over seeds of the protocol's mean IoU)."""
    import jax
    import numpy as np

    from agents.training.driver import read_metrics
    from agents.training.plotting import plot_curve
    from agents.training.registry import build_algorithm
    from agents.training.sweep import arm_dir

    rows = []
    for arm in range(swept.num_arms):
        arm_config, directory = swept.arm_config(config, arm), arm_dir(out_dir, arm)
        runs = slice(arm * config.seeds, (arm + 1) * config.seeds)
        plot_curve(
            read_metrics(directory),
            config.task,
            f"{config.algorithm} on {config.task}: {swept.label(arm)}",
            directory / "curve.png",
        )
        if options is None:
            continue
        print(f"\n## arm {arm}: {swept.label(arm)}")
        arm_state = state.replace(params=jax.tree.map(lambda x: x[runs], state.params))
        results = evaluate_run(build_algorithm(arm_config), arm_state, directory, options["eval_episodes"])
        means = [r.mean for r in results]
        rows.append(f"| {arm} | {swept.label(arm)} | {', '.join(f'{m:.3f}' for m in means)} | {np.mean(means):.3f} |")
    print(f"wrote {out_dir / 'arms'}/<i>/curve.png for {swept.num_arms} arms", file=sys.stderr)
    if rows:
        print(f"\n## {swept.num_arms} arms, greedy mean IoU (tuning key)\n")
        print("| arm | settings | per seed | mean |\n|---:|---|---|---:|\n" + "\n".join(rows))


def evaluate_run(
    algorithm, state, out_dir: Path, episodes: int | None, seed: int | None = None, counts: dict[str, int] | None = None
) -> list:
    """The protocol on each seed's greedy policy: table on stdout, `out_dir/eval.json`. `seed` is
    the evaluation key (default `TUNING_EVAL_SEED`; `snac table` reports with `REPORT_EVAL_SEED`);
    `counts` (`static_episodes`, `episodes_per_test_design`) replaces `episodes` where given."""
    import jax

    from agents.training.driver import divergence_note, read_metrics
    from snac_jax.atomic import atomic_write_json
    from snac_jax.evaluation import EPISODES_PER_TEST_DESIGN, STATIC_EPISODES, TUNING_EVAL_SEED, evaluate_task
    from snac_jax.paper import load_paper_results, markdown_table, paper_cell, paper_column, paper_row

    config = algorithm.config
    if counts is None:
        counts = {} if episodes is None else {"static_episodes": episodes, "episodes_per_test_design": episodes}
    overrides = config.env_overrides  # scored on the episodes it trained on
    if overrides:
        print(
            f"evaluated with the run's training settings {overrides} (the protocol's numbers assume the task's own)",
            file=sys.stderr,
        )
    results = []
    for index in range(config.seeds):
        params = jax.tree.map(lambda x: x[index], state.params)
        team = getattr(
            algorithm, "evaluate_team", None
        )  # a team of robots (agents.learners.ippo) runs its own episodes
        if team is not None:
            protocol = {"static_episodes": STATIC_EPISODES, "episodes_per_test_design": EPISODES_PER_TEST_DESIGN}
            result = team(params, **{**protocol, **counts}, seed=TUNING_EVAL_SEED if seed is None else seed)
        else:
            result = evaluate_task(
                config.task,
                algorithm.policy(params),
                **counts,
                **overrides,
                seed=TUNING_EVAL_SEED if seed is None else seed,
            )
        if config.seeds > 1:
            result = dataclasses.replace(result, task=f"{config.task} (seed {index})")
        results.append(result)
    diverged = divergence_note(read_metrics(out_dir))
    if overrides:  # the paper scored the task as it is, not with these settings (as `snac eval` says)
        paper = {}
        print(f"{config.algorithm} on {config.task}, greedy policy, with {overrides} (no paper row)")
    else:
        row = paper_row(load_paper_results(), config.paper_method)
        paper = {r.task: paper_cell(row, config.task) for r in results}
        print(
            f"{config.algorithm} on {config.task}, greedy policy; paper row: {config.paper_method} "
            f"(the paper's {paper_column(config.task)} column)"
        )
    print()
    print(markdown_table(results, paper))
    if diverged:
        print(f"\nnote: {diverged}")
    rows = {r.task: r.to_json() for r in results}
    if overrides:  # what the numbers were scored with travels with them, as `snac eval` writes it
        rows = {task: {**row, "overrides": overrides} for task, row in rows.items()}
    atomic_write_json(out_dir / "eval.json", rows)
    print(f"\nwrote {out_dir / 'eval.json'}")
    return results
