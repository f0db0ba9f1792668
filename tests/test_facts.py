"""Each fact of the benchmark has one home, and every other place reads it from there: the step
limits (`snac_jax.tasks.STEP_LIMITS`), the paper's columns (`snac_jax.paper.PAPER_TASKS`), the
protocol's episode counts (`snac_jax.evaluation`), the paper's training budgets (the paper
preset of `budgets.toml`) and the observation's special cell values (`snac_jax.observation`,
`snac_jax.transition`)."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from snac_jax import evaluation, paper, tasks

ROOT = Path(__file__).parents[1]
BUDGETS = ROOT / "agents" / "table" / "budgets.toml"
PAPER_RESULTS = ROOT / "snac_jax" / "data" / "paper_results.json"


# --- the step limits ---------------------------------------------------------------------------


@pytest.mark.slow
def test_every_task_takes_its_step_limit_from_step_limits():
    for task in tasks.TASKS:
        spec = tasks.task_spec(task)
        assert spec.max_steps == tasks.STEP_LIMITS[spec.dim, spec.dynamic], task
    _, params = tasks.make("3d-dynamic-dense", design_bank_size=1)
    assert int(params.max_steps_in_episode) == tasks.STEP_LIMITS[3, True]


def test_budgets_toml_converts_episodes_with_the_tasks_step_limit():
    from agents.table.plan import requested_budget
    from agents.table.presets import load_presets
    from agents.training.registry import make_config

    preset = load_presets()["paper"]
    for task in ("1d-static-sin", "2d-dynamic-dense", "3d-static-dense", "3d-dynamic-sparse"):
        steps, _ = requested_budget(preset, make_config("drqn", task))
        assert steps == preset.budgets["drqn"]["episodes"] * tasks.task_spec(task).max_steps, task


# --- the paper's columns -----------------------------------------------------------------------


def test_paper_results_json_names_no_column_list_of_its_own_and_uses_paper_tasks():
    results = json.loads(PAPER_RESULTS.read_text())
    assert "tasks" not in results
    for method, row in results["methods"].items():
        assert set(row) == set(paper.PAPER_TASKS), method


def test_a_paper_results_file_with_a_column_the_paper_lacks_is_refused(tmp_path):
    path = tmp_path / "paper.json"
    path.write_text(json.dumps({"methods": {"dqn": {"4d-static": {"avg": 0.5, "min": 0.1}}}}))
    with pytest.raises(ValueError, match=r"methods\.dqn .*unknown column\(s\) \['4d-static'\]"):
        paper.load_paper_results(path)


# --- the protocol's episode counts -------------------------------------------------------------


def test_no_data_file_restates_the_protocols_counts():
    assert "protocol" not in json.loads(PAPER_RESULTS.read_text())
    for name, table in tomllib.loads(BUDGETS.read_text()).items():  # a preset gives its own counts only
        assert table.get("static_episodes") != evaluation.STATIC_EPISODES, name
        assert table.get("episodes_per_test_design") != evaluation.EPISODES_PER_TEST_DESIGN, name


def test_a_preset_without_counts_scores_with_the_protocols(tmp_path):
    from agents.table.presets import load_presets

    path = tmp_path / "budgets.toml"
    path.write_text("[p]\nseeds = 1\n")
    assert load_presets(path)["p"].protocol == {
        "static_episodes": evaluation.STATIC_EPISODES,
        "episodes_per_test_design": evaluation.EPISODES_PER_TEST_DESIGN,
    }


# --- the paper's budgets -----------------------------------------------------------------------


def test_the_paper_presets_budgets_are_the_paper_appendixs():
    """The appendix of the paper (Baseline setup): "We train DQN on each task for 3,000 episodes",
    DRQN "for 10,000 episodes", "this DRQN+Hindsight for 10,000 episodes", "PPO for 10 million time
    steps"; it states none for Rainbow and SAC, which train their tuned total_steps."""
    from agents.table.presets import load_presets

    paper = load_presets()["paper"]
    budgets = {
        algorithm: {k: v for k, v in budget.items() if k != "source"} for algorithm, budget in paper.budgets.items()
    }
    assert budgets == {
        "ppo": {"env_steps": 10_000_000},
        "dqn": {"episodes": 3_000},
        "drqn": {"episodes": 10_000},
        "drqn-her": {"episodes": 10_000},
        "rainbow": {},
        "sac": {},
        "ppo-privileged": {"env_steps": 10_000_000},  # PPO's, so that it differs from PPO in its signals alone
    }
    assert all(budget.get("source") for budget in paper.budgets.values())


def test_every_recorded_cell_was_asked_the_budget_its_preset_plans_today():
    """budgets.toml and the record agree: each copied cell of a preset (bench/results/table/) was
    requested the env steps per seed that its preset plans for it now, so an ablation's budget,
    written in its own preset, is the one its base cell (copied from another preset) trained."""
    from agents.table.files import load_raw
    from agents.table.plan import make_plan
    from agents.table.presets import load_presets

    presets, results = load_presets(), ROOT / "bench" / "results"
    checked = 0
    # not `tuned`: its budgets are agents/tuned/*.toml as they are, which move with tuning
    for name in sorted(p.name for p in (results / "table").iterdir() if p.name != "tuned"):
        for algorithm, cells in load_raw(results, name, {}).items():
            tasks = sorted({files["cell"]["task"] for files in cells.values()})
            plan = {c.directory.name: c for c in make_plan(presets[name], [algorithm], tasks, None, "/nonexistent")}
            for cell_name, files in cells.items():
                requested = files["cell"]["budget"]["requested"]
                assert plan[cell_name].config.total_steps == requested, (name, algorithm, cell_name)
                checked += 1
    assert checked > 100


# --- the observation's cell values -------------------------------------------------------------


def test_the_learners_inputs_class_the_librarys_padding_and_landmark_values():
    from agents.common import inputs
    from snac_jax.observation import LANDMARK_VALUE
    from snac_jax.transition import PADDING

    layout = inputs.ObsLayout(env=None, height_scale=3.0, brick_scale=1.0, step_scale=1.0)
    cells = jnp.array([LANDMARK_VALUE, PADDING, 0, 1, 2, 3, 4, 9], jnp.float32)
    classes = np.asarray(layout.height_classes(cells)).argmax(-1)
    assert classes.tolist() == [0, 1, 2, 3, 4, 5, 6, 6]  # one class each, in order; taller ones share the last
    assert layout.num_height_classes == 7
