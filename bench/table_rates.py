"""Training rates and evaluation times that `snac table --dry-run` estimates wall time from
(`agents/table/rates.json`): env steps per second of a tuned config *with learning*, summed over
its seeds, and seconds of the reporting protocol per seed.

    python bench/table_rates.py --algorithms drqn --tasks 2d-static-dense 3d-static-dense --write

Each (algorithm, task) builds its tuned config (`agents/tuned/<algorithm>.toml`), compiles the
driver's vmapped chunk of `--updates` updates, runs it once untimed (warm-up; a replay learner's
first steps before learning starts fall there), then times `--repeats` chunks in wall-clock and
in this process's CPU time. With `--eval`, the reporting protocol is timed on seed 0's policy,
compile included.

On a shared CPU the wall-clock rate says more about the other processes than about the
learner, while the CPU-time rate (env steps per CPU-second) barely moves. So when rates.json
already holds an idle machine's rate for the algorithm on `--reference` (an entry copied from a
results page, without `load_avg`) with as many seeds as `--seeds`, the reference is measured in
the same run and every entry's `steps_per_s` is its CPU-time rate times the reference's idle wall
rate over its CPU-time rate (how many cores the learner keeps busy when it has the machine).
Without such a reference, `--cores N` takes the CPU-time rate times N, and otherwise
`steps_per_s` is the wall-clock rate, with the load average beside it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

from agents.table.rates import RATES_FILE, load_rates


def measure(algorithm: str, task: str, chunk_steps: int, repeats: int, seeds: int, evaluate: bool) -> dict:
    import jax

    from agents.training.driver import initial_state
    from agents.training.registry import build_algorithm, make_config
    from snac_jax.evaluation import REPORT_EVAL_SEED, evaluate_task

    base = make_config(algorithm, task)
    updates = max(1, math.ceil(chunk_steps / base.steps_per_update))
    config = make_config(algorithm, task, seeds=seeds, total_steps=updates * base.steps_per_update * (repeats + 1))
    agent = build_algorithm(config)
    state = initial_state(agent)
    chunk = jax.jit(jax.vmap(lambda s, p: agent.train_chunk(s, p, updates), in_axes=(0, None)), donate_argnums=0)
    chunk = chunk.lower(state, agent.env_params).compile()
    state, _ = jax.block_until_ready(chunk(state, agent.env_params))
    load = os.getloadavg()[0]
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(repeats):
        state, _ = jax.block_until_ready(chunk(state, agent.env_params))
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    steps = updates * config.steps_per_update * seeds * repeats
    entry = {
        "wall_steps_per_s": round(steps / wall),
        "cpu_steps_per_s": round(steps / cpu),
        "seeds": seeds,
        "load_avg": [round(load, 2), round(os.getloadavg()[0], 2)],
        "measured": f"bench/table_rates.py, tuned config, {repeats} chunks of {updates * config.steps_per_update:,} "
        f"env steps per seed after a warm-up chunk, {time.strftime('%Y-%m-%d')}",
    }
    if evaluate:
        params = jax.tree.map(lambda x: x[0], state.params)
        start = time.perf_counter()
        evaluate_task(task, agent.policy(params), seed=REPORT_EVAL_SEED)
        entry["eval_s"] = round(time.perf_counter() - start, 1)
    return entry


def idle_reference(rates: dict, algorithm: str, task: str, seeds: int) -> dict | None:
    """The rates.json entry that may calibrate a measurement of `seeds` vmapped seeds: an idle
    machine's rate (no `load_avg`) of `algorithm` on `task` with as many seeds. Why the seed
    count must match: more seeds keep more of the cores busy, so another count's wall-over-CPU
    ratio would mis-scale the CPU-time rate."""
    entry = rates.get(algorithm, {}).get(task)
    if entry is None or "load_avg" in entry or entry.get("seeds", 1) != seeds:
        return None
    return entry


def calibrated(entry: dict, reference: dict | None, reference_task: str, cores: float | None = None) -> dict:
    """`steps_per_s` of a measured entry: CPU-time rate x the idle reference's cores in use (or
    x `cores` without a reference), else the wall-clock rate."""
    entry = dict(entry)
    if reference is None and cores is not None:
        entry["steps_per_s"] = round(entry["cpu_steps_per_s"] * cores)
        entry["source"] = f"{entry['measured']}: CPU-time rate x {cores:g} (--cores; no idle run to calibrate with)"
        return entry
    if reference is None:
        entry["steps_per_s"] = entry["wall_steps_per_s"]
        entry["source"] = f"{entry['measured']}: wall-clock rate at load average {entry['load_avg']}"
        return entry
    cores = reference["idle_steps_per_s"] / reference["cpu_steps_per_s"]
    entry["steps_per_s"] = round(entry["cpu_steps_per_s"] * cores)
    entry["source"] = (
        f"{entry['measured']}: CPU-time rate x {cores:.2f} (the idle wall rate of {reference_task}, "
        f"{reference['idle_steps_per_s']:,}/s, over its CPU-time rate in the same run, "
        f"{reference['cpu_steps_per_s']:,}/s)"
    )
    return entry


def merged(old: dict, entry: dict) -> dict:
    """What `--write` stores for a task that already has `old`: an idle machine's rate (no
    `load_avg`) outlives a measurement under load of as many seeds (another seed count is
    another quantity: the table's cells vmap three), and a run without `--eval` keeps the
    protocol time measured before (the rate and the evaluation time are measured separately)."""
    if "load_avg" not in old and "steps_per_s" in old and old.get("seeds", 1) == entry["seeds"]:
        return {**old, **{k: v for k, v in entry.items() if k.startswith("eval")}}
    if "eval_s" in old and "eval_s" not in entry:
        return {**entry, "eval_s": old["eval_s"]}
    return entry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algorithms", nargs="+", required=True)
    parser.add_argument("--tasks", nargs="+", required=True, help="environment task ids")
    parser.add_argument(
        "--chunk-steps", type=int, default=100_000, help="env steps per seed per chunk (at least one update)"
    )
    parser.add_argument("--repeats", type=int, default=2, help="timed chunks")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument(
        "--reference", default="1d-static-sin", help="task whose idle rate calibrates the CPU-time rates"
    )
    parser.add_argument(
        "--cores",
        type=float,
        default=None,
        help="without an idle reference: steps_per_s = CPU-time rate x CORES (default: the wall rate)",
    )
    parser.add_argument("--eval", action="store_true", help="also time the reporting protocol on seed 0's policy")
    parser.add_argument("--write", action="store_true", help=f"merge the entries into {RATES_FILE}")
    args = parser.parse_args()
    for name in ("chunk_steps", "repeats", "seeds"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1")

    from snac_jax import devices
    from snac_jax.atomic import atomic_write_text

    devices.use_cpu_devices(1)  # as `snac table` trains on a CPU
    for algorithm in args.algorithms:
        rates = load_rates()
        idle = idle_reference(rates, algorithm, args.reference, args.seeds)
        reference = None
        if idle is not None:
            ref = measure(algorithm, args.reference, args.chunk_steps, args.repeats, args.seeds, False)
            reference = {"idle_steps_per_s": idle["steps_per_s"], "cpu_steps_per_s": ref["cpu_steps_per_s"]}
            print(json.dumps({"algorithm": algorithm, "reference": args.reference, **ref}), flush=True)
        for task in args.tasks:
            entry = calibrated(
                measure(algorithm, task, args.chunk_steps, args.repeats, args.seeds, args.eval),
                reference,
                args.reference,
                args.cores,
            )
            print(json.dumps({"algorithm": algorithm, "task": task, **entry}), flush=True)
            if args.write:
                rates = load_rates()
                known = rates.setdefault(algorithm, {})
                known[task] = merged(known.get(task, {}), entry)
                atomic_write_text(RATES_FILE, json.dumps(rates, indent=1, sort_keys=True) + "\n")


if __name__ == "__main__":
    main()
