"""The Python-API cases of `bench/robustness.py`, run in a process of their own:
`python bench/robustness_api.py WORK all|skip-memory` prints their verdicts as one JSON line."""

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.dont_write_bytecode = True
os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

import gymnasium  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import snac_jax.gymnasium  # noqa: E402, F401  (registers the SNAC/<task>-v0 ids)
from agents.training.registry import make_config  # noqa: E402
from snac_jax import make  # noqa: E402
from snac_jax.evaluation import evaluate_task  # noqa: E402
from snac_jax.human.game import GameSession  # noqa: E402
from snac_jax.policy import Policy, uniform_random_policy  # noqa: E402
from snac_jax.replay import load_traces, replay  # noqa: E402

env2, p2 = make("2d-static-dense")
env1, p1 = make("1d-static-sin")
envb, pb = make("2d-dynamic-dense", design_bank_size=4)
s2 = env2.reset(jax.random.key(0), p2)[1]
sb = envb.reset(jax.random.key(0), pb)[1]
two = Policy(lambda k, d: 0, lambda p, s, o, k: (jnp.ones(2, jnp.int32), s), None, "two-actions")
bare = Policy(lambda k, d: jnp.zeros(2), lambda p, s, o, k: jnp.int32(0), None, "bare-action")
grows = Policy(lambda k, d: jnp.zeros(2), lambda p, s, o, k: (jnp.int32(0), jnp.zeros(3)), None, "memory-grows")
states2 = jax.vmap(env2.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), 3), p2)[1]


def step_past_the_end():
    """The single Gymnasium env stepped once more after its episode was truncated."""
    env = gymnasium.make("SNAC/1d-static-sin-v0", max_steps=3)
    env.reset(seed=0)
    for _ in range(3):
        env.step(2)
    env.step(2)


cases = [
    ("make(max_steps=2**31)", lambda: make("2d-static-dense", max_steps=2**31), "int in 1..2147483647"),
    ("make(design_seed=2**64)", lambda: make("2d-dynamic-dense", design_seed=2**64), "int in 0..4294967295"),
    (
        "make(design_seed=2**32), which JAX would read as seed 0",
        lambda: make("2d-dynamic-dense", design_seed=2**32),
        "int in 0..4294967295",
    ),
    (
        "make(design_bank_size=10**10)",
        lambda: make("2d-dynamic-dense", design_bank_size=10**10),
        "designs needs about",
        "memory",
    ),
    ("a 2D env reset with 1D params", lambda: env2.reset(jax.random.key(0), p1), "params of another task"),
    ("a 2D env stepped with 1D params", lambda: env2.step(jax.random.key(0), s2, 0, p1), "params of another task"),
    (
        "a 2D env stepped with a 1D state",
        lambda: env2.step(jax.random.key(0), env1.reset(jax.random.key(0), p1)[1], 0, p2),
        "state.grid has shape",
    ),
    (
        "reset_to_design(index 4) on a bank of 4",
        lambda: envb.reset_to_design(jax.random.key(0), pb, 4),
        "design_index must be in 0..3",
    ),
    ("step_with_stride(stride=7)", lambda: envb.step_with_stride(sb, 0, 7, pb), "stride must be in 1..3"),
    ("step_with_stride(action=99)", lambda: envb.step_with_stride(sb, 99, 1, pb), "action must be in 0..4"),
    (
        "reset_to_design(design_index=0.5)",
        lambda: envb.reset_to_design(jax.random.key(0), pb, 0.5),
        "design_index must be one int in 0..3",
    ),
    ("step_with_stride(stride=2.0)", lambda: envb.step_with_stride(sb, 0, 2.0, pb), "stride must be one int in 1..3"),
    ("env.privileged on a batch of 3 states", lambda: env2.privileged(states2, p2), "jax.vmap(env.privileged"),
    (
        "evaluate_task: a policy whose act returns a bare action",
        lambda: evaluate_task("1d-static-sin", bare, static_episodes=2, max_steps=5),
        "policy.act must return (action, policy_state)",
    ),
    (
        "evaluate_task: a policy whose act changes its memory's shape",
        lambda: evaluate_task("1d-static-sin", grows, static_episodes=2, max_steps=5),
        "policy.act must return a policy_state like the one it was given",
    ),
    (
        "gymnasium.make('SNAC/1d-static-sin-v0', task_id='2d-static-dense')",
        lambda: gymnasium.make("SNAC/1d-static-sin-v0", task_id="2d-static-dense"),
        "is the task 1d-static-sin",
    ),
    ("the single Gymnasium env stepped after truncation", step_past_the_end, "the episode ended (truncated)"),
    (
        "make_config('pqn-belief', view_radius=100000)",
        lambda: make_config("pqn-belief", "2d-static-dense", view_radius=100000),
        "view_radius must be 0 or in 3..19",
    ),
    (
        "evaluate_task: a 5-action random policy on a 3-action task",
        lambda: evaluate_task("1d-static-sin", uniform_random_policy(5), static_episodes=4, max_steps=30),
        "outside 0..2",
    ),
    (
        "evaluate_task: a policy returning two actions",
        lambda: evaluate_task("1d-static-sin", two, static_episodes=2, max_steps=5),
        "one integer action",
    ),
    (
        "evaluate_task(test_design=3)",
        lambda: evaluate_task("2d-dynamic-dense", uniform_random_policy(5), test_design=3),
        "test_design pins one design",
    ),
    (
        "evaluate_task(seed=2**64)",
        lambda: evaluate_task("1d-static-sin", uniform_random_policy(3), seed=2**64),
        "seed must be an int in 0..4294967295",
    ),
    (
        "evaluate_task(static_episodes=10**11)",
        lambda: evaluate_task("1d-static-sin", uniform_random_policy(3), static_episodes=10**11),
        "episodes at once needs",
        "memory",
    ),
    ("replay with action 7 on a 3-action task", lambda: replay(env1, p1, [0, 7], [1, 1]), "actions must be in 0..2"),
    ("load_traces of an empty list", lambda: load_traces(sys.argv[1] + "/empty_traces.json"), "non-empty JSON list"),
    ("GameSession(seed=2**32)", lambda: GameSession("1d-static-sin", seed=2**32), "seed must be an int in"),
]
results = []
for what, call, phrase, *memory in cases:
    if memory and sys.argv[2] == "skip-memory":
        results.append({"what": what, "input": "Python API", "verdict": "not run", "note": "memory case skipped"})
        continue
    try:
        call()
        verdict, note = "bad", "accepted"
    except (ValueError, gymnasium.error.ResetNeeded) as error:  # ResetNeeded: Gymnasium's convention
        verdict, note = ("good" if phrase in str(error) else "bad"), f"{type(error).__name__}: {error}"
    except Exception as error:
        verdict, note = ("poor" if phrase in str(error) else "bad"), f"{type(error).__name__}: {error}"
    results.append({"what": what, "input": "Python API", "verdict": verdict, "note": note.splitlines()[0][:300]})
documented = "clamps" in env2.step.__doc__ and "0..num_actions-1" in env2.step.__doc__
clamp = jax.jit(env1.step_with_stride)
same = np.array_equal(
    clamp(env1.reset(jax.random.key(0), p1)[1], 99, 1, p1)[1].grid,
    clamp(env1.reset(jax.random.key(0), p1)[1], 2, 1, p1)[1].grid,
)
results.append(
    {
        "what": "a traced action 99 inside jit (no per-step check)",
        "input": "Python API",
        "verdict": "good" if documented and same else "bad",
        "note": "documented in SNACEnv.step: clamped to the last action; the evaluator refuses such policies",
    }
)
print(json.dumps(results))
