"""Training throughput: env steps per second of PPO *including learning* (rollout, GAE and the
update epochs), per task and network, on every local device (one CPU device per core).

    python bench/train_throughput.py --tasks 1d-static-sin 2d-static-dense --recurrent both

Each configuration is compiled first (compile time reported apart), then timed over `--updates`
updates; the load average is printed beside each timing because a shared CPU skews them.
"""

from __future__ import annotations

import argparse
import os
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["1d-static-sin", "2d-static-dense"])
    parser.add_argument("--recurrent", choices=("yes", "no", "both"), default="both")
    parser.add_argument("--updates", type=int, default=10, help="timed updates per configuration")
    parser.add_argument("--num-envs", type=int, default=None, help="default: the tuned value per task")
    parser.add_argument("--devices", type=int, default=None, help="default: one CPU device per core")
    for option in ("hidden-size", "rnn-size", "update-epochs", "num-minibatches", "rollout-steps"):
        parser.add_argument("--" + option, type=int, default=None, help="default: the tuned value per task")
    args = parser.parse_args()

    from snac_jax import devices

    devices.use_cpu_devices(args.devices)
    import jax

    from agents.config import make_config
    from agents.driver import build_algorithm, initial_state
    from agents.networks import param_count

    variants = {"yes": [True], "no": [False], "both": [False, True]}[args.recurrent]
    print(f"jax {jax.__version__}, {len(jax.devices())} {jax.devices()[0].platform} device(s)")
    print("| task | network | worlds | steps x epochs x minibatches | params | compile s | env-steps/s (with learning) | load avg |")
    print("|---|---|---:|---|---:|---:|---:|---|")
    for task in args.tasks:
        for recurrent in variants:
            config = make_config("ppo", task, recurrent=recurrent, num_envs=args.num_envs, hidden_size=args.hidden_size,
                                 rnn_size=args.rnn_size, update_epochs=args.update_epochs,
                                 num_minibatches=args.num_minibatches, rollout_steps=args.rollout_steps)
            algorithm = build_algorithm(config)
            mesh = devices.env_mesh(args.devices, config.num_envs)
            state = initial_state(algorithm, mesh)
            fn = jax.jit(jax.vmap(lambda s, p: algorithm.train_chunk(s, p, args.updates), in_axes=(0, None)))
            start = time.perf_counter()
            compiled = fn.lower(state, algorithm.env_params).compile()
            compile_s = time.perf_counter() - start
            state, _ = jax.block_until_ready(compiled(state, algorithm.env_params))  # warm-up
            load = os.getloadavg()
            start = time.perf_counter()
            jax.block_until_ready(compiled(state, algorithm.env_params))
            elapsed = time.perf_counter() - start
            rate = args.updates * algorithm.config.steps_per_update / elapsed
            params = param_count(jax.tree.map(lambda x: x[0], state.params))
            kind = f"GRU {config.rnn_size}" if recurrent else "feed-forward"
            print(f"| {task} | {kind}, hidden {config.hidden_size} | {config.num_envs} | {config.rollout_steps} x {config.update_epochs} x {config.num_minibatches} | {params:,} | {compile_s:.1f} | "
                  f"{rate:,.0f} | {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
