"""A/B of how a sequence's design runs are encoded in a learner's update, interleaved in one
process: the CPU's loop of passes (`agents.common.networks.encode_each_run`, `--chunk` runs a
pass) against the accelerators' bounded pass (`encode_design_runs`). Each way's training chunk
is compiled once, then the two are timed in turn, `--repeats` times each, so that a load that
drifts (a shared 2-core CPU) falls on both alike; prints the median env steps/s of each.

    python bench/design_runs_ab.py --algorithm ppo --task 3d-dynamic-dense --chunk quarter

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
    in_a_loop, ways = networks.runs_in_a_loop, {}
    for way, choice in (("loop", in_a_loop), ("bounded pass", lambda: False)):
        networks.runs_in_a_loop = choice  # read when the chunk is traced
        state = initial_state(algorithm, None)
        chunk = jax.jit(
            jax.vmap(lambda s: algorithm.train_chunk(s, algorithm.env_params, args.updates)[0]), donate_argnums=0
        )
        compiled = chunk.lower(state).compile()
        ways[way] = [compiled, jax.block_until_ready(compiled(state)), []]  # warmed up
    networks.runs_in_a_loop = in_a_loop
    for _ in range(args.repeats):
        for way in ways:
            compiled, state, times = ways[way]
            start = time.perf_counter()
            ways[way][1] = jax.block_until_ready(compiled(state))
            times.append(time.perf_counter() - start)
    steps = args.updates * algorithm.config.steps_per_update
    rates = {way: steps / statistics.median(times) for way, (_, _, times) in ways.items()}
    print(
        f"{args.algorithm} on {args.task}, loop of {args.chunk} a pass; env steps/s with learning, median of "
        f"{args.repeats}, interleaved: "
        + ", ".join(f"{way} {rate:,.0f}" for way, rate in rates.items())
        + f"; loop / bounded {rates['loop'] / rates['bounded pass']:.2f}"
    )


if __name__ == "__main__":
    main()
