"""What a user of the built wheel gets: run in a fresh virtual environment where only the wheel
is installed (no editable install, no repository on the path), it makes every task of
`snac_jax.TASKS`, resets it and takes a few steps, checks each observation against the task's
space, and checks that the installed package is the wheel's and not the working tree's.

    python .ci/wheel_check.py          # .ci/run runs it from a scratch directory

Exit status 0 and one line per task on success; a traceback otherwise."""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import numpy as np

import snac_jax

STEPS = 3


def main() -> int:
    here = Path(__file__).resolve().parents[1]
    installed = Path(snac_jax.__file__).resolve()
    if here in installed.parents:
        raise SystemExit(f"snac_jax was imported from the working tree ({installed}), not the installed wheel")
    key = jax.random.key(0)
    for task in snac_jax.TASKS:
        # A small design bank: the dynamic tasks' default bank is costly to generate and adds nothing here.
        env, params = snac_jax.make(task, **({"design_bank_size": 2} if "dynamic" in task else {}))
        key, key_reset = jax.random.split(key)
        obs, state = env.reset(key_reset, params)
        space = env.observation_space(params)
        for t in range(STEPS):
            key, key_step = jax.random.split(key)
            obs, state, reward, terminated, truncated, _ = env.step(key_step, state, t % env.num_actions, params)
            assert bool(space.contains(obs)), f"{task}: step {t}'s observation is outside its space"
            assert np.isfinite(float(reward)), task
        print(f"{task}: made, reset and stepped {STEPS} times; observation {obs.shape} in its space")
    print(f"snac-jax {snac_jax.__version__} from {installed.parent}: every task of snac_jax.TASKS steps")
    return 0


if __name__ == "__main__":
    sys.exit(main())
