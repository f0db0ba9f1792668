"""`evaluation.protocol_episodes`: the designs and keys of the protocol's episodes, the same ones
`evaluate_task` scores."""

from __future__ import annotations

import zlib

import jax
import numpy as np
import pytest

from snac_jax import evaluation, make
from snac_jax.evaluation import evaluate_task, protocol_episodes
from snac_jax.policy import uniform_random_policy


def _key_data(key) -> np.ndarray:
    return np.asarray(jax.random.key_data(key))


def test_a_dynamic_task_runs_each_test_design_in_turn_from_its_own_key():
    env, params = make("1d-dynamic", design_bank_size=2)
    setup = protocol_episodes("1d-dynamic", params, 5, episodes_per_test_design=2)
    assert setup.names == tuple(f"1d-dynamic-test{i}" for i in range(10))
    assert setup.num_episodes == 20
    assert setup.design_indices.tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5, 6, 6, 7, 7, 8, 8, 9, 9]
    assert setup.design_indices.dtype == np.int32
    np.testing.assert_array_equal(
        np.asarray(setup.params.designs), np.asarray(evaluation.test_design_params("1d-dynamic", params).designs)
    )
    task_key = jax.random.fold_in(jax.random.key(5), zlib.crc32(b"1d-dynamic"))
    np.testing.assert_array_equal(_key_data(setup.key), _key_data(task_key))
    np.testing.assert_array_equal(_key_data(setup.keys), _key_data(jax.random.split(task_key, 20)))


def test_a_static_task_runs_its_one_design_and_the_seed_and_task_change_the_key():
    _, params = make("2d-static-sparse")
    setup = protocol_episodes("2d-static-sparse", params, 5, static_episodes=3, episodes_per_test_design=7)
    assert setup.names == ("2d-static-sparse",) and setup.design_indices.tolist() == [0, 0, 0]
    assert setup.params is params and setup.keys.shape == (3,)
    other_seed = protocol_episodes("2d-static-sparse", params, 6, static_episodes=3)
    other_task = protocol_episodes("2d-static-dense", make("2d-static-dense")[1], 5, static_episodes=3)
    assert not np.array_equal(_key_data(setup.key), _key_data(other_seed.key))
    assert not np.array_equal(_key_data(setup.key), _key_data(other_task.key))


def test_its_episodes_are_the_ones_evaluate_task_scores():
    """A policy whose every action comes from its key: running the setup's keys and designs by
    hand gives evaluate_task's per-design numbers exactly."""
    env, params = make("1d-dynamic", max_steps=40)
    policy = uniform_random_policy(env.num_actions)
    setup = protocol_episodes("1d-dynamic", params, 11, episodes_per_test_design=3)
    by_hand = jax.device_get(
        evaluation._run_episodes(
            env, policy.init, policy.act, policy.params, setup.params, setup.keys, setup.design_indices
        )
    )
    scored = evaluate_task("1d-dynamic", policy, episodes_per_test_design=3, seed=11, num_devices=1, max_steps=40)
    assert np.unique(by_hand.bricks_used).size > 1  # the keys matter to these episodes
    for index, name in enumerate(setup.names):
        ious = np.asarray(by_hand.iou[setup.design_indices == index], np.float64)
        assert scored.per_design[name]["mean"] == pytest.approx(ious.mean(), abs=1e-12)
        assert scored.per_design[name]["min"] == pytest.approx(ious.min(), abs=1e-12)


@pytest.mark.parametrize(
    "task, kwargs, match",
    [
        ("2d-static-sparse", {"static_episodes": 0}, r"^static_episodes must be an int >= 1, got 0$"),
        ("1d-dynamic", {"episodes_per_test_design": 2.0}, r"^episodes_per_test_design must be an int >= 1, got 2\.0$"),
        ("2d-static-sparse", {"seed": -1}, r"^seed must be an int in 0\.\.4294967295, got -1$"),
        ("1d-static", {}, r"^unknown task id '1d-static'; allowed task ids: 1d-static-sin, "),
    ],
)
def test_bad_input_is_a_one_line_value_error(task, kwargs, match):
    _, params = make("2d-static-sparse")
    with pytest.raises(ValueError, match=match):
        protocol_episodes(task, params, **{"seed": 0, **kwargs})
