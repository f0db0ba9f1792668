"""`snac table`'s arms that change only how a trained policy acts when scored
(`Variant.evaluation`): checked where the preset is loaded and planned (acting options only; a
base run to score), never scoring a raw copy (no params), refused when a finished cell was scored
otherwise, printed "at evaluation" in the report, and (slow) scoring the base arm's run again
with the arm's settings, without training, across a kill before scoring."""

from __future__ import annotations

import dataclasses
import json

import pytest

from agents.table import ablation
from agents.table.plan import make_plan, scoring_config
from agents.table.presets import Variant, load_presets
from snac_jax.evaluation import REPORT_EVAL_SEED
from tests.table_cells import cell_files

PRESETS = load_presets()
SMOKE_TASK = "1d-static-sin"


@pytest.fixture
def gamma_acts(monkeypatch):
    """PPO, the cheapest learner, has no acting option; the tests of the table's mechanics give it
    one (gamma, which changes nothing at evaluation) rather than train a learner that has one."""
    from agents.learners.ppo import PPOConfig

    monkeypatch.setattr(PPOConfig, "acting_options", ("gamma",))


def _scored_again(**evaluation) -> Variant:
    return Variant(name="acting", paper="", switches="", tasks=(SMOKE_TASK,), evaluation=evaluation)


def _abl(evaluation: dict) -> object:
    """An ablation of the smoke preset: its base arm, and an arm scored acting with `evaluation`."""
    arms = (Variant(name="base", paper="base", switches="", tasks=(SMOKE_TASK,)), _scored_again(**evaluation))
    return dataclasses.replace(PRESETS["smoke"], name="abl", variants=arms)


def test_the_safe_drops_arm_at_evaluation_trains_as_the_base_and_acts_with_the_mask(tmp_path):
    preset = PRESETS["safe-drops"]
    assert [v.name for v in preset.variants] == ["base", "safe", "at-evaluation"]
    arms = {v.name: v for v in preset.variants}
    base, acting = make_plan(preset, ["pqn-belief"], ["3d-dynamic-sparse"], None, tmp_path, ["base", "at-evaluation"])
    assert acting.config == base.config and not acting.config.safe_drops  # the same training
    assert acting.base_run == base.directory  # the base arm trains here first: no beyond run
    assert arms["at-evaluation"].evaluation == {"safe_drops": True} and arms["safe"].evaluation == {}
    assert scoring_config(acting.config, acting.evaluation) == dataclasses.replace(acting.config, safe_drops=True)
    # Planned without its base arm, where no base run is there, it is refused: no params to score.
    with pytest.raises(ValueError, match="train it first"):
        make_plan(preset, ["pqn-belief"], ["3d-dynamic-sparse"], None, tmp_path, arms=["at-evaluation"])
    cells = make_plan(preset, ["pqn-belief"], ["3d-dynamic-sparse"], None, tmp_path, arms=["base", "safe"])
    assert [c.evaluation for c in cells] == [{}, {}] and "evaluation" not in cells[0].record()


def test_an_arm_scored_otherwise_is_checked_when_loaded_and_planned(tmp_path):
    head = '[a]\nseeds = 1\nalgorithms = ["pqn"]\n'
    base = '[a.variants.base]\ntasks = ["2d-static-dense"]\n'
    arm = '[a.variants.b]\ntasks = ["2d-static-dense"]\n'
    for name, text, message in [
        (
            "both",
            head + base + arm + "evaluation = { safe_drops = true }\nsettings = { gamma = 0.9 }\n",
            r"\[a.variants.b\]: an arm with evaluation settings scores the base arm's run: no settings or switches",
        ),
        (
            "switches",
            head + base + arm + 'evaluation = { safe_drops = true }\nswitches = "obstacles=true"\n',
            "no settings or switches",
        ),
        ("base scored", head + base + "evaluation = { safe_drops = true }\n", "the base arm trains the run"),
        (
            "planned",
            head + base + arm + "evaluation = { seeds = 2 }\n",
            r"evaluation may not set \['seeds'\]: the plan sets seed, seeds, switches, task, total_steps$",
        ),
    ]:
        (tmp_path / f"{name}.toml").write_text(text)
        with pytest.raises(ValueError, match=message):
            load_presets(tmp_path / f"{name}.toml")
    # What the learner refuses is refused when planned, before anything trains: an option that is
    # not one of its acting options, and the mask on a task without the obstacle rule.
    for lines, message in [
        (
            "evaluation = { gamma = 0.5 }\n",
            r"pqn cannot act with \['gamma'\] at evaluation: .*"
            r"pqn's: safe_drops$",
        ),
        ("evaluation = { safe_drops = true }\n", "obstacle"),
    ]:
        (tmp_path / "learner.toml").write_text(head + base + arm + lines)
        with pytest.raises(ValueError, match=message):
            make_plan(load_presets(tmp_path / "learner.toml")["a"], ["pqn"], ["2d-static-dense"], None, tmp_path)
    with pytest.raises(ValueError, match=r"ppo cannot act with \['gamma'\] at evaluation: .* ppo's: none$"):
        make_plan(_abl({"gamma": 0.5}), ["ppo"], [SMOKE_TASK], None, tmp_path)


def test_an_arm_that_scores_the_policy_again_needs_its_base_arms_run(tmp_path, gamma_acts):
    """Planned without its base arm, it is refused where no run of the base arm is there (the
    record's copy of a cell holds no checkpoint to score); planned with it, it waits for it."""
    runs = tmp_path / "runs"
    with pytest.raises(
        ValueError,
        match=r"arm 'acting' of preset 'abl' scores the base arm's run again: .* train it first "
        r"\(snac table --preset abl --tasks 1d-static-sin\) or leave the arm out \(--arms\)",
    ):
        make_plan(_abl({"gamma": 0.5}), ["ppo"], [SMOKE_TASK], None, runs, arms=["acting"])
    base, acting = make_plan(_abl({"gamma": 0.5}), ["ppo"], [SMOKE_TASK], None, runs)
    assert (base.status, acting.status, acting.base_run) == ("new", "new", base.directory)


def test_a_finished_cell_scored_with_other_settings_is_refused(tmp_path, gamma_acts):
    """Its own files back without checkpoints; the branch of a run with its checkpoints is the
    slow test's."""
    runs, preset = tmp_path / "runs", _abl({"gamma": 0.5})
    [base, acting] = make_plan(preset, ["ppo"], [SMOKE_TASK], None, runs)
    config, directory = acting.config, acting.directory
    directory.mkdir(parents=True)
    row = {
        "min": 0.1,
        "std": 0.1,
        "ci95": [0.4, 0.6],
        "episodes": 2,
        "mean_length": 40.0,
        "mean_bricks_used": 3.0,
        "mean_return": 1.0,
        "per_design": {},
        "seed": REPORT_EVAL_SEED,
        "wall_s": 1.0,
    }
    evaluation = {
        f"{SMOKE_TASK} (seed {i})": {"task": f"{SMOKE_TASK} (seed {i})", "mean": 0.5, **row} for i in range(2)
    }
    record = {
        "preset": "abl",
        "algorithm": "ppo",
        "column": "1d-static",
        "task": SMOKE_TASK,
        "budget": acting.record()["budget"],
        "eval_seed": REPORT_EVAL_SEED,
        "protocol": preset.protocol,
        "variant": "acting",
        "paper_variant": "",
        "switches": "",
        "settings": {},
    }  # scored as it trained
    for name, content in (("config.json", config.to_json()), ("cell.json", record), ("eval.json", evaluation)):
        (directory / name).write_text(json.dumps(content))
    (directory / "metrics.jsonl").write_text(
        "".join(json.dumps({"chunk": i, "env_steps": 512 * (i + 1), "wall_s": 1.0 + i}) + "\n" for i in range(4))
    )
    with pytest.raises(
        ValueError,
        match=r"abl/ppo/1d-static-sin.acting was scored acting with its training settings, "
        r"the arm now asks \{'gamma': 0.5\}; move that directory away",
    ):
        make_plan(preset, ["ppo"], [SMOKE_TASK], None, runs, arms=["acting"])
    (directory / "cell.json").write_text(json.dumps({**record, "evaluation": {"gamma": 0.5}}))
    [again] = make_plan(preset, ["ppo"], [SMOKE_TASK], None, runs, arms=["acting"])
    assert again.status == "done"


def test_the_report_prints_an_arms_settings_at_evaluation():
    files = cell_files("pqn-belief", "3d-dynamic-sparse", [0.5, 0.6, 0.55], 1000)
    files["cell"].update(
        task="3d-dynamic-sparse",
        variant="at-evaluation",
        paper_variant="",
        switches="",
        settings={},
        evaluation={"safe_drops": True},
    )
    table = ablation.build(
        {"pqn-belief": {"3d-dynamic-sparse.at-evaluation": files}}, arms=["base", "at-evaluation"], reps=200
    )
    text = "\n".join(ablation.section(table, "test"))
    assert "| pqn-belief | 3d-dynamic-sparse | at-evaluation | `safe_drops=true at evaluation` | 0.550" in text
    assert 'an arm whose settings say "at evaluation" trains as the base arm' in text
    del files["cell"]["evaluation"]  # a section without such an arm does not explain them
    table = ablation.build({"pqn-belief": {"3d-dynamic-sparse.at-evaluation": files}}, arms=["base"], reps=200)
    assert "at evaluation" not in "\n".join(ablation.section(table, "test"))


@pytest.mark.slow  # one tiny training and two evaluations
def test_an_arm_scored_otherwise_takes_over_the_run_and_scores_its_params_acting_so(tmp_path, monkeypatch, gamma_acts):
    import jax
    import numpy as np

    import agents.training.cli
    import agents.training.driver
    from agents.table import run as table_run
    from agents.training import checkpoint
    from agents.training.trained import load_trained

    runs = tmp_path / "runs"
    source, acting = make_plan(_abl({"gamma": 0.5}), ["ppo"], [SMOKE_TASK], None, runs)
    assert table_run.run_cell(source, progress=False)  # the base arm, whose run the other arm scores
    assert acting.base_run == source.directory and "again: unknown" in acting.estimate_from

    scored, trained = [], []
    real_evaluate = agents.training.cli.evaluate_run

    def evaluate_spy(algorithm, state, out_dir, *args, **kwargs):
        scored.append((algorithm.config, state.params))
        if len(scored) == 1:
            raise KeyboardInterrupt  # killed after the copy, before scoring
        return real_evaluate(algorithm, state, out_dir, *args, **kwargs)

    monkeypatch.setattr(agents.training.cli, "evaluate_run", evaluate_spy)
    monkeypatch.setattr(agents.training.driver, "train", lambda *a, **k: trained.append(1))
    with pytest.raises(KeyboardInterrupt):
        table_run.run_cell(acting, progress=False)
    assert not (acting.directory / "eval.json").exists()
    [acting] = make_plan(_abl({"gamma": 0.5}), ["ppo"], [SMOKE_TASK], None, runs, ["acting"])
    assert acting.status == "new"  # its scoring cut short: scored again
    assert table_run.run_cell(acting, progress=False)
    # Never trained: the base run's params, scored with gamma 0.5, beside its metrics.
    assert trained == [] and len(scored) == 2
    assert checkpoint.read_metrics_lines(acting.directory / "metrics.jsonl") == checkpoint.read_metrics_lines(
        source.directory / "metrics.jsonl"
    )
    assert not (acting.directory / "checkpoints").exists()
    config, params = scored[1]
    assert config == dataclasses.replace(source.config, gamma=0.5)
    _, trained_state, _ = load_trained(source.directory)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(trained_state.params)))
    cell = json.loads((acting.directory / "cell.json").read_text())
    assert (cell["evaluation"], cell["adopted_from"]) == ({"gamma": 0.5}, "abl/ppo/1d-static-sin.base")
    evals = json.loads((acting.directory / "eval.json").read_text())
    assert {r["seed"] for r in evals.values()} == {REPORT_EVAL_SEED}
    assert json.loads((acting.directory / "config.json").read_text()) == source.config.to_json()  # as it trained
    [again] = make_plan(_abl({"gamma": 0.5}), ["ppo"], [SMOKE_TASK], None, runs, arms=["acting"])
    assert again.status == "done"
    with pytest.raises(ValueError, match=r"was scored acting with \{'gamma': 0.5\}, the arm now asks \{'gamma': 0.9\}"):
        make_plan(_abl({"gamma": 0.9}), ["ppo"], [SMOKE_TASK], None, runs, arms=["acting"])
