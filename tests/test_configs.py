"""Configurations: every tuned (algorithm, task) resolves to the values it had when the tuned
table moved into `agents/tuned/*.toml` (tests/data/resolved_configs.json, dumped from the code
before the move; later deliberate changes, new options with their defaults and re-tuned entries,
are made there with them), and bad values are refused from the fields' declarations."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import pytest

from agents.training.config import field_specs
from agents.training.registry import ALGORITHMS, config_class, config_from_json, make_config, tuned_table
from snac_jax.tasks import TASKS

RESOLVED = json.loads((Path(__file__).parent / "data" / "resolved_configs.json").read_text())


@pytest.mark.parametrize("algorithm", list(ALGORITHMS))
def test_every_task_resolves_to_the_recorded_configuration(algorithm):
    for task in TASKS:
        assert make_config(algorithm, task).to_json() == RESOLVED[f"{algorithm}/{task}"], (algorithm, task)


def test_the_fixture_covers_every_algorithm_and_task():
    assert set(RESOLVED) == {f"{a}/{t}" for a in ALGORITHMS for t in TASKS}


@pytest.mark.parametrize("algorithm", list(ALGORITHMS))
def test_config_json_round_trips(algorithm):
    config = make_config(algorithm, "2d-static-dense", seeds=3)
    assert config_from_json(config.to_json()) == config


@pytest.mark.parametrize("algorithm", list(ALGORITHMS))
def test_every_tuned_entry_names_the_result_page_it_was_tuned_for(algorithm):
    import tomllib

    from agents.training.registry import tuned_files

    root = Path(__file__).parents[1]
    paths = tuned_files(algorithm)
    if not paths:
        pytest.skip(f"{algorithm} has no tuned settings: every task uses the config class's defaults")
    for path in paths:
        for task, entry in tomllib.loads(path.read_text()).items():
            assert (root / entry["result"]).is_file(), (algorithm, task, entry["result"])
    assert tuned_table(algorithm)  # loads and checks the keys against the config's fields


@pytest.mark.parametrize("algorithm", list(ALGORITHMS))
def test_every_field_declares_help_and_a_known_type(algorithm):
    for spec in field_specs(config_class(algorithm)).values():
        assert spec.kind in (bool, int, float, str), spec
        assert spec.help, spec.name


@pytest.mark.parametrize(
    "name,value,message",
    [
        ("total_steps", 0, "total_steps must be an int >= 1, got 0"),
        ("learning_rate", 0.0, "learning_rate must be a number > 0, got 0.0"),
        ("gamma", 1.5, r"gamma must be a number in \[0, 1\], got 1.5"),
        ("recurrent", 1, "recurrent must be True or False, got 1"),
        ("ent_coef_end", -2.0, "ent_coef_end must be a number >= -1 or None, got -2.0"),
        ("seed", 2**64, "seed must be an int in"),
        ("max_steps", float("nan"), "max_steps must be an int in"),
        ("total_steps", 10**20, r"makes 1,525,878,906,250,000 updates of 65,536 env steps; at most 2,147,483,647"),
    ],
)
def test_bad_values_are_refused_with_the_allowed_range(name, value, message):
    with pytest.raises(ValueError, match=message):
        make_config("ppo", "1d-static-sin", **{name: value})


def test_cross_field_rules_and_unknown_names():
    with pytest.raises(ValueError, match="multiple of num_minibatches"):
        make_config("ppo", "1d-static-sin", num_envs=6, num_minibatches=4)
    with pytest.raises(ValueError, match="unknown ppo option"):
        make_config("ppo", "1d-static-sin", lstm_size=3)
    with pytest.raises(ValueError, match="unknown algorithm 'a2c'; allowed: " + ", ".join(ALGORITHMS)):
        make_config("a2c", "1d-static-sin")
    with pytest.raises(ValueError, match="unknown task"):
        make_config("dqn", "4d-static")


def test_switches_reach_the_training_env_and_the_evaluation_and_are_checked_up_front():
    config = make_config("drqn", "2d-static-dense", switches="gps=true,stride_probs=1/0/0", max_steps=50)
    assert config.env_overrides == {"gps": True, "stride_probs": (1.0, 0.0, 0.0), "max_steps": 50}
    env, params = config.make_env()
    plain, plain_params = make_config("drqn", "2d-static-dense").make_env()
    size = lambda env, params: env.observation_space(params).shape[0]
    assert env.config.gps and size(env, params) == size(plain, plain_params) + 2 and params.max_steps_in_episode == 50
    assert config_from_json(config.to_json()) == config
    # A run's config.json from before the option existed loads with the task as defined.
    old = {k: v for k, v in make_config("drqn", "2d-static-dense").to_json().items() if k != "switches"}
    assert config_from_json(old).env_overrides == {}
    with pytest.raises(ValueError, match="landmarks need a 2D or 3D task"):
        make_config("ppo", "1d-static-sin", switches="landmarks=4")
    with pytest.raises(ValueError, match="unknown switch 'gpss'"):
        make_config("ppo", "1d-static-sin", switches="gpss=true")


def test_a_tuned_file_with_an_unknown_option_is_refused(tmp_path, monkeypatch):
    from agents.training import registry

    (tmp_path / "ppo.toml").write_text('["1d-static-sin"]\nresult = "bench/results/ppo.md"\nlearning_rat = 0.1\n')
    monkeypatch.setattr(registry, "TUNED_DIR", tmp_path)
    registry.tuned_table.cache_clear()
    try:
        with pytest.raises(ValueError, match=r"unknown ppo option\(s\) \['learning_rat'\]"):
            registry.tuned_table("ppo")
    finally:
        registry.tuned_table.cache_clear()


def test_a_variant_reads_its_base_learners_tuned_file_then_its_own(tmp_path, monkeypatch):
    from agents.training import registry

    (tmp_path / "pqn.toml").write_text(
        '["1d-dynamic"]\nresult = "r"\nnum_envs = 64\nlearning_rate = 0.003\n'
        '["2d-static-dense"]\nresult = "r"\nnum_envs = 128\n'
    )
    (tmp_path / "pqn-belief.toml").write_text('["1d-dynamic"]\nresult = "r"\nlearning_rate = 0.001\nview_radius = 4\n')
    monkeypatch.setattr(registry, "TUNED_DIR", tmp_path)
    registry.tuned_table.cache_clear()
    try:
        assert registry.tuned_table("pqn-belief") == {
            "1d-dynamic": {"num_envs": 64, "learning_rate": 0.001, "view_radius": 4},
            "2d-static-dense": {"num_envs": 128},
        }
        assert registry.tuned_table("pqn") == {
            "1d-dynamic": {"num_envs": 64, "learning_rate": 0.003},
            "2d-static-dense": {"num_envs": 128},
        }
        assert registry.tuned_source("pqn-belief", "1d-dynamic", "num_envs") == tmp_path / "pqn.toml"
        assert registry.tuned_source("pqn-belief", "1d-dynamic", "learning_rate") == tmp_path / "pqn-belief.toml"
        assert registry.tuned_source("pqn-belief", "1d-dynamic", "total_steps") is None
        (tmp_path / "pqn.toml").write_text('["1d-dynamic"]\nresult = "r"\nview_radius = 4\n')  # not a pqn option
        registry.tuned_table.cache_clear()
        with pytest.raises(ValueError, match=r"unknown pqn option\(s\) \['view_radius'\]"):
            registry.tuned_table("pqn")
    finally:
        registry.tuned_table.cache_clear()


@pytest.mark.parametrize("algorithm", list(ALGORITHMS))
def test_every_field_is_a_flag_of_snac_train(algorithm):
    """The command line is derived from the config's declarations: one flag per field, parsed
    into the field's type."""
    from snac_jax.cli import build_parser

    parser = build_parser()
    for spec in field_specs(config_class(algorithm)).values():
        if not spec.cli:
            continue
        flag = "--" + spec.name.replace("_", "-")
        if spec.kind is bool:
            value, text = (not spec.default), ([flag] if not spec.default else ["--no-" + flag[2:]])
        else:
            value = spec.default if spec.default is not None else (spec.low if spec.low is not None else 1)
            if spec.low is not None and spec.low_open and value == spec.low:
                value = spec.low + 1
            text = [flag, str(value)]
        args = parser.parse_args(["train", algorithm, *text])
        assert getattr(args, spec.name) == spec.kind(value), (algorithm, spec.name)
        assert spec.name in args.config_options


def test_a_flag_out_of_its_range_is_an_argparse_error(capsys):
    from snac_jax.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "ppo", "--gamma", "1.5"])
    assert "must be a number in [0, 1], got '1.5'" in capsys.readouterr().err


@pytest.mark.parametrize("algorithm", ["ppo", "pqn-belief", "dqn", "ippo"])
def test_train_reward_changes_the_training_env_alone(algorithm):
    from agents.training.registry import build_algorithm

    config = make_config(algorithm, "2d-dynamic-dense", train_reward="height", num_envs=8)
    plain = make_config(algorithm, "2d-dynamic-dense", num_envs=8, train_reward="")  # the task's own reward
    training_env = lambda learner: (
        getattr(learner, "team_env", None) or learner.env
    )  # a team's (agents.learners.ippo) or one robot's
    assert training_env(build_algorithm(config)).config.reward_scheme == "height"  # what its rollouts are rewarded by
    assert training_env(build_algorithm(plain)).config.reward_scheme == "binary"  # 2D's own (SPEC §5)
    # Scored as the task is defined: the evaluator's overrides and the world a checkpoint must match.
    assert config.env_overrides == {} and config.env_config() == plain.env_config()
    assert config.env_config().reward_scheme == "binary"
    # The training world is the plain one but for the reward: the same observation, rules and episodes.
    assert dataclasses.replace(config.make_env()[0].config, reward_scheme="binary") == plain.make_env()[0].config
    assert config_from_json(config.to_json()) == config
    old = {k: v for k, v in plain.to_json().items() if k != "train_reward"}  # a config.json from before the option
    assert config_from_json(old) == plain


def test_train_reward_is_checked_up_front():
    with pytest.raises(ValueError, match=r"train_reward must be one of \('', 'height', 'binary'\).*got 'dense'"):
        make_config("pqn-belief", "2d-dynamic-dense", train_reward="dense")
    with pytest.raises(ValueError, match="reward_scheme switch .* or as train_reward .* not both"):
        make_config("pqn-belief", "2d-dynamic-dense", train_reward="height", switches="reward_scheme=binary")


def test_an_option_the_learner_does_not_have_is_refused_naming_the_file(tmp_path):
    """A config.json with an option its learner does not have (a typo, or an ingredient that has
    left the code) is refused through `read_config`, naming the file, the option and the allowed ones."""
    from agents.training.checkpoint import read_config

    config = make_config("pqn-belief", "2d-static-dense")
    path = tmp_path / "config.json"
    path.write_text(json.dumps({**config.to_json(), "brick_mapp": False}))
    with pytest.raises(
        ValueError, match=re.escape(str(path)) + r".*unknown pqn-belief option\(s\) \['brick_mapp'\]; allowed: "
    ):
        read_config(tmp_path)
