"""The evaluation protocol: statistics on policies whose IoU is known, strata, compile-once."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from snac_jax import evaluation, make
from snac_jax.evaluation import evaluate_task, summarize
from snac_jax.policy import Policy, uniform_random_policy


def _never_drop(env) -> Policy:
    """Walks right forever: builds nothing, so every episode ends at the step limit with IoU 0."""

    def init(key, design):
        return jnp.zeros((), jnp.int32)

    def act(params, state, obs, key):
        return jnp.asarray(1, jnp.int32), state

    return Policy(init, act, None, "never-drop")


_NEVER_DROP = _never_drop(None)


def _gps_oracle_1d() -> Policy:
    """Test only: a 1D policy that reads its true column (the GPS entry at the end of the
    observation) and keeps an exact record of its bricks. It drops where the design still wants
    bricks and walks toward the nearest such column, so it ends with the design built exactly."""

    def init(key, design):
        return {"design": design[0].astype(jnp.int32), "built": jnp.zeros(design.shape[1], jnp.int32)}

    def act(params, state, obs, key):
        column = obs[-1].astype(jnp.int32)
        missing = state["built"] < state["design"]
        drop = missing[column]
        columns = jnp.arange(missing.shape[0])
        target = jnp.argmin(jnp.where(missing, jnp.abs(columns - column), 10_000))
        action = jnp.where(drop, 2, jnp.where(target < column, 0, 1)).astype(jnp.int32)
        built = state["built"].at[column].add(jnp.where(drop, 1, 0))
        return action, {**state, "built": built}

    return Policy(init, act, None, "gps-oracle")


_ORACLE = _gps_oracle_1d()


def test_never_drop_scores_zero_and_runs_to_the_step_limit():
    result = evaluate_task("2d-static-sparse", _NEVER_DROP, static_episodes=6)
    assert result.episodes == 6
    assert result.mean == 0.0 and result.min == 0.0 and result.std == 0.0
    assert result.ci95 == [0.0, 0.0]
    assert result.mean_bricks_used == 0.0
    assert result.mean_length == 600.0
    assert result.per_design == {}


def test_gps_oracle_builds_the_1d_design_exactly():
    result = evaluate_task("1d-static-sin", _ORACLE, static_episodes=8, gps=True)
    assert result.episodes == 8
    assert result.mean > 0.99 and result.min > 0.95
    assert result.mean_bricks_used == 600.0  # the whole budget, sum of the design
    assert result.ci95[0] <= result.mean <= result.ci95[1]


def test_1d_static_is_the_three_shapes():
    result = evaluate_task("1d-static", _ORACLE, static_episodes=4, gps=True)
    assert result.episodes == 12
    assert list(result.per_design) == ["1d-static-sin", "1d-static-gauss", "1d-static-step"]
    assert all(v["episodes"] == 4 for v in result.per_design.values())
    means = [v["mean"] for v in result.per_design.values()]
    assert result.mean == pytest.approx(np.mean(means))
    assert result.min == min(v["min"] for v in result.per_design.values())


def test_dynamic_tasks_use_the_ten_test_designs():
    result = evaluate_task("1d-dynamic", _NEVER_DROP, episodes_per_test_design=2)
    assert result.episodes == 20
    assert list(result.per_design) == [f"1d-dynamic-test{i}" for i in range(10)]
    assert all(v["episodes"] == 2 and v["mean"] == 0.0 for v in result.per_design.values())


@pytest.mark.slow
def test_test_design_params_hold_the_ten_test_designs():
    env, params = make("3d-dynamic-dense", design_bank_size=2)
    test = evaluation.test_design_params("3d-dynamic-dense", params)
    assert test.designs.shape == (10, 20, 20)
    pinned = make("3d-dynamic-dense", test_design=4)[1]
    np.testing.assert_array_equal(np.asarray(test.designs[4]), np.asarray(pinned.designs[0]))
    assert int(test.design_max_bricks[4]) == int(pinned.design_max_bricks[0])
    assert int(test.design_volume[4]) == int(pinned.design_volume[0])
    assert float(test.max_steps_in_episode) == float(params.max_steps_in_episode)


def test_summarize_weights_strata_equally_with_a_stratified_interval():
    strata = {"a": np.array([0.0, 1.0]), "b": np.array([0.5, 0.5, 0.5, 0.9])}
    stats = summarize(strata)
    mean_b = np.mean(strata["b"])
    assert stats["mean"] == pytest.approx((0.5 + mean_b) / 2)
    assert stats["min"] == 0.0
    assert stats["episodes"] == 6
    assert stats["std"] == pytest.approx(np.std(np.concatenate(list(strata.values())), ddof=1))
    se = math.sqrt(np.var(strata["a"], ddof=1) / 2 + np.var(strata["b"], ddof=1) / 4) / 2
    assert stats["ci95"] == pytest.approx([stats["mean"] - 1.959964 * se, stats["mean"] + 1.959964 * se])


def test_single_stratum_interval_is_the_usual_one():
    values = np.linspace(0.2, 0.8, 50)
    stats = summarize({"only": values})
    half = 1.959964 * np.std(values, ddof=1) / math.sqrt(values.size)
    assert stats["ci95"] == pytest.approx([values.mean() - half, values.mean() + half])


def _compiled_programs() -> int:
    return evaluation._run_episodes._cache_size() + evaluation._run_episodes_sharded._cache_size()


_RANDOM = uniform_random_policy(5)  # its actions depend on the key it is given


def test_same_seed_same_episodes_and_one_compile_per_configuration():
    """A policy whose every action comes from its key: the same seed repeats every episode (the
    per-episode arrays, not only their means), another seed changes them, and nothing recompiles."""
    env, params = make("2d-static-sparse", max_steps=60)
    indices = np.zeros(6, np.int32)
    first = jax.device_get(evaluation.run_episodes(env, params, _RANDOM, jax.random.key(1), indices))
    compiled = _compiled_programs()
    again = jax.device_get(evaluation.run_episodes(env, params, _RANDOM, jax.random.key(1), indices))
    other = jax.device_get(evaluation.run_episodes(env, params, _RANDOM, jax.random.key(2), indices))
    assert _compiled_programs() == compiled
    for name in ("iou", "length", "bricks_used", "episode_return"):
        np.testing.assert_array_equal(getattr(first, name), getattr(again, name), err_msg=name)
    assert np.unique(first.bricks_used).size > 1  # the episodes differ from one another...
    assert not np.array_equal(first.episode_return, other.episode_return)  # ...and with the seed
    a = evaluate_task("2d-static-sparse", _RANDOM, static_episodes=6, seed=1, max_steps=60)
    b = evaluate_task("2d-static-sparse", _RANDOM, static_episodes=6, seed=1, max_steps=60)
    assert {**a.to_json(), "wall_s": 0} == {**b.to_json(), "wall_s": 0}


def test_seed_changes_the_episodes():
    a = evaluate_task("1d-static-sin", _ORACLE, static_episodes=4, seed=0, gps=True)
    b = evaluate_task("1d-static-sin", _ORACLE, static_episodes=4, seed=1, gps=True)
    assert a.mean_length != b.mean_length


def test_a_builder_is_called_once_per_environment_task():
    seen = []

    def builder(env):
        seen.append(env.config.task_id)
        return _ORACLE

    evaluate_task("1d-static", builder, static_episodes=4, gps=True)  # as above: compiled once
    assert seen == ["1d-static-sin", "1d-static-gauss", "1d-static-step"]


@pytest.mark.parametrize(
    "task, kwargs, match",
    [
        ("2d-static", {}, "allowed"),
        ("2d-static-dense", {"static_episodes": 0}, "static_episodes"),
        ("2d-dynamic-dense", {"episodes_per_test_design": 1.5}, "episodes_per_test_design"),
        ("2d-dynamic-dense", {"test_design": 3}, "test_design pins one design"),
        ("1d-static-sin", {"seed": 2**32}, r"seed must be an int in 0\.\.4294967295"),
        ("1d-static-sin", {"seed": -1}, r"seed must be an int in 0\.\.4294967295"),
        (
            "1d-static-sin",
            {"static_episodes": 10**11},
            "100,000,000,000 episodes at once needs about .* GiB, more than",
        ),
    ],
)
def test_bad_input_is_a_value_error(task, kwargs, match):
    with pytest.raises(ValueError, match=match):
        evaluate_task(task, _NEVER_DROP, **kwargs)


def test_a_policy_with_actions_outside_the_task_is_refused_not_scored():
    """5 random actions on a 3-action task: the env would clamp 3 and 4 to the drop (2)."""
    with pytest.raises(ValueError, match=r"took [\d,]+ action\(s\) outside 0\.\.2 in 4 of 4 episodes of 1d-static-sin"):
        evaluate_task("1d-static-sin", uniform_random_policy(5), static_episodes=4, max_steps=30)
    below = Policy(_NEVER_DROP.init, lambda p, s, o, k: (jnp.asarray(-1, jnp.int32), s), None, "minus-one")
    with pytest.raises(ValueError, match="outside 0..4"):
        evaluate_task("2d-static-sparse", below, static_episodes=2, max_steps=5)


def test_a_policy_must_return_one_integer_action():
    batched = Policy(_NEVER_DROP.init, lambda p, s, o, k: (jnp.ones(2, jnp.int32), s), None, "two-actions")
    floating = Policy(_NEVER_DROP.init, lambda p, s, o, k: (jnp.asarray(1.0), s), None, "float")
    for policy in (batched, floating):
        with pytest.raises(ValueError, match="one integer action"):
            evaluate_task("1d-static-sin", policy, static_episodes=2, max_steps=5)


def test_run_episodes_checks_design_indices_and_params():
    env, params = make("2d-static-sparse", max_steps=5)
    with pytest.raises(ValueError, match=r"design_indices must be in 0\.\.0, got 1"):
        evaluation.run_episodes(env, params, _NEVER_DROP, jax.random.key(0), [0, 1])
    _, other = make("1d-static-sin")
    with pytest.raises(ValueError, match="params of another task"):
        evaluation.run_episodes(env, other, _NEVER_DROP, jax.random.key(0), [0])


def test_paper_results_are_packaged():
    from snac_jax import paper as paper_module

    paper = paper_module.load_paper_results()
    row = paper_module.paper_row(paper, "handcrafted")
    assert set(paper_module.PAPER_TASKS) <= set(row)
    assert paper_module.paper_row(paper, None) == {}
    assert [paper_module.paper_column(t) for t in ("1d-static-gauss", "1d-dynamic", "3d-static-dense")] == [
        "1d-static",
        "1d-dynamic",
        "3d-static-dense",
    ]
