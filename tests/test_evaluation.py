"""The evaluation protocol: statistics on policies whose IoU is known, strata, compile-once."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from snac_jax import evaluation, make
from snac_jax.evaluation import evaluate_task, summarize
from snac_jax.policy import Policy


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


def test_same_seed_same_numbers_and_one_compile_per_configuration():
    first = evaluate_task("2d-static-sparse", _NEVER_DROP, static_episodes=6, seed=1)
    compiled = _compiled_programs()
    again = evaluate_task("2d-static-sparse", _NEVER_DROP, static_episodes=6, seed=1)
    other_seed = evaluate_task("2d-static-sparse", _NEVER_DROP, static_episodes=6, seed=2)
    assert _compiled_programs() == compiled
    assert (first.mean, first.mean_length) == (again.mean, again.mean_length) == (other_seed.mean, 600.0)


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
    ],
)
def test_bad_input_is_a_value_error(task, kwargs, match):
    with pytest.raises(ValueError, match=match):
        evaluate_task(task, _NEVER_DROP, **kwargs)


def test_paper_results_are_packaged():
    from snac_jax import paper as paper_module

    paper = paper_module.load_paper_results()
    row = paper_module.paper_row(paper, "handcrafted")
    assert set(paper_module.PAPER_TASKS) <= set(row)
    assert paper_module.paper_row(paper, None) == {}
    assert [paper_module.paper_column(t) for t in ("1d-static-gauss", "1d-dynamic", "3d-static-dense")] == [
        "1d-static", "1d-dynamic", "3d-static-dense"]
