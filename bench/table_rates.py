"""Training rates and evaluation times that `snac table --dry-run` estimates wall time from
(`agents/table/rates.json`): env steps per second of a tuned config *with learning*, summed over
its seeds, and seconds of the reporting protocol per seed.

    python bench/table_rates.py --algorithms drqn --tasks 2d-static-dense 3d-static-dense --write

Each (algorithm, task) trains its tuned config (`agents/tuned/<algorithm>.toml`) through
`agents.driver.train`, the table's own path, in a temporary directory: `--chunks` chunks of
about `--chunk-steps` env steps per seed. The rate is the last chunk's (each chunk is compiled
before it is timed, and a replay learner's first steps, before learning starts, fall in the
first chunks). With `--eval`, the reporting protocol is then timed on seed 0's policy, compile
included. The load average is recorded with each entry: on a shared CPU it skews the rate, so
`--max-load` first waits (at most `--max-wait` minutes) for the 1-minute load average to drop.
Entries copied by hand from a results page (an idle machine's whole tuned run) name that page
in `source`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from pathlib import Path

RATES_FILE = Path(__file__).resolve().parents[1] / "agents" / "table" / "rates.json"


def wait_for_quiet(max_load: float | None, max_wait_s: float) -> None:
    start = time.monotonic()
    while max_load is not None and os.getloadavg()[0] > max_load and time.monotonic() - start < max_wait_s:
        time.sleep(15)


def measure(algorithm: str, task: str, chunk_steps: int, chunks: int, seeds: int, evaluate: bool) -> dict:
    import jax

    from agents.driver import read_metrics, train
    from agents.registry import make_config
    from snac_jax.evaluation import REPORT_EVAL_SEED, evaluate_task

    base = make_config(algorithm, task)
    updates = max(1, math.ceil(chunk_steps / base.steps_per_update))
    config = make_config(algorithm, task, total_steps=updates * chunks * base.steps_per_update, chunks=chunks, seeds=seeds)
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as out:
        algorithm_obj, state = train(config, out, progress=False)
        last = read_metrics(out)[-1]
        entry = {
            "steps_per_s": round(last["steps_per_s"]),
            "seeds": seeds,
            "load_avg": [round(load, 2), round(os.getloadavg()[0], 2)],
            "source": f"bench/table_rates.py, tuned config, last of {chunks} chunks of {updates * base.steps_per_update:,} "
                      f"env steps per seed, {time.strftime('%Y-%m-%d')}",
        }
        if evaluate:
            params = jax.tree.map(lambda x: x[0], state.params)
            start = time.perf_counter()
            evaluate_task(task, algorithm_obj.policy(params), seed=REPORT_EVAL_SEED)
            entry["eval_s"] = round(time.perf_counter() - start, 1)
    return entry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algorithms", nargs="+", required=True)
    parser.add_argument("--tasks", nargs="+", required=True, help="environment task ids")
    parser.add_argument("--chunk-steps", type=int, default=100_000, help="env steps per seed per chunk (at least one update)")
    parser.add_argument("--chunks", type=int, default=3)
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--eval", action="store_true", help="also time the reporting protocol on seed 0's policy")
    parser.add_argument("--write", action="store_true", help=f"merge the entries into {RATES_FILE}")
    parser.add_argument("--max-load", type=float, default=None, help="wait for the 1-minute load average to drop to this")
    parser.add_argument("--max-wait", type=float, default=10.0, help="minutes to wait for --max-load (then measure anyway)")
    args = parser.parse_args()
    for name in ("chunk_steps", "chunks", "seeds"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1")

    from snac_jax import devices

    devices.use_cpu_devices(1)  # as `snac table` trains on a CPU
    for algorithm in args.algorithms:
        for task in args.tasks:
            wait_for_quiet(args.max_load, 60 * args.max_wait)
            entry = measure(algorithm, task, args.chunk_steps, args.chunks, args.seeds, args.eval)
            print(json.dumps({"algorithm": algorithm, "task": task, **entry}), flush=True)
            if args.write:
                rates = json.loads(RATES_FILE.read_text()) if RATES_FILE.is_file() else {}
                rates.setdefault(algorithm, {})[task] = entry
                RATES_FILE.write_text(json.dumps(rates, indent=1, sort_keys=True) + "\n")


if __name__ == "__main__":
    main()
