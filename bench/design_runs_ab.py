"""A/B of how a learner reads a dynamic task's design, interleaved in one process. `--compare
loop`: a sequence's design runs encoded by the CPU's loop of passes
(`agents.common.networks.encode_each_run`, `--chunk` runs a pass) against the accelerators'
bounded pass (`encode_design_runs`). `--compare first-layer`: the first hidden layer's product
with the design features computed once per run (`ObservationEncoder`) against that layer over
every step's concatenated inputs. Each way's training chunk is compiled once, then the two are
timed in turn, `--repeats` times each, so that a load that drifts (a shared 2-core CPU) falls on
both alike; prints the median env steps/s of each.

    python bench/design_runs_ab.py --algorithm ppo --task 3d-dynamic-dense --chunk quarter
    python bench/design_runs_ab.py --algorithm pqn --compare first-layer

Writes nothing.
"""

from __future__ import annotations

import argparse
import statistics
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algorithm", default="pqn", help="an algorithm id of `snac train`")
    parser.add_argument("--task", default="3d-dynamic-dense", help="a dynamic task")
    parser.add_argument("--compare", choices=("loop", "first-layer"), default="loop", help="which two ways (above)")
    parser.add_argument("--chunk", choices=("columns", "quarter"), default="columns", help="runs per pass of the loop")
    parser.add_argument("--updates", type=int, default=2, help="updates per timed call")
    parser.add_argument("--repeats", type=int, default=4, help="timed calls of each way")
    args = parser.parse_args()
    if args.updates < 1 or args.repeats < 1:
        parser.error("--updates and --repeats must be >= 1")
    import jax

    from agents.common import networks
    from agents.training.driver import initial_state
    from agents.training.registry import ALGORITHMS, build_algorithm, make_config
    from snac_jax.tasks import TASKS, task_spec

    if args.algorithm not in ALGORITHMS:
        parser.error(f"--algorithm: unknown {args.algorithm!r}; allowed: {', '.join(ALGORITHMS)}")
    dynamic = [t for t in TASKS if task_spec(t).dynamic]
    if args.task not in dynamic:
        parser.error(f"--task: {args.task!r} holds no design to encode; allowed: {', '.join(dynamic)}")
    if args.chunk == "quarter":
        networks.run_chunk = lambda columns: max(1, -(-columns // 4))
    algorithm = build_algorithm(make_config(args.algorithm, args.task, seeds=1))
    in_a_loop, once_per_run, ways = networks.runs_in_a_loop, networks.ObservationEncoder._design_once_per_run, {}
    choices = {
        "loop": (("loop", in_a_loop, once_per_run), ("bounded pass", lambda: False, once_per_run)),
        "first-layer": (("once per run", in_a_loop, once_per_run), ("every step", in_a_loop, lambda *_: False)),
    }[args.compare]
    for way, loop, split in choices:
        networks.runs_in_a_loop, networks.ObservationEncoder._design_once_per_run = loop, split  # read when traced
        state = initial_state(algorithm, None)
        chunk = jax.jit(
            jax.vmap(lambda s: algorithm.train_chunk(s, algorithm.env_params, args.updates)[0]), donate_argnums=0
        )
        compiled = chunk.lower(state).compile()
        ways[way] = [compiled, jax.block_until_ready(compiled(state)), []]  # warmed up
    networks.runs_in_a_loop, networks.ObservationEncoder._design_once_per_run = in_a_loop, once_per_run
    for _ in range(args.repeats):
        for way in ways:
            compiled, state, times = ways[way]
            start = time.perf_counter()
            ways[way][1] = jax.block_until_ready(compiled(state))
            times.append(time.perf_counter() - start)
    steps = args.updates * algorithm.config.steps_per_update
    rates = {way: steps / statistics.median(times) for way, (_, _, times) in ways.items()}
    (a, rate_a), (b, rate_b) = rates.items()
    what = f"loop of {args.chunk} a pass" if args.compare == "loop" else "the first layer's design share"
    print(
        f"{args.algorithm} on {args.task}, {what}; env steps/s with learning, median of {args.repeats}, "
        f"interleaved: {a} {rate_a:,.0f}, {b} {rate_b:,.0f}; {a} / {b} {rate_a / rate_b:.2f}"
    )


if __name__ == "__main__":
    main()
