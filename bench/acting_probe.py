"""Acting rate of a replay learner alone: env steps per second of its jitted `_rollout` (the
exploring steps between two updates), with the design read as it is, encoded at every step, or
not refreshed at all, to tell what a dynamic column's acting step spends its time on.

    python bench/acting_probe.py --algorithm dqn --task 2d-dynamic-dense --num-envs 64
    python bench/acting_probe.py --algorithm dqn --task 2d-dynamic-dense --num-envs 64 --design every-step

`--design cache` (default): as the learner acts (`apply_with_design_cache`); `every-step`: the
network applied without the cache, encoding every world's design at every step; `no-refresh`:
the features cached at a rollout's first step read as they are, never refreshed (wrong features,
for timing only: what acting costs with the encoder run once per rollout). Prints one line; writes nothing. Median of `--repeats`
rollouts after a warm-up, on whatever device JAX picks.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algorithm", required=True, help="a replay learner: dqn, drqn, drqn-her, rainbow, sac")
    parser.add_argument("--task", required=True)
    parser.add_argument("--num-envs", type=int, default=None, help="worlds (default: the tuned value)")
    parser.add_argument("--design", choices=("cache", "every-step", "no-refresh"), default="cache")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    for name in ("repeats", "num_envs"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")

    import jax

    from agents.common import networks, offpolicy
    from agents.training.registry import build_algorithm, make_config

    overrides = {} if args.num_envs is None else {"num_envs": args.num_envs}
    config = make_config(args.algorithm, args.task, **overrides)
    algorithm = build_algorithm(config)
    if not isinstance(algorithm, offpolicy.ReplayLearner):
        parser.error(f"--algorithm {args.algorithm} is not a replay learner (agents.common.offpolicy)")
    if args.design == "every-step":
        plain = lambda network, variables, cache, *inputs, **kw: (network.apply(variables, *inputs, **kw), cache)
        for module in ("agents.learners.dqn", "agents.learners.rainbow", "agents.learners.sac"):
            __import__(module)
            sys.modules[module].apply_with_design_cache = plain  # the name each learner acts through
    elif args.design == "no-refresh":
        networks.refresh_design_features = lambda encode, designs, seen, features: features

    state = jax.jit(algorithm.init)(jax.random.key(0))
    # donated, as the driver donates its state: else each call copies the replay buffer it returns
    rollout = jax.jit(lambda s: algorithm._rollout(s, algorithm.env_params), donate_argnums=0)
    state, steps, _ = rollout(state)
    jax.block_until_ready(steps)
    times = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        state, steps, _ = rollout(state)
        jax.block_until_ready(steps)
        times.append(time.perf_counter() - start)
    rate = config.num_envs * config.rollout_steps / statistics.median(times)
    print(
        f"{args.algorithm} {args.task} ({config.num_envs} worlds, design: {args.design}): {rate:,.0f} env-steps/s "
        f"acting, median of {args.repeats} rollouts of {config.rollout_steps} steps on {jax.devices()[0].platform}"
    )


if __name__ == "__main__":
    main()
