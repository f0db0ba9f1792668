"""Bad input raises ValueError naming what is allowed, before anything is traced."""

import pytest

from snac_jax import TASKS, make, test_design_names


@pytest.mark.parametrize(
    "task,overrides,message",
    [
        ("2d-static", {}, "allowed task ids: 1d-static-sin"),
        ("4d-static-dense", {}, "3d-dynamic-sparse"),
        ("2d-static-dense", {"gpss": True}, "allowed overrides: gps"),
        ("2d-static-dense", {"stride_probs": (0.5, 0.5, 0.5)}, "summing to 1"),
        ("2d-static-dense", {"stride_probs": (1.2, -0.2, 0)}, "non-negative"),
        ("2d-static-dense", {"stride_probs": (0.5, 0.5)}, "three"),
        ("2d-static-dense", {"stride_probs": "uniform"}, "three"),
        ("2d-dynamic-dense", {"test_design": 10}, r"0\.\.9"),
        ("2d-dynamic-dense", {"test_design": -1}, r"0\.\.9"),
        ("2d-static-dense", {"test_design": 0}, "dynamic tasks only"),
        ("2d-dynamic-dense", {"test_design": 1, "design_seed": 2}, "cannot be combined"),
        ("1d-static-sin", {"landmarks": 8}, "2D or 3D"),
        ("1d-dynamic", {"obstacles": True}, "2D or 3D"),
        ("2d-static-dense", {"obstacles": "yes"}, "True or False"),
        ("2d-static-dense", {"gps": 1}, "True or False"),
        ("2d-static-dense", {"landmarks": -3}, "int >= 0"),
        ("2d-static-dense", {"landmarks": 300}, "at most 252"),
        ("3d-static-dense", {"reward_scheme": "sparse"}, "one of \\('height', 'binary'\\)"),
        ("2d-static-dense", {"max_steps": 0}, "int >= 1"),
        ("2d-dynamic-sparse", {"design_bank_size": 0}, "int >= 1"),
    ],
)
def test_make_rejects_bad_input(task, overrides, message):
    with pytest.raises(ValueError, match=message):
        make(task, **overrides)


def test_static_tasks_have_no_test_designs():
    with pytest.raises(ValueError, match="dynamic tasks: 1d-dynamic"):
        test_design_names("2d-static-dense")


def test_every_task_builds_with_defaults():
    for task in TASKS:
        env, params = make(task, design_bank_size=4) if "dynamic" in task else make(task)
        assert env.name == task
