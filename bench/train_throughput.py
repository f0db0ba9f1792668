"""Training throughput: env steps per second of a learner *including learning* (acting,
returns, replay and updates), per task and network, with its tuned defaults
(`agents/tuned/<algorithm>.toml`, else its config class's); every learner of
`agents.training.registry.ALGORITHMS`.

    python bench/train_throughput.py --algorithm ppo --tasks 2d-static-dense 2d-dynamic-dense
    python bench/train_throughput.py --algorithm pqn-belief --tasks 3d-dynamic-sparse \
        --variant view_radius=0,design_encoder=true

`--variant` adds a row per set of settings over the tuned ones, timed in the same run as the
tuned row: what a setting costs is read as the ratio of two rows, not against another day's
number. `--design-runs both` does the same for how a sequence's design runs are encoded: a
dynamic task's row again with the accelerators' one bounded pass in place of the CPU's loop
(`agents.common.networks.runs_in_a_loop`).

Each configuration is compiled first (compile time reported apart), then timed `--repeats` times
over `--updates` updates (the median is reported), beside a baseline timed in the same run: the
same acting without learning. The load average is printed because a shared CPU skews both. A
replay learner starts learning at once (`learning_starts=0`), so every timed update learns.

To tell a slow implementation from a busy processor, each row also gives the matrix arithmetic
the learner does per env step, counted from the traced chunk (`bench/flops.py`: every matrix
product and convolution, times the trips of the scans around it, so a design encoded once per
episode counts once), as GFLOP/s at the measured rate. That is set beside the rate of a plain
float32 matrix product as wide as the recurrent core (the hidden layers for a feed-forward
network), one minibatch of rows, timed in the same run: when the two are close, the learner is
compute-bound and only less arithmetic goes faster.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # `bench.flops` when run as a script


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--algorithm",
        default="ppo",
        help="the learner to time: an algorithm id of `snac train` (checked once JAX's devices are set)",
    )
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME=VALUE[,NAME=VALUE...]",
        help="settings over the tuned ones, timed as a row more (repeatable; the tuned row is always timed)",
    )
    parser.add_argument("--tasks", nargs="+", default=["1d-static-sin", "2d-static-dense"])
    parser.add_argument("--recurrent", choices=("yes", "no", "both"), default="yes")
    parser.add_argument("--updates", type=int, default=10, help="timed updates per repeat")
    parser.add_argument(
        "--repeats", type=int, default=3, help="timed repeats per configuration (the median is reported)"
    )
    parser.add_argument("--num-envs", type=int, default=None, help="default: the tuned value per task")
    parser.add_argument("--devices", type=int, default=1, help="CPU devices (default 1, as `snac train` uses)")
    parser.add_argument("--out", default=None, help="also write the table to this Markdown file (replaced)")
    parser.add_argument(
        "--design-runs",
        choices=("default", "both"),
        default="default",
        help="both: time each dynamic task also with a sequence's design runs encoded in one bounded pass "
        "(the accelerators' way) in place of the CPU's loop, as a row more in the same run",
    )
    for option in ("hidden-size", "rnn-size", "update-epochs", "num-minibatches", "rollout-steps"):
        parser.add_argument("--" + option, type=int, default=None, help="default: the tuned value per task")
    args = parser.parse_args()
    for name in ("updates", "repeats", "devices"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    from snac_jax import atomic, devices

    if args.out:
        try:
            atomic.check_writable(args.out, "--out")
        except ValueError as error:
            parser.error(str(error))

    devices.use_cpu_devices(args.devices)  # before anything starts JAX's backend (the variants' imports do)
    from agents.training.registry import ALGORITHMS

    if args.algorithm not in ALGORITHMS:
        parser.error(f"--algorithm: unknown {args.algorithm!r}; allowed: {', '.join(ALGORITHMS)}")
    try:
        variants = [{}] + [_variant_settings(text, args.algorithm, set(vars(args))) for text in args.variant]
    except ValueError as error:
        parser.error(str(error))
    import jax

    from agents.common import networks as network_pieces
    from agents.common.networks import param_count
    from agents.training.driver import initial_state
    from agents.training.registry import build_algorithm, config_class, make_config
    from bench import flops
    from snac_jax.tasks import task_spec

    networks = {"yes": [True], "no": [False], "both": [False, True]}[args.recurrent]
    lines = []

    def emit(text: str) -> None:
        """Print a line, and keep it for --out (written as each row finishes: a killed run keeps its rows)."""
        print(text, flush=True)
        lines.append(text)
        if args.out:
            atomic.atomic_write_text(args.out, "\n".join(lines) + "\n")

    emit(
        f"{args.algorithm}; jax {jax.__version__}, {len(jax.devices())} {jax.devices()[0].platform} device(s) "
        f"({jax.devices()[0].device_kind}; {os.cpu_count()} CPU cores); "
        f"median of {args.repeats} repeats of {args.updates} updates"
    )
    emit(
        "| task | network | worlds | learning per update | params | compile s | "
        "env-steps/s with learning | acting only (same run) | learning's share of the time | "
        "network GFLOP/s (counted; ≈: a cond's costliest branch, a while loop's body once) | matmul GFLOP/s (core width, same run) | load avg |"
    )
    emit("|---|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---|")
    rows = []  # every configuration made (and so checked) before the first is compiled
    fields = {f.name for f in dataclasses.fields(config_class(args.algorithm))}
    if "recurrent" not in fields:
        networks = [None]  # a learner whose network is set by its own options (DRQN's LSTM, DQN's none)
    for task, recurrent, settings in itertools.product(args.tasks, networks, variants):
        overrides = dict(
            recurrent=recurrent,
            num_envs=args.num_envs,
            hidden_size=args.hidden_size,
            rnn_size=args.rnn_size,
            update_epochs=args.update_epochs,
            num_minibatches=args.num_minibatches,
            rollout_steps=args.rollout_steps,
            learning_starts=0,
        )
        overrides = {name: value for name, value in overrides.items() if name in fields}
        try:
            config = make_config(args.algorithm, task, **overrides, **settings)
        except ValueError as error:
            parser.error(f"{task}: {error}")
        rows.append((task, settings, config, False))
        if args.design_runs == "both" and task_spec(task).dynamic:
            rows.append((task, settings, config, True))
    in_a_loop = network_pieces.runs_in_a_loop
    for task, settings, config, bounded in rows:
        # read when the network is traced: the compile and the count below
        network_pieces.runs_in_a_loop = (lambda: False) if bounded else in_a_loop
        algorithm = build_algorithm(config)
        mesh = devices.env_mesh(args.devices, config.num_envs)
        state = initial_state(algorithm, mesh)
        steps = args.updates * config.steps_per_update

        rollout = getattr(algorithm, "rollout", None) or algorithm._rollout  # the replay learners' acting

        def acting_only(s, p):  # the baseline: the same acting, no learning
            return jax.lax.scan(lambda s, _: (rollout(s, p)[0], None), s, None, length=args.updates)[0]

        # The state is donated, as the driver donates it: without, each call would copy its whole
        # output state, a replay learner's buffer included (hundreds of MB on a dynamic column,
        # whose observations hold the design), and time the copy rather than the learner.
        train = jax.jit(
            jax.vmap(lambda s, p: algorithm.train_chunk(s, p, args.updates)[0], in_axes=(0, None)), donate_argnums=0
        )
        act = jax.jit(jax.vmap(acting_only, in_axes=(0, None)), donate_argnums=0)
        start = time.perf_counter()
        train = train.lower(state, algorithm.env_params).compile()
        compile_s = time.perf_counter() - start
        act = act.lower(state, algorithm.env_params).compile()
        state = jax.block_until_ready(train(state, algorithm.env_params))  # warm-up
        load = os.getloadavg()
        rates = {"train": [], "act": []}
        for _ in range(args.repeats):
            for name, fn in (("train", train), ("act", act)):
                start = time.perf_counter()
                state = jax.block_until_ready(fn(state, algorithm.env_params))
                rates[name].append(steps / (time.perf_counter() - start))
        rate, acting = statistics.median(rates["train"]), statistics.median(rates["act"])
        params = param_count(jax.tree.map(lambda x: x[0], state.params))
        chunk_flops = flops.count(
            jax.vmap(lambda s, p: algorithm.train_chunk(s, p, 1)[0], in_axes=(0, None)), state, algorithm.env_params
        )
        network_gflops = rate * chunk_flops.total / (state.update.shape[0] * config.steps_per_update) / 1e9
        matmul_gflops = _matmul_gflops(_minibatch_rows(config), _core_width(config), args.repeats)
        kind = _network_text(config) + "".join(f"; {name}={value}" for name, value in settings.items())
        kind += "; design runs in one bounded pass" if bounded else ""
        bound = "" if chunk_flops.exact else "≈ "  # a rare branch counted as taken, a loop's body once
        emit(
            f"| {task} | {kind} | {config.num_envs} | {_learning_text(config)} | {params:,} | {compile_s:.1f} | "
            f"{rate:,.0f} | {acting:,.0f} | {1 - rate / acting:.0%} | {bound}{_gflops_text(network_gflops)} | "
            f"{_gflops_text(matmul_gflops)} | {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} |"
        )


def _hidden_width(config) -> int:
    return config.layers[0] if hasattr(config, "layers") else config.hidden_size  # SAC: its layers' widths


def _core_width(config) -> int:
    """The recurrent core's width, else the first hidden layer's."""
    if getattr(config, "recurrent", False):
        return config.rnn_size
    return getattr(config, "lstm_size", 0) or _hidden_width(config)


def _network_text(config) -> str:
    hidden = f"hidden {config.hidden_sizes}" if hasattr(config, "hidden_sizes") else f"hidden {config.hidden_size}"
    if getattr(config, "recurrent", False):
        return f"GRU {config.rnn_size}, {hidden}"
    if getattr(config, "lstm_size", 0):
        return f"LSTM {config.lstm_size}, {hidden}"
    return f"feed-forward, {hidden}"


def _learning_text(config) -> str:
    """What one update learns from: rollout steps x epochs x minibatches (on-policy), or rollout
    steps x gradient steps x sampled batch (replay)."""
    if hasattr(config, "update_epochs"):
        return f"{config.rollout_steps} x {config.update_epochs} epochs x {config.num_minibatches} minibatches"
    return f"{config.rollout_steps} x {config.gradient_steps} gradient steps x {config.batch_size} samples"


def _minibatch_rows(config) -> int:
    """The rows one gradient step's matrix products take: a minibatch of the rollout, or a batch."""
    if hasattr(config, "num_minibatches"):
        return config.steps_per_update // config.num_minibatches
    return config.batch_size * getattr(config, "sample_length", 1)


def _variant_settings(text: str, algorithm: str, own_flags: set[str]) -> dict:
    """`NAME=VALUE[,NAME=VALUE...]` as the settings it names, each value of its option's type; a
    one-line `ValueError` naming the algorithm's settings otherwise (their values are checked when
    `main` makes every row's config, before the first compiles). A setting that is one of
    `own_flags` (this script's own options, e.g. --num-envs) is refused: its flag sets every row."""
    from agents.training.cli import flag_type
    from agents.training.config import field_specs
    from agents.training.registry import config_class

    fields = {name: spec for name, spec in field_specs(config_class(algorithm)).items() if spec.cli}
    settings = {}
    for item in text.split(","):
        name, sep, value = (part.strip() for part in item.partition("="))
        name = name.replace("-", "_")
        if not sep or not value or name not in fields:
            raise ValueError(
                f"--variant takes NAME=VALUE[,NAME=VALUE...] with NAME one of {algorithm}'s settings "
                f"({', '.join(fields)}), got {item!r}"
            )
        if name in settings:
            raise ValueError(f"--variant: {name} is named twice in {text!r}")
        if name in own_flags:
            raise ValueError(
                f"--variant: {name} has its own flag (--{name.replace('_', '-')}), which sets it for every row"
            )
        kind = fields[name].kind
        if kind is bool:
            if value.lower() not in ("true", "false"):
                raise ValueError(f"--variant {name}: true or false, got {value!r}")
            settings[name] = value.lower() == "true"
        else:
            try:
                settings[name] = flag_type(fields[name])(value)  # `snac train`'s parsing and check of the flag
            except argparse.ArgumentTypeError as error:
                raise ValueError(f"--variant {name}: {error}") from None
    return settings


def _gflops_text(gflops: float) -> str:
    """One decimal, or three significant figures below 100 so that a tiny network's rate does
    not print as 0.0."""
    return f"{gflops:.1f}" if gflops >= 100 else f"{gflops:.3g}"


def _matmul_gflops(rows: int, width: int, repeats: int) -> float:
    """Median GFLOP/s of `(rows, width) @ (width, width)` in float32, ten products per call."""
    import jax
    import jax.numpy as jnp

    x = jnp.ones((rows, width), jnp.float32)
    w = jnp.full((width, width), 1.0 / width, jnp.float32)
    chain = jax.jit(lambda x: jax.lax.fori_loop(0, 10, lambda _, y: y @ w, x))
    _seconds(chain, x)  # compile
    return 10 * 2 * rows * width * width / statistics.median(_seconds(chain, x) for _ in range(repeats)) / 1e9


def _seconds(fn, *args) -> float:
    """Wall seconds of one call of `fn(*args)`, waiting for its device work."""
    import jax

    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start


if __name__ == "__main__":
    main()
