"""Sweeps in one program (`agents.training.sweep`, `snac train --sweep`): each arm trains as a separate run
of its settings would, a sweep resumes like any run, and a setting that would need another
program per arm is refused in one line before anything runs."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from agents.training import driver
from agents.training.registry import make_config
from agents.training.sweep import Sweep, check_traceable, parse_sweep

TINY = dict(
    num_envs=8,
    rollout_steps=8,
    num_minibatches=2,
    update_epochs=1,
    hidden_size=8,
    rnn_size=8,
    total_steps=256,
    chunks=2,
    max_steps=30,
    seeds=2,
)
VALUES = (1e-3, 3e-2)


def _config(**overrides):
    return make_config("ppo", "1d-static-sin", **{**TINY, **overrides})


def _records(out_dir):
    return driver.read_metrics(out_dir)


def _assert_same_learning(a: list[dict], b: list[dict]) -> None:
    """The same chunks and, to float rounding, every per-seed measurement (episodes, IoU and
    return means, every loss)."""
    assert [r["chunk"] for r in a] == [r["chunk"] for r in b]
    for ra, rb in zip(a, b):
        measured = {name for name, value in ra.items() if isinstance(value, list)}
        assert measured == {name for name, value in rb.items() if isinstance(value, list)} and "loss" in measured
        for name in measured:
            np.testing.assert_allclose(
                np.asarray(ra[name], float),
                np.asarray(rb[name], float),
                rtol=2e-4,
                atol=1e-6,
                err_msg=f"chunk {ra['chunk']} {name}",
            )


@pytest.fixture(scope="module")
def sweep_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("sweep")
    config = _config()
    swept = parse_sweep([f"learning_rate={','.join(map(str, VALUES))}"], config)
    driver.train(config, base / "sweep", progress=False, swept=swept)
    return base, config, swept


@pytest.mark.slow  # over 10 s on the 2-core CPU: `pytest -m slow` (CI runs both)
def test_a_sweep_of_two_values_and_two_seeds_equals_the_separate_runs(sweep_run):
    base, config, swept = sweep_run
    assert swept.num_arms == 2 and swept.arms == ((VALUES[0],), (VALUES[1],))
    run = base / "sweep"
    assert json.loads((run / "sweep.json").read_text()) == {
        "names": ["learning_rate"],
        "arms": [[VALUES[0]], [VALUES[1]]],
    }
    for arm, value in enumerate(VALUES):
        arm_config = json.loads((run / "arms" / str(arm) / "config.json").read_text())
        assert arm_config["learning_rate"] == value and arm_config["seeds"] == 2
        driver.train(_config(learning_rate=value), base / f"single-{arm}", progress=False)
        _assert_same_learning(_records(run / "arms" / str(arm)), _records(base / f"single-{arm}"))
    # the arms learned differently: the values reached the learner
    losses = [np.asarray(_records(run / "arms" / str(arm))[-1]["loss"]) for arm in range(2)]
    assert not np.allclose(losses[0], losses[1])
    whole = _records(run)
    assert len(whole[-1]["iou"]) == 4  # arms x seeds, arm-major, in the run's own metrics


@pytest.mark.slow
def test_a_stopped_sweep_resumes_to_the_uninterrupted_result(sweep_run, tmp_path):
    _, config, swept = sweep_run
    driver.train(config, tmp_path / "cut", progress=False, swept=swept, stop_after_chunks=1)
    assert len(_records(tmp_path / "cut" / "arms" / "1")) == 1
    driver.train(config, tmp_path / "cut", resume=True, progress=False)  # the grid is read back from the run
    _assert_same_learning(_records(tmp_path / "cut"), _records(sweep_run[0] / "sweep"))
    for arm in range(2):
        assert len(_records(tmp_path / "cut" / "arms" / str(arm))) == 2


@pytest.mark.parametrize(
    "spec,phrase",
    [
        ("num_envs=8,16", "num_envs cannot be swept in one program: it sets shapes or loop counts"),
        ("hidden_size=8,16", "hidden_size cannot be swept in one program: it sets shapes or loop counts"),
        ("recurrent=0,1", "recurrent cannot be swept in one program: it changes the program's structure"),
        ("lr=1,2", "ppo has no setting 'lr'; sweepable: "),
        ("gamma=0.9,1.5", "gamma must be a number in [0, 1], got 1.5"),
        ("gamma=0.9,0.9", "a value is given twice"),
        ("gamma=0.9,x", "values must be numbers separated by commas"),
        ("gamma", "--sweep takes NAME=V1,V2"),
    ],
)
def test_a_sweep_that_would_need_a_program_per_arm_or_is_malformed_is_refused(spec, phrase):
    with pytest.raises(ValueError, match=r"^.*$") as caught:
        parse_sweep([spec], _config())
    assert phrase in str(caught.value) and "\n" not in str(caught.value)


def test_the_grid_is_the_product_of_the_values_first_name_slowest():
    swept = parse_sweep(["gamma=0.9,0.99", "learning_rate=1e-3,2e-3,3e-3"], _config())
    assert swept.num_arms == 6 and swept.arms[:3] == ((0.9, 1e-3), (0.9, 2e-3), (0.9, 3e-3))
    values = swept.run_values(seeds=2)
    assert values["gamma"].tolist() == pytest.approx([0.9] * 6 + [0.99] * 6)
    assert Sweep.from_json(swept.to_json(), "x") == swept


def test_a_float_the_learner_reads_outside_the_trace_is_refused_before_training():
    config = make_config(
        "dqn",
        "1d-static-sin",
        num_envs=8,
        rollout_steps=8,
        total_steps=512,
        learning_starts=0,
        batch_size=8,
        buffer_size=256,
    )
    swept = parse_sweep(["exploration_fraction=0.1,0.5"], config)
    with pytest.raises(ValueError, match="reads exploration_fraction outside the traced computation"):
        check_traceable(config, swept)
    check_traceable(_config(), parse_sweep(["learning_rate=1e-3,2e-3", "gamma=0.9,0.99"], _config()))


@pytest.mark.slow
@pytest.mark.parametrize(
    "argv,phrase",
    [
        (["--sweep", "num-envs=8,16"], "num_envs cannot be swept in one program"),
        pytest.param(
            ["--learning-rate", "0.001", "--sweep", "learning-rate=1e-3,2e-3"],
            "--learning-rate and --sweep learning_rate=... both set",
            marks=pytest.mark.slow,
        ),
    ],
)
def test_snac_train_refuses_a_bad_sweep_in_one_line(argv, phrase, tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "snac_jax.cli", "train", "ppo", "--no-progress", "--out", str(tmp_path / "run"), *argv],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines() == [done.stderr.strip()] and phrase in done.stderr
    assert not (tmp_path / "run").exists()


def test_a_sweep_runs_policies_load_by_run_index_with_their_arms_settings(sweep_run):
    from agents.training.trained import checkpoint_policy
    from snac_jax import make

    base, config, _ = sweep_run
    env, _ = make("1d-static-sin", max_steps=30)
    checkpoint_policy(env, base / "sweep", seed_index=3)  # arm 1, seed 1
    with pytest.raises(ValueError, match=r"must be in 0\.\.3 .*a sweep: arm a, seed s is index a \* 2 \+ s"):
        checkpoint_policy(env, base / "sweep", seed_index=4)


def test_a_damaged_sweep_json_is_refused_naming_the_file_and_the_field(tmp_path):
    from agents.training import sweep

    (tmp_path / "sweep.json").write_text('{"names": ["learning_rate"], "arms": [[0.001], ["fast"]]}')
    with pytest.raises(ValueError, match=r"sweep\.json: arms\[1\] must be finite numbers, got 'fast'") as caught:
        sweep.load(tmp_path)
    assert "\n" not in str(caught.value)
    (tmp_path / "sweep.json").write_text('{"names": ["learning_rate"], "arms": [[0.001, 0.9]]}')
    with pytest.raises(ValueError, match="not a sweep"):
        sweep.load(tmp_path)


def _copy_of_the_sweep(sweep_run, tmp_path):
    import shutil

    shutil.copytree(sweep_run[0] / "sweep", tmp_path / "run")
    return tmp_path / "run"


def _edit_json(path, change):
    path.write_text(json.dumps(change(json.loads(path.read_text()))))


def _resume(run):
    driver.train(None, run, resume=True, progress=False)


def test_a_sweep_json_out_of_bounds_is_refused_on_resume_naming_the_file(sweep_run, tmp_path):
    run = _copy_of_the_sweep(sweep_run, tmp_path)
    _edit_json(run / "sweep.json", lambda d: {**d, "arms": [[-1.0], [VALUES[1]]]})
    with pytest.raises(ValueError, match=r"sweep\.json: learning_rate must be a number > 0, got -1\.0") as caught:
        _resume(run)
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize(
    "names,arms,phrase",
    [
        (["num_envs"], [[8], [16]], "num_envs cannot be swept in one program: it sets shapes or loop counts"),
        (["lr"], [[0.1], [0.2]], "ppo has no setting 'lr'; sweepable: "),
        (["learning_rate"], [[1e39], [0.1]], "learning_rate=1e+39 is inf in float32"),
        (["learning_rate"], [[0.1], [0.1000000001]], "arms 0 (learning_rate=0.1) and 1 (learning_rate=0.1)"),
        (["learning_rate", "learning_rate"], [[0.1, 0.2]], "learning_rate is given twice"),
    ],
)
def test_a_sweep_json_the_command_line_would_refuse_is_refused_in_one_line(sweep_run, tmp_path, names, arms, phrase):
    from agents.training import sweep

    run = _copy_of_the_sweep(sweep_run, tmp_path)
    (run / "sweep.json").write_text(json.dumps({"names": names, "arms": arms}))
    with pytest.raises(ValueError) as caught:
        sweep.load(run)
    assert phrase in str(caught.value) and "sweep.json" in str(caught.value) and "\n" not in str(caught.value)


def test_a_valid_edit_of_sweep_json_disagreeing_with_an_arms_config_is_refused(sweep_run, tmp_path):
    run = _copy_of_the_sweep(sweep_run, tmp_path)
    _edit_json(run / "sweep.json", lambda d: {**d, "arms": [[VALUES[0]], [0.02]]})
    with pytest.raises(ValueError, match=r"arms/1/config\.json disagrees with .*sweep\.json's arm 1: learning_rate="):
        _resume(run)
    _edit_json(run / "sweep.json", lambda d: {**d, "names": ["gamma"], "arms": [[0.9], [0.99]]})
    with pytest.raises(ValueError, match=r"sweeps gamma but .*config\.json says the run sweeps learning_rate"):
        _resume(run)


def test_an_arms_config_edited_alone_is_refused(sweep_run, tmp_path):
    run = _copy_of_the_sweep(sweep_run, tmp_path)
    _edit_json(run / "arms" / "0" / "config.json", lambda d: {**d, "learning_rate": 0.5})
    with pytest.raises(ValueError, match=r"arms/0/config\.json disagrees"):
        _resume(run)


def test_swept_values_float32_would_change_are_refused_on_the_command_line():
    for spec, phrase in (
        ("learning_rate=1e39,0.1", "learning_rate=1e+39 is inf in float32"),
        ("learning_rate=1e-50,0.1", "learning_rate=1e-50 is 0 in float32"),
        ("learning_rate=1e-40,0.1", "learning_rate=1e-40 is a subnormal in float32"),
        ("learning_rate=0.1,0.1000000001", "are the same arm in float32"),
    ):
        with pytest.raises(ValueError) as caught:
            parse_sweep([spec], _config())
        assert phrase in str(caught.value) and "\n" not in str(caught.value), spec


def test_a_sweeps_top_level_config_names_the_swept_settings_instead_of_one_value(sweep_run):
    from agents.training.checkpoint import read_config

    run = sweep_run[0] / "sweep"
    recorded = json.loads((run / "config.json").read_text())
    assert "learning_rate" not in recorded and recorded["swept"] == ["learning_rate"]
    assert read_config(run).hidden_size == TINY["hidden_size"]


def test_an_arm_folder_linked_outside_the_run_is_refused_and_a_lost_arm_config_restored(sweep_run, tmp_path, capsys):
    import shutil

    run = _copy_of_the_sweep(sweep_run, tmp_path)
    outside = tmp_path / "outside"
    shutil.move(run / "arms" / "0", outside)
    (run / "arms" / "0").symlink_to(outside)
    with pytest.raises(ValueError, match=r"arms/0 is not the run's own folder \(a link or a file\)"):
        _resume(run)
    (run / "arms" / "0").unlink()
    shutil.move(outside, run / "arms" / "0")
    written = (run / "arms" / "1" / "config.json").read_text()
    (run / "arms" / "1" / "config.json").unlink()
    _resume(run)
    assert (run / "arms" / "1" / "config.json").read_text() == written
    assert "arms/1/config.json was missing; rewritten from" in capsys.readouterr().err


def test_snac_eval_of_a_sweep_names_the_arm_and_seed_of_a_run_index(sweep_run, capsys):
    from snac_jax.cli import main

    run = sweep_run[0] / "sweep"
    code = main(["eval", "--checkpoint", str(run), "--seed-index", "3", "--episodes", "2", "--devices", "1"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert f"arm 1 (learning_rate={VALUES[1]:g}), training seed index 1 (run index 3)" in out
    assert "training seed index 3" not in out
