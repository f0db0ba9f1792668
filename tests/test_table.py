"""`snac table`: the plan and its estimates, the statistics (against hand-computed values), the
aggregation into table.json / table.md, an ablation's base arm copied from another preset, and
(slow) the smoke preset run, interrupted, resumed, skipped and reported."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from agents.table import ablation, statistics
from agents.table.plan import TRAIN_SEED, format_plan, make_plan
from agents.table.presets import Variant, expand_tasks, load_presets
from agents.table.report import build, markdown
from snac_jax.evaluation import REPORT_EVAL_SEED, TUNING_EVAL_SEED
from tests.table_cells import cell_files as _files
from tests.table_cells import write_record

PRESETS = load_presets()


def _run_cli(argv: list[str]) -> int:
    from agents.table import cli

    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["table", *argv])
    return args.func(args)


# --- plan ----------------------------------------------------------------------------------------


def test_paper_columns_expand_to_environment_tasks():
    assert expand_tasks(["1d-static", "1d-static-sin", "2d-static-dense"]) == [
        "1d-static-sin",
        "1d-static-gauss",
        "1d-static-step",
        "2d-static-dense",
    ]
    with pytest.raises(ValueError, match="unknown task"):
        expand_tasks(["4d-static"])


def test_paper_budgets_and_estimates(tmp_path):
    cells = make_plan(PRESETS["paper"], ["ppo", "drqn", "dqn"], ["1d-static", "2d-static-dense"], 3, tmp_path)
    by = {(c.algorithm, c.task): c for c in cells}
    assert len(cells) == 3 * 4 and {c.status for c in cells} == {"new"}
    # PPO: 10M steps per seed, trained as 152 whole updates of 1024 worlds x 64 steps.
    ppo = by["ppo", "1d-static-gauss"]
    assert ppo.config.total_steps == 10_000_000 and ppo.total_steps == 152 * 1024 * 64
    assert ppo.config.seeds == 3 and ppo.config.seed == TRAIN_SEED
    # DRQN: 10,000 episodes x 750 steps, the whole of it: nothing caps a budget.
    drqn = by["drqn", "1d-static-sin"]
    assert drqn.config.total_steps == 7_500_000
    assert drqn.record()["budget"] == {"env_steps": 7_500_000, "requested": 7_500_000, "source": drqn.budget_source}
    # DQN: 3,000 episodes x 600 steps on 2D.
    assert by["dqn", "2d-static-dense"].config.total_steps == 1_800_000
    # A cell that has not started has no time estimate: nothing measured it.
    assert {(c.estimate_s, c.estimate_from) for c in cells} == {(None, "unknown: not started")}
    text = format_plan(cells, tmp_path)
    assert "x the step limit (1D: 750)" in text
    assert "total estimate: unknown (12 new, 0 partial, 0 done; 12 cells of unknown time)" in text
    assert "7.5M" in text


def test_unknown_keys_are_refused_naming_the_allowed_ones(tmp_path):
    for key in ("wall_limit_minutes = 30", "cheap_seeds = 5"):
        _refused(
            tmp_path / "preset.toml",
            f"[a]\nseeds = 3\n{key}\n",
            rf"unknown field\(s\) \['{key.split()[0]}'\] in a; allowed: description, seeds, .*budgets",
        )
    _refused(
        tmp_path / "budget.toml",
        '[a]\nseeds = 1\n[a.budgets]\ndrqn = { episodes = 10_000, source = "s", wall_limit_minutes = 60 }\n',
        r"unknown field\(s\) \['wall_limit_minutes'\] in a.budgets.drqn; allowed: env_steps, episodes, source",
    )
    _refused(
        tmp_path / "both.toml",
        '[a]\nseeds = 1\n[a.budgets]\ndrqn = { episodes = 10_000, env_steps = 5, source = "s" }\n',
        r"a.budgets.drqn gives env_steps and episodes; one or the other",
    )
    _refused(tmp_path / "seeds.toml", '[a]\nseeds = "3"\n', r"a.seeds must be an int >= 1, got '3'")
    _refused(
        tmp_path / "steps.toml",
        '[a]\n[a.budgets]\ndrqn = { env_steps = 0, source = "s" }\n',
        r"a.budgets.drqn.env_steps must be an int >= 1 or an object, got 0",
    )


def test_a_run_with_another_budget_is_a_run_with_other_settings(tmp_path, monkeypatch):
    """A run with the cell's settings but another total_steps (a smaller one included, as the
    wall-time cap the table once had left) is refused, naming the budgets, never trained over."""
    from agents.training import checkpoint
    from agents.training.config import save_config

    [cell] = make_plan(PRESETS["paper"], ["drqn"], ["1d-static-sin"], 3, tmp_path)
    cell.directory.mkdir(parents=True)
    monkeypatch.setattr(checkpoint, "latest_chunk", lambda directory: 0)  # as if a chunk were saved
    for steps in (1_700_000, 8_000_000):
        save_config(dataclasses.replace(cell.config, total_steps=steps), cell.directory / checkpoint.CONFIG_FILE)
        with pytest.raises(
            ValueError, match=f"holds a run made with other settings \\(total_steps: {steps} there, 7500000 now"
        ):
            make_plan(PRESETS["paper"], ["drqn"], ["1d-static-sin"], 3, tmp_path)
    save_config(cell.config, cell.directory / checkpoint.CONFIG_FILE)
    assert make_plan(PRESETS["paper"], ["drqn"], ["1d-static-sin"], 3, tmp_path)[0].status == "partial"


def test_tuned_preset_keeps_the_tuned_settings(tmp_path):
    from agents.training.registry import make_config

    [cell] = make_plan(PRESETS["tuned"], ["ppo"], ["1d-static-step"], 2, tmp_path)
    tuned = make_config("ppo", "1d-static-step")
    assert cell.config.total_steps == tuned.total_steps and cell.config.rnn_size == tuned.rnn_size
    assert "agents/tuned/ppo.toml" in cell.budget_source


def test_dry_run_prints_the_plan(tmp_path, capsys):
    assert (
        _run_cli(
            [
                "--preset",
                "paper",
                "--algorithms",
                "ppo",
                "drqn",
                "--tasks",
                "1d-static",
                "3d-dynamic-dense",
                "--runs-dir",
                str(tmp_path),
                "--dry-run",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "preset 'paper'" in out and "8 cells, 3 seeds each" in out and "total estimate:" in out
    assert out.count(" new ") == 8 and not any(tmp_path.iterdir())  # nothing started


def test_a_plan_without_estimates_totals_unknown_never_zero(tmp_path, capsys):
    """A sum of no estimates is no estimate: the `multi` preset's plan in an empty runs directory
    (nothing started, nothing measured) read 'total estimate: 0 min 00 s'. Where some cells have an
    estimate and others none, the total is a lower bound."""
    assert _run_cli(["--preset", "multi", "--runs-dir", str(tmp_path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "total estimate: unknown (6 new, 0 partial, 0 done; 6 cells of unknown time)" in out, out
    assert "0 min 00 s" not in out
    cells = make_plan(PRESETS["paper"], ["ppo"], ["1d-static-sin", "2d-static-dense"], 3, tmp_path)
    for estimates, total in [
        ((0.0, None), "unknown (2 new, 0 partial, 0 done; 1 cell of unknown time)"),  # a finished cell adds none
        ((90.0, None), "at least 1 min 30 s (2 new, 0 partial, 0 done; 1 cell of unknown time not counted)"),
        ((90.0, 30.0), "2 min 00 s (2 new, 0 partial, 0 done)"),
        ((0.0, 0.0), "0 min 00 s (2 new, 0 partial, 0 done)"),  # known: nothing left
    ]:
        plan = [dataclasses.replace(c, estimate_s=e) for c, e in zip(cells, estimates)]
        assert f"total estimate: {total}" in format_plan(plan, tmp_path)


# --- statistics ----------------------------------------------------------------------------------


def test_iqm_by_hand():
    # sorted: .1 .2 .3 .4 .5 .7 .8 .9 -> a quarter (2) cut from each end -> mean(.3, .4, .5, .7)
    assert statistics.iqm([0.1, 0.9, 0.5, 0.3, 0.7, 0.2, 0.8, 0.4]) == pytest.approx(0.475)
    assert statistics.iqm([[1.0, 2.0], [3.0, 4.0]]) == pytest.approx(2.5)


def test_bootstrap_intervals():
    assert statistics.stratified_bootstrap_ci([0.7, 0.7, 0.7]) == (pytest.approx(0.7), pytest.approx(0.7))
    # Two seeds 0 and 1: resampled means are 0, 0.5, 1 with probabilities 1/4, 1/2, 1/4.
    assert statistics.stratified_bootstrap_ci([0.0, 1.0]) == (0.0, 1.0)
    values = np.random.default_rng(1).uniform(size=7)
    first = statistics.stratified_bootstrap_ci(values, reps=500, seed=3)
    assert statistics.stratified_bootstrap_ci(values, reps=500, seed=3) == first
    assert statistics.stratified_bootstrap_ci(values, reps=500, seed=4) != first
    assert first[0] < values.mean() < first[1]
    # Stratified: seeds are resampled within each task, so constant tasks give a constant IQM.
    assert statistics.stratified_bootstrap_ci([[0.2, 0.9], [0.2, 0.9]], statistics.iqm_of_runs) == (
        pytest.approx(0.55),
        pytest.approx(0.55),
    )
    with pytest.raises(ValueError, match="finite"):
        statistics.stratified_bootstrap_ci([0.1, np.nan])


def test_difference_intervals_by_hand():
    # Constant arms: the difference is exact.
    assert statistics.difference_summary([0.5, 0.5], [0.2, 0.2]) == {
        "delta": pytest.approx(0.3),
        "ci95": [pytest.approx(0.3)] * 2,
    }
    # Arm seeds 0 and 1 against a constant base 0: resampled differences 0, 0.5, 1 with
    # probabilities 1/4, 1/2, 1/4, so the 2.5th and 97.5th percentiles are 0 and 1.
    assert statistics.difference_summary([0.0, 1.0], [0.0, 0.0, 0.0]) == {"delta": 0.5, "ci95": [0.0, 1.0]}
    assert statistics.difference_summary([0.4, 0.6], [0.7, 0.9])["delta"] == pytest.approx(-0.3)


# --- aggregation ---------------------------------------------------------------------------------


def test_aggregation_by_hand(tmp_path):
    raw = {
        "ppo": {
            "1d-static-sin": _files("ppo", "1d-static-sin", [0.9, 0.6], 1000, walls=(30.0, 60.0)),
            "1d-static-gauss": _files("ppo", "1d-static-gauss", [0.6, 0.6], 1000, walls=(120.0,)),
            "1d-static-step": _files("ppo", "1d-static-step", [0.3, 0.6], 2000, below=True, walls=(100.0, 180.0)),
            "2d-static-dense": _files("ppo", "2d-static-dense", [0.2, 0.4], 1000),  # its curve was not kept
            "2d-static-sparse": _files("ppo", "2d-static-sparse", [0.5, 0.5], 1000),  # no column misses it
        },
        "drqn": {"1d-dynamic": _files("drqn", "1d-dynamic", [0.8], 500)},
    }
    hand = {"1d-static": {"mean": 0.95, "seed": TUNING_EVAL_SEED}}
    table = build(raw, handcrafted=hand, preset="smoke", reps=2000)
    ppo = table["learners"]["ppo"]
    # 1d-static per seed: mean over the three shapes of the same seed index.
    assert ppo["1d-static"]["seeds"] == [pytest.approx(0.6), pytest.approx(0.6)]
    assert ppo["1d-static"]["mean"] == pytest.approx(0.6) and ppo["1d-static"]["ci95"] == [pytest.approx(0.6)] * 2
    assert ppo["1d-static"]["paper"] == 0.776  # the paper's PPO, 1d-static
    assert ppo["1d-static"]["budget"]["env_steps_per_seed"]["1d-static-step"] == 2000
    assert ppo["1d-static"]["budget"]["requested_per_seed"]["1d-static-step"] == 4000
    assert ppo["2d-static-dense"]["mean"] == pytest.approx(0.3) and ppo["2d-static-dense"]["ci95"] == [0.2, 0.4]
    # Training wall: the last cumulative wall_s of each shape, summed (60 + 120 + 180 s = 6 min).
    assert ppo["1d-static"]["budget"]["training_wall_s"] == 360.0
    assert ppo["2d-static-dense"]["budget"]["training_wall_s"] is None
    assert set(ppo) == {"1d-static", "2d-static-dense", "2d-static-sparse"}
    # IQM of the (2 seeds x 3 columns) runs .6 .6 .2 .4 .5 .5: sorted .2 .4 .5 .5 .6 .6, one cut each end.
    assert table["iqm"]["ppo"]["iqm"] == pytest.approx(0.5)
    assert table["iqm"]["ppo"]["tasks"] == 3 and table["iqm"]["drqn"]["iqm"] == pytest.approx(0.8)
    assert table["handcrafted"]["1d-static"]["paper"] == 0.948 and table["human"]["1d-static"]["paper"] == 0.83
    assert table["eval_seed"] == REPORT_EVAL_SEED != TUNING_EVAL_SEED
    text = markdown({"smoke": table}, {"smoke": "test preset"})
    assert "| **ppo** (ours) | 0.600 [0.600, 0.600] |" in text and "(3 of 10 columns)" in text
    assert "| ppo | 2 | 1k–2k* |" in text
    assert "| ppo | 6.0 | — | — |" in text  # the wall-time table, minutes
    # The paper's row shows every column it reports (ours has no 1d-dynamic), its IQM only ours' columns.
    assert table["paper_rows"]["ppo"]["1d-dynamic"] == 0.791 and "| ppo (paper) | 0.776 | 0.791 |" in text
    assert table["iqm"]["ppo"]["paper_columns"] == 3 and "(ours' 3 columns)" in text
    assert table["paper_methods"] == {"ppo": "ppo", "drqn": "drqn"}
    assert f"REPORT_EVAL_SEED = {REPORT_EVAL_SEED}" in text and f"TUNING_EVAL_SEED = {TUNING_EVAL_SEED}" in text


def test_a_column_with_more_seeds_adds_them_to_its_cell_and_not_to_the_iqm():
    raw = {
        "sac": {
            "2d-static-dense": _files("sac", "2d-static-dense", [0.1, 0.2, 0.3, 0.9, 0.9], 1000),
            "2d-static-sparse": _files("sac", "2d-static-sparse", [0.4, 0.5, 0.6], 1000),
        }
    }
    table = build(raw, reps=200)
    assert table["learners"]["sac"]["2d-static-dense"]["mean"] == pytest.approx(0.48)  # all five seeds
    # IQM over seeds 0-2 of both columns: .1 .2 .3 .4 .5 .6, one cut each end -> mean(.2 .3 .4 .5).
    assert table["iqm"]["sac"]["iqm"] == pytest.approx(0.35) and table["iqm"]["sac"]["runs"] == 3
    assert "| sac | 3, 5 |" in markdown({"x": table}, {"x": "test"})


def test_a_new_learner_shows_its_bases_paper_row_under_the_bases_name():
    raw = {
        "ppo-privileged": {"2d-static-sparse": _files("ppo-privileged", "2d-static-sparse", [0.4, 0.5], 1000)},
        "drqn-her": {"2d-static-sparse": _files("drqn-her", "2d-static-sparse", [0.1, 0.2], 1000)},
    }
    table = build(raw, handcrafted={}, preset="smoke", reps=200)
    text = markdown({"smoke": table}, {"smoke": "test preset"})
    assert table["paper_methods"] == {"ppo-privileged": "ppo", "drqn-her": "drqn_her"}
    # The paper's PPO row (every column it reports) beside the privileged learner, named as PPO's.
    assert "| ppo-privileged: its base, the paper's ppo | 0.776 | 0.791 | 0.682 | 0.308 |" in text
    assert "ppo-privileged (paper)" not in text and "| drqn-her (paper) |" in text


def _arm(task: str, arm: str, paper_arm: str, switches: str, means: list[float]) -> dict:
    files = _files("drqn", task, means, 1000)
    files["cell"].update(task=task, variant=arm, paper_variant=paper_arm, switches=switches)
    return files


def test_ablation_preset_has_every_arm_of_the_papers_table():
    preset = PRESETS["ablation"]
    paper = json.loads((Path(__file__).parents[1] / "snac_jax" / "data" / "paper_results.json").read_text())[
        "ablation_drqn"
    ]
    arms = {task: {v.paper for v in preset.variants if task in v.tasks} for task in preset.tasks}
    assert arms == {task: set(paper[task]) - {"source"} for task in paper if task != "source"}
    assert preset.algorithms == ("drqn",) and preset.seeds >= 3
    cells = make_plan(preset, ["drqn"], ["2d-static-sparse"], None, Path("unused"))
    assert [c.directory.name for c in cells] == [
        "2d-static-sparse.base",
        "2d-static-sparse.gps",
        "2d-static-sparse.no-uncertainty",
        "2d-static-sparse.obstacles",
        "2d-static-sparse.landmarks",
    ]
    assert cells[0].config.switches == "" and cells[3].config.env_overrides == {"obstacles": True}
    assert cells[1].record()["paper_variant"] == "+gps" and cells[1].config.total_steps == 10_000 * 600


def test_ablation_report_by_hand():
    raw = {
        "drqn": {
            "2d-static-dense.base": _arm("2d-static-dense", "base", "base", "", [0.5, 0.7]),
            "2d-static-dense.gps": _arm("2d-static-dense", "gps", "+gps", "gps=true", [0.8, 0.8]),
            "3d-static-dense.no-obstacles": _arm(
                "3d-static-dense", "no-obstacles", "-obstacle", "obstacles=false", [0.4]
            ),
        }
    }
    table = ablation.build(raw, arms=["base", "gps", "no-obstacles"], preset="ablation", reps=2000)
    dense = table["ablation"]["drqn"]["2d-static-dense"]
    assert list(dense) == ["base", "gps"] and dense["base"]["paper"] == 0.772 and "delta" not in dense["base"]
    # gps: 0.8 - mean(0.5, 0.7); the base's resampled means are 0.5, 0.6, 0.7 -> differences 0.3 .. 0.1.
    assert dense["gps"]["delta"] == {"delta": pytest.approx(0.2), "ci95": [pytest.approx(0.1), pytest.approx(0.3)]}
    assert dense["gps"]["paper"] == 0.079  # the paper's change from its base
    assert table["ablation"]["drqn"]["3d-static-dense"]["no-obstacles"]["delta"] is None  # no base cell yet
    text = "\n".join(ablation.section(table, "test"))
    assert (
        "| drqn | 2d-static-dense | gps (+gps) | `gps=true` | 0.800 [0.800, 0.800] | +0.200 [+0.100, +0.300] | +0.079 | 1k |"
        in text
    )
    assert "| drqn | 2d-static-dense | base (base) | `—` | 0.600 [0.500, 0.700] | — | 0.772 | 1k |" in text
    assert "## Preset `ablation`: test" in markdown({"ablation": table}, {"ablation": "test"})
    assert "another cell trained" not in text
    raw["drqn"]["2d-static-dense.base"]["cell"]["adopted_from"] = "paper/drqn/2d-static-dense"
    text = "\n".join(ablation.section(ablation.build(raw, arms=["base", "gps"], preset="ablation", reps=200), "test"))
    assert "Arms whose run another cell trained: " in text
    assert "scored that run again: drqn on 2d-static-dense (base): `paper/drqn/2d-static-dense`." in text


def test_an_arm_trained_another_number_of_steps_than_its_base_has_no_delta():
    raw = {
        "drqn": {
            "2d-static-dense.base": _arm("2d-static-dense", "base", "base", "", [0.5, 0.7]),
            "2d-static-dense.gps": _arm("2d-static-dense", "gps", "+gps", "gps=true", [0.8, 0.8]),
        }
    }
    assert ablation.build(raw, arms=["base", "gps"], reps=20)["ablation"]["drqn"]["2d-static-dense"]["gps"]["delta"]
    raw["drqn"]["2d-static-dense.base"]["config"]["total_steps"] *= 2  # a base retrained at a larger budget
    table = ablation.build(raw, arms=["base", "gps"], reps=20)
    assert table["ablation"]["drqn"]["2d-static-dense"]["gps"]["delta"] is None


def test_ablation_report_keeps_unknown_arms_and_gives_paper_values_to_drqn_only():
    raw = {
        "drqn": {
            "2d-static-dense.base": _arm("2d-static-dense", "base", "base", "", [0.5]),
            "2d-static-dense.renamed": _arm("2d-static-dense", "renamed", "+gps", "gps=true", [0.7]),
        },
        "ppo": {"2d-static-dense.base": _arm("2d-static-dense", "base", "base", "", [0.4])},
        "drqn-aux": {"2d-static-dense.base": _arm("2d-static-dense", "base", "base", "", [0.6])},
    }
    table = ablation.build(raw, arms=["base", "gps"], reps=200)
    assert list(table["ablation"]["drqn"]["2d-static-dense"]) == ["base", "renamed"]  # an arm budgets.toml lost
    assert table["ablation"]["drqn"]["2d-static-dense"]["renamed"]["paper"] == 0.079
    assert table["ablation"]["ppo"]["2d-static-dense"]["base"]["paper"] is None  # the paper ablated DRQN
    assert (
        table["ablation"]["drqn-aux"]["2d-static-dense"]["base"]["paper"] is None
    )  # DRQN's paper row, another learner


def _refused(path: Path, text: str, match: str) -> None:
    """budgets.toml text that load_presets refuses, with a message matching `match`."""
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        load_presets(path)


def test_ablation_presets_are_checked_when_loaded(tmp_path):
    base = '[a]\nseeds = 1\n[a.variants.base]\npaper = "base"\nswitches = ""\ntasks = ["1d-static"]\n'
    (tmp_path / "ok.toml").write_text(base)
    assert load_presets(tmp_path / "ok.toml")["a"].variants[0].tasks == (
        "1d-static-sin",
        "1d-static-gauss",
        "1d-static-step",
    )
    _refused(tmp_path / "nobase.toml", base.replace("variants.base", "variants.gps"), "needs an arm named base")
    _refused(
        tmp_path / "bad.toml",
        base.replace('switches = ""', 'switches = "gpss=true"'),
        r"\[a.variants.base\]: unknown switch 'gpss'",
    )
    with pytest.raises(ValueError, match="no arm of preset 'ablation' runs on 1d-dynamic"):
        make_plan(PRESETS["ablation"], ["drqn"], ["1d-dynamic"], None, tmp_path)


def test_a_budget_per_environment_task(tmp_path):
    text = (
        "[b]\nseeds = 1\n[b.budgets]\n"
        'pqn = { env_steps = { "1d-dynamic" = 3_000_000, "2d-static-sparse" = 9_000_000 }, source = "why" }\n'
    )
    (tmp_path / "ok.toml").write_text(text)
    preset = load_presets(tmp_path / "ok.toml")["b"]
    cells = make_plan(preset, ["pqn"], ["1d-dynamic", "2d-static-sparse"], None, tmp_path)
    assert cells[0].budget_source == "b: why"
    assert [c.config.total_steps for c in cells] == [3_000_000, 9_000_000]
    with pytest.raises(
        ValueError, match="the b preset gives pqn a budget on 1d-dynamic, 2d-static-sparse only, not on 2d-static-dense"
    ):
        make_plan(preset, ["pqn"], ["2d-static-dense"], None, tmp_path)
    _refused(
        tmp_path / "typo.toml",
        text.replace('"1d-dynamic"', '"1d-dynamo"'),
        r"unknown field\(s\) \['1d-dynamo'\] in b.budgets.pqn.env_steps; allowed: 1d-static-sin",
    )


def test_an_arm_can_switch_a_learner_setting_off():
    """The privileged-ablation preset's arms change learner settings, not the environment: each
    arm's config differs from the base arm's in its settings alone, and the report prints them."""
    preset = PRESETS["privileged-ablation"]
    cells = {
        c.variant.name: c for c in make_plan(preset, ["ppo-privileged"], ["2d-static-sparse"], None, Path("unused"))
    }
    assert list(cells) == ["base", "no-critic", "no-position", "curriculum"]
    base = cells["base"].config.to_json()
    changed = {name: {k: v for k, v in cell.config.to_json().items() if base[k] != v} for name, cell in cells.items()}
    assert changed == {
        "base": {},
        "no-critic": {"privileged_critic": False},
        "no-position": {"position_coef": 0.0},
        "curriculum": {"stride_curriculum": 0.5},
    }
    assert cells["base"].config.privileged_critic and cells["base"].config.position_coef > 0
    assert cells["no-critic"].record()["settings"] == {"privileged_critic": False}

    files = _arm("2d-static-sparse", "no-critic", "", "", [0.4])
    files["cell"]["settings"] = {"privileged_critic": False}
    table = ablation.build(
        {"ppo-privileged": {"2d-static-sparse.no-critic": files}}, arms=["base", "no-critic"], reps=200
    )
    text = "\n".join(ablation.section(table, "test"))
    assert (
        "| ppo-privileged | 2d-static-sparse | no-critic | `privileged_critic=false` | 0.400 [0.400, 0.400] | — | — |"
        in text
    )


def test_arms_runs_only_the_named_arms_and_refuses_unknown_ones():
    """`--arms` plans the named arms alone (an arm whose run is the same as another preset's cell
    need not train again); an unknown arm, or arms of a preset without any, fail naming the arms."""
    preset = PRESETS["privileged-ablation"]
    cells = make_plan(
        preset,
        ["ppo-privileged"],
        ["2d-static-sparse"],
        None,
        Path("unused"),
        arms=["no-position", "no-critic"],
    )
    assert [c.variant.name for c in cells] == ["no-critic", "no-position"]
    with pytest.raises(ValueError, match="no arm.*'no-gps'.*its arms: base, no-critic, no-position, curriculum"):
        make_plan(preset, ["ppo-privileged"], ["2d-static-sparse"], None, Path("unused"), arms=["no-gps"])
    with pytest.raises(ValueError, match="not an ablation"):
        make_plan(PRESETS["paper"], ["ppo"], ["1d-dynamic"], None, Path("unused"), arms=["base"])
    with pytest.raises(
        ValueError, match="needs at least one arm named; its arms: base, no-critic, no-position, curriculum"
    ):
        make_plan(preset, ["ppo-privileged"], ["2d-static-sparse"], None, Path("unused"), arms=[])
    with pytest.raises(
        ValueError,
        match=r"no arm named in --arms of preset 'ablation' runs on 3d-static-dense; "
        r"their tasks: gps: 2d-static-dense, 2d-static-sparse$",
    ):
        make_plan(PRESETS["ablation"], ["drqn"], ["3d-static-dense"], None, Path("unused"), arms=["gps"])


def test_an_arm_with_an_unknown_key_or_setting_is_refused(tmp_path):
    arm = '[a]\nseeds = 1\n[a.variants.base]\ntasks = ["1d-static-sin"]\n'
    _refused(
        tmp_path / "typo.toml",
        arm.replace("tasks =", "setting = { x = 1 }\ntasks ="),
        r"unknown field\(s\) \['setting'\] in a.variants.base; allowed: paper, switches",
    )
    _refused(
        tmp_path / "planned.toml",
        arm.replace("tasks =", "settings = { seeds = 1 }\ntasks ="),
        r"settings may not set \['seeds'\]: the plan sets seed, seeds, switches",
    )
    (tmp_path / "option.toml").write_text(arm.replace("tasks =", "settings = { no_such_option = 1 }\ntasks ="))
    preset = load_presets(tmp_path / "option.toml")["a"]
    with pytest.raises(ValueError, match=r"unknown ppo option\(s\) \['no_such_option'\]"):
        make_plan(preset, ["ppo"], ["1d-static-sin"], None, tmp_path)


# --- the smoke preset, end to end ----------------------------------------------------------------


def _abl(**changes):
    """An ablation of the smoke preset on 1d-static-sin: its base arm and a gps arm."""
    arms = (
        Variant(name="base", paper="base", switches="", tasks=("1d-static-sin", "1d-static-gauss")),
        Variant(name="gps", paper="+gps", switches="gps=true", tasks=("1d-static-sin",)),
    )
    return dataclasses.replace(PRESETS["smoke"], **{"name": "abl", "variants": arms, **changes})


@pytest.mark.slow  # two tiny trainings, a resume and four evaluations: ~1 min on a loaded 2-core CPU
def test_smoke_grid_interrupted_resumed_skipped_and_reported(tmp_path, capsys, monkeypatch):
    from agents.table import run as table_run
    from agents.table.report import write_report
    from agents.training import checkpoint

    runs, results = tmp_path / "runs", tmp_path / "results"
    smoke = PRESETS["smoke"]
    first, second = make_plan(smoke, ["ppo"], ["1d-static-sin", "1d-static-gauss"], None, runs)
    assert table_run.run_cells([first], progress=False) == 1
    assert not table_run.run_cell(second, progress=False, stop_after_chunks=1)  # "killed" after 1 of 4 chunks

    cells = make_plan(smoke, ["ppo"], ["1d-static-sin", "1d-static-gauss"], None, runs)
    assert [c.status for c in cells] == ["done", "partial"] and cells[1].done_steps == 2048 // 4
    assert "25% done" in format_plan(cells, runs) and "this run's metrics.jsonl" in cells[1].estimate_from
    before = (cells[0].directory / "eval.json").stat().st_mtime_ns
    calls = []
    import agents.training.driver as driver

    real_train = driver.train

    def spy(config, out_dir, **kwargs):
        calls.append((config.task, kwargs["resume"]))
        return real_train(config, out_dir, **kwargs)

    monkeypatch.setattr(driver, "train", spy)
    assert table_run.run_cells(cells, progress=False) == 2
    assert calls == [("1d-static-gauss", True)]
    assert (cells[0].directory / "eval.json").stat().st_mtime_ns == before  # the finished cell was skipped
    metrics = [json.loads(x) for x in (cells[1].directory / "metrics.jsonl").read_text().splitlines()]
    assert [r["chunk"] for r in metrics] == [0, 1, 2, 3]
    evals = json.loads((cells[1].directory / "eval.json").read_text())
    assert len(evals) == 2 and {r["seed"] for r in evals.values()} == {REPORT_EVAL_SEED}

    with pytest.raises(ValueError, match="seeds: 2 there, 3 now"):
        make_plan(smoke, ["ppo"], ["1d-static-sin"], 3, runs)

    paths = write_report("smoke", runs, results, reps=200)
    table = json.loads(paths["json"].read_text())["smoke"]
    assert table["learners"] == {"ppo": {}}  # 1d-static-step is missing: no column is complete
    copied = sorted(p.relative_to(results).as_posix() for p in (results / "table").rglob("*") if p.is_file())
    assert copied == [f"table/smoke/ppo/{t}.json" for t in ("1d-static-gauss", "1d-static-sin")]
    for task, source in (("1d-static-sin", cells[0].directory), ("1d-static-gauss", cells[1].directory)):
        record = json.loads((results / "table" / "smoke" / "ppo" / f"{task}.json").read_text())
        assert list(record) == ["cell", "config", "eval", "curve"]  # the whole record in one file
        assert record["eval"] == json.loads((source / "eval.json").read_text())
        assert record["config"] == json.loads((source / "config.json").read_text())
        assert record["curve"] == checkpoint.read_metrics_lines(source / "metrics.jsonl")
    assert "## Preset `smoke`" in paths["md"].read_text() and paths["png:smoke"].stat().st_size > 0


@pytest.mark.slow  # three tiny trainings and six evaluations
def test_ablation_smoke_grid_trains_each_arm_with_its_switches_and_reports(tmp_path):
    from agents.table import run as table_run
    from agents.table.report import write_report

    runs, results = tmp_path / "runs", tmp_path / "results"
    arms = (
        Variant(name="base", paper="base", switches="", tasks=("1d-static-sin",)),
        Variant(name="gps", paper="+gps", switches="gps=true", tasks=("1d-static-sin",)),
        Variant(name="no-uncertainty", paper="-uncertainty", switches="stride_probs=1/0/0", tasks=("1d-static-sin",)),
    )
    preset = dataclasses.replace(PRESETS["smoke"], name="ablation", variants=arms)
    cells = make_plan(preset, ["ppo"], ["1d-static-sin"], None, runs)
    assert table_run.run_cells(cells, progress=False) == 3
    stored = json.loads((runs / "ablation" / "ppo" / "1d-static-sin.gps" / "config.json").read_text())
    assert stored["switches"] == "gps=true"
    assert make_plan(preset, ["ppo"], ["1d-static-sin"], None, runs)[1].status == "done"

    paths = write_report("ablation", runs, results, reps=200)
    table = json.loads(paths["json"].read_text())["ablation"]
    rows = table["ablation"]["ppo"]["1d-static-sin"]
    assert list(rows) == ["base", "gps", "no-uncertainty"] and rows["gps"]["delta"] is not None
    assert (
        "png:ablation" not in paths and "| ppo | 1d-static-sin | gps (+gps) | `gps=true` |" in paths["md"].read_text()
    )
    # no per-column figure for an ablation, but each arm's learning curve, from the copied metrics
    assert (
        paths["png:ablation-curves"] == results / "table-ablation-curves.png"
        and paths["png:ablation-curves"].stat().st_size
    )
    assert "Learning curves of the arms: `table-ablation-curves.png`" in paths["md"].read_text()


# --- a hand-made record --------------------------------------------------------------------------


def _gps_arm_copy(results, record):
    """The raw copy of `_abl()`'s gps arm, written by hand from the smoke preset's `record`."""
    arm = results / "table" / "abl" / "ppo" / "1d-static-sin.gps.json"
    arm.parent.mkdir(parents=True, exist_ok=True)
    arm.write_text(
        record.read_text()
        .replace('"preset": "smoke"', '"preset": "abl"')
        .replace(
            '"column": "1d-static",',
            '"column": "1d-static", "variant": "gps", "paper_variant": "+gps", "switches": "gps=true", "settings": {},',
        )
        .replace('"switches": ""', '"switches": "gps=true"')
    )
    return arm


def _abl_report(results, monkeypatch) -> dict:
    from agents.table import report

    monkeypatch.setattr(report, "load_presets", lambda: {**load_presets(), "abl": _abl()})
    report.write_report("abl", None, results, reps=200)
    return json.loads((results / "table.json").read_text())["abl"]["ablation"]["ppo"]["1d-static-sin"]


def test_a_hand_made_record_gives_the_expected_rows_and_marks_a_budget_below_its_request(tmp_path):
    """Two cells copied by hand (one trained half the budget its preset asked): the report's
    rows, their `*`, and the README's learner table from them."""
    from agents.table.readme import BEGIN, END, write_readme
    from agents.table.report import write_report

    results = tmp_path / "results"
    cells = make_plan(PRESETS["smoke"], ["ppo"], ["2d-static-dense", "2d-static-sparse"], None, tmp_path / "runs")
    below = write_record(results, cells[0], means=(0.5, 0.7))  # as the wall-time cap once left it
    below.write_text(below.read_text().replace('"requested": 2048', '"requested": 4096'))
    write_record(results, cells[1], means=(0.2, 0.4))
    paths = write_report("smoke", None, results, reps=200)
    table = json.loads(paths["json"].read_text())["smoke"]
    dense, sparse = table["learners"]["ppo"]["2d-static-dense"], table["learners"]["ppo"]["2d-static-sparse"]
    assert dense["mean"] == pytest.approx(0.6) and dense["seeds"] == [0.5, 0.7] and sparse["mean"] == pytest.approx(0.3)
    assert dense["budget"]["requested_per_seed"] == {"2d-static-dense": 4096}
    assert table["iqm"]["ppo"]["tasks"] == 2 and table["iqm"]["ppo"]["iqm"] == pytest.approx(0.45)
    md = paths["md"].read_text()
    assert "| ppo | 2 | — | — | 2.05k* | 2.05k | —" in md  # env steps per seed, `*`: below the request
    assert "| ppo | — | — | 0.1 | 0.1 | —" in md  # minutes of training, from the curves (8 s each)
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{BEGIN}\nold\n{END}\n")
    write_readme(readme, json.loads(paths["json"].read_text()))
    assert (
        "| ppo (smoke preset) | 2.05k*, 2.05k | — (0.776) | — (0.791) | 0.600 [0.500, 0.700] (0.682) |"
        in readme.read_text()
    )


def test_an_ablations_base_arm_is_its_own_copy_naming_the_run_it_was_copied_from(tmp_path, monkeypatch):
    """The report reads an ablation's base row from the ablation's own folder (a copy of another
    preset's cell names it in `adopted_from`, and the page says so); where the ablation has no
    base copy, no other preset's cell stands in for it: no base row, no Δ."""
    runs, results = tmp_path / "runs", tmp_path / "results"
    [source] = make_plan(PRESETS["smoke"], ["ppo"], ["1d-static-sin"], None, runs)
    path = write_record(results, source)
    _gps_arm_copy(results, path)
    rows = _abl_report(results, monkeypatch)
    assert list(rows) == ["gps"] and rows["gps"]["delta"] is None
    own = json.loads(path.read_text())
    own["cell"].update(preset="abl", variant="base", paper_variant="base", switches="", settings={})
    own["cell"]["adopted_from"] = "smoke/ppo/1d-static-sin"
    own["eval"] = {k: {**v, "mean": 0.3, "min": 0.1, "ci95": [0.25, 0.35]} for k, v in own["eval"].items()}
    (results / "table" / "abl" / "ppo" / "1d-static-sin.base.json").write_text(json.dumps(own))
    rows = _abl_report(results, monkeypatch)
    assert rows["base"]["adopted_from"] == "smoke/ppo/1d-static-sin" and rows["base"]["mean"] == pytest.approx(0.3)
    assert rows["gps"]["delta"]["delta"] == pytest.approx(0.6 - 0.3)
    assert "(base): `smoke/ppo/1d-static-sin`." in (results / "table.md").read_text()


def test_the_cli_plans_an_ablations_base_arm_as_its_own_cell(tmp_path, capsys):
    """landmark-action's pqn-belief arms, its base included, are cells of its own at the beyond
    preset's budget on the sparse 2D tasks; a dry run writes nothing."""
    runs = tmp_path / "runs"
    argv = ["--preset", "landmark-action", "--algorithms", "pqn-belief", "--tasks", "2d-static-sparse"]
    assert _run_cli([*argv, "--runs-dir", str(runs), "--dry-run"]) == 0
    out = capsys.readouterr().out
    rows = [line.split()[:5] for line in out.splitlines() if line.startswith("pqn-belief")]
    assert rows == [
        ["pqn-belief", "2d-static-sparse.base", "20M", "3", "new"],
        ["pqn-belief", "2d-static-sparse.landmark-action", "20M", "3", "new"],
    ]
    assert "(2 new, 0 partial, 0 done" in out and not runs.exists()
