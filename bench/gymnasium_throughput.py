"""Steps/s of `snac_jax.gymnasium.SNACVectorEnv` beside the jitted env it wraps, at N worlds.

    python bench/gymnasium_throughput.py --out bench/results
    python bench/gymnasium_throughput.py --out /tmp/gym --task 1d-static-sin --num-envs 1 64 --repeats 3

Three ways to step N worlds with uniform-random actions and auto-reset, all through
`SNACEnv.step_batch`:

- `vector_env`: `SNACVectorEnv.step` called from Python with NumPy actions; each call is one
  jitted step of the N worlds, and the observations, rewards and flags come back as NumPy
  arrays (what a Gymnasium client sees).
- `jit_step`: a jitted function (draw keys and actions, `env.step_batch`) called once per step
  from Python; nothing leaves the device until the last call of a repeat is waited for.
- `jit_scan`: one jitted `lax.scan` of `--steps` such steps (a PureJaxRL-style rollout).

The jitted loops fold every observation into a checksum, so, like the vector env, they compute
the observations (a policy that reads none lets XLA skip them). Each point is the median over
`--repeats` timed repeats of `--steps` steps, after a warm-up that compiles.

Writes only under `--out` (a directory): `gymnasium_throughput.json` (the settings, the
machine and one row per N) and `gymnasium_throughput.md` (the table).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from functools import partial
from pathlib import Path

sys.dont_write_bytecode = True  # nothing but the results is written
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

NAME = "gymnasium_throughput"


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {text}")
    return value


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="directory for the JSON and the markdown table")
    parser.add_argument("--task", default="2d-static-dense", help="task id (default 2d-static-dense)")
    parser.add_argument("--num-envs", type=positive_int, nargs="+", default=[1, 64, 1024], help="batch sizes N")
    parser.add_argument("--steps", type=positive_int, default=200, help="steps of the N worlds per timed repeat")
    parser.add_argument("--repeats", type=positive_int, default=5, help="timed repeats per point (the median is kept)")
    return parser.parse_args(argv)


def time_vector_env(task: str, num_envs: int, steps: int, repeats: int) -> list[float]:
    import numpy as np

    from snac_jax.gymnasium import SNACVectorEnv

    envs = SNACVectorEnv(task, num_envs=num_envs)
    envs.reset(seed=0)
    rng = np.random.default_rng(0)
    n = envs.single_action_space.n
    envs.step(rng.integers(0, n, size=num_envs))
    times = []
    for _ in range(repeats):
        actions = rng.integers(0, n, size=(steps, num_envs))
        start = time.perf_counter()
        for row in actions:
            envs.step(row)
        times.append(time.perf_counter() - start)
    envs.close()
    return times


def time_jitted(task: str, num_envs: int, steps: int, repeats: int) -> tuple[list[float], list[float]]:
    import jax
    import jax.numpy as jnp

    from snac_jax import make

    env, params = make(task)

    def one_step(carry, _):
        key, states, checksum = carry
        key, step_key, action_key = jax.random.split(key, 3)
        actions = jax.random.randint(action_key, (num_envs,), 0, env.num_actions)
        keys = jax.random.split(step_key, num_envs)
        obs, states, reward, *_ = env.step_batch(keys, states, actions, params)
        return (key, states, checksum + jnp.sum(obs) + jnp.sum(reward)), None

    step = jax.jit(lambda carry: one_step(carry, None)[0])

    @partial(jax.jit, donate_argnums=0)
    def scan(carry):
        return jax.lax.scan(one_step, carry, None, length=steps)[0]

    key = jax.random.key(0)
    _, states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, num_envs), params)
    carry = (key, states, jnp.zeros((), jnp.float32))
    carry = jax.block_until_ready(step(carry))
    carry = jax.block_until_ready(scan(carry))

    step_times, scan_times = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(steps):
            carry = step(carry)
        jax.block_until_ready(carry)
        step_times.append(time.perf_counter() - start)

        start = time.perf_counter()
        carry = jax.block_until_ready(scan(carry))
        scan_times.append(time.perf_counter() - start)
    return step_times, scan_times


def rate(num_envs: int, steps: int, times: list[float]) -> float:
    return num_envs * steps / statistics.median(times)


def table(result: dict) -> str:
    lines = [
        f"# Gymnasium vector env throughput: {result['task']}",
        "",
        f"Env-steps/s (median of {result['repeats']} repeats of {result['steps']} steps), uniform-random actions, "
        f"auto-reset; {result['device']} ({result['cpu_count']} CPU cores), jax {result['jax']}, gymnasium {result['gymnasium']}.",
        "",
        "| N | SNACVectorEnv | jitted step_batch, one call per step | jitted lax.scan of step_batch | vector env / scan |",
        "|---:|---:|---:|---:|---:|",
    ]
    for row in result["rows"]:
        lines.append(
            f"| {row['num_envs']} | {row['vector_env_steps_per_s']:,.0f} | {row['jit_step_steps_per_s']:,.0f} | "
            f"{row['jit_scan_steps_per_s']:,.0f} | {row['vector_env_steps_per_s'] / row['jit_scan_steps_per_s']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    args = parse_args(argv)
    import gymnasium
    import jax

    rows = []
    for num_envs in args.num_envs:
        vector_times = time_vector_env(args.task, num_envs, args.steps, args.repeats)
        step_times, scan_times = time_jitted(args.task, num_envs, args.steps, args.repeats)
        row = {
            "num_envs": num_envs,
            "vector_env_steps_per_s": rate(num_envs, args.steps, vector_times),
            "jit_step_steps_per_s": rate(num_envs, args.steps, step_times),
            "jit_scan_steps_per_s": rate(num_envs, args.steps, scan_times),
            "vector_env_s": vector_times,
            "jit_step_s": step_times,
            "jit_scan_s": scan_times,
        }
        rows.append(row)
        print(
            f"N={num_envs}: vector env {row['vector_env_steps_per_s']:,.0f}/s, jitted step {row['jit_step_steps_per_s']:,.0f}/s, "
            f"jitted scan {row['jit_scan_steps_per_s']:,.0f}/s",
            flush=True,
        )
    device = jax.devices()[0]
    result = {
        "task": args.task,
        "steps": args.steps,
        "repeats": args.repeats,
        "device": f"{device.platform} ({device.device_kind}), {len(jax.devices())} device(s)",
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "gymnasium": gymnasium.__version__,
        "rows": rows,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{NAME}.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out / f"{NAME}.md").write_text(table(result))
    return result


if __name__ == "__main__":
    main()
