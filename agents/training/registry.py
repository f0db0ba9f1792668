"""The one table from an algorithm's name to its module, config class and algorithm class, and
the resolution of a config: class defaults, then the task's tuned entry, then the caller's values.

Tuned values are data, `agents/tuned/<algorithm>.toml`: one table per task, each naming in
`result` the page under `bench/results/` that records the runs it was chosen from. A variant
that adds training signals to a base learner (its config's `tuned_as`) reads the base's file, then
its own where it has one (the settings of its own, or its own choices on a task).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import tomllib
from pathlib import Path
from typing import Any

from agents.training.config import TrainConfig
from snac_jax.tasks import TASKS

TUNED_DIR = Path(__file__).parents[1] / "tuned"


@dataclasses.dataclass(frozen=True)
class Entry:
    module: str
    config: str  # the config class's name in `module`
    algorithm: str  # the algorithm class's name in `module`
    summary: str  # one line for `snac train --help`


ALGORITHMS: dict[str, Entry] = {
    "ppo": Entry("agents.learners.ppo", "PPOConfig", "PPO", "PPO, with or without a GRU core (--[no-]recurrent)"),
    "dqn": Entry(
        "agents.learners.dqn", "DQNConfig", "DQN", "DQN: double Q, dueling head, n-step returns; replay on device"
    ),
    "drqn": Entry(
        "agents.learners.drqn",
        "DRQNConfig",
        "DRQN",
        "DRQN: DQN with an LSTM, trained on replayed sequences with burn-in",
    ),
    "drqn-her": Entry(
        "agents.learners.drqn_her",
        "DRQNHERConfig",
        "DRQNHER",
        "DRQN + hindsight relabelling with the episode's final grid as the design",
    ),
    "pqn": Entry(
        "agents.learners.pqn",
        "PQNConfig",
        "PQN",
        "PQN: Q(lambda) over many worlds, LayerNorm, no replay or target "
        "network (PQN-RNN or feed-forward: --[no-]recurrent)",
    ),
    "sac": Entry(
        "agents.learners.sac",
        "SACConfig",
        "SAC",
        "SAC for discrete actions: categorical actor, twin critics, learned temperature",
    ),
    "rainbow": Entry(
        "agents.learners.rainbow",
        "RainbowConfig",
        "Rainbow",
        "Rainbow: C51 dueling head, noisy layers, prioritised replay, n-step double-Q; replay on device",
    ),
    "ppo-privileged": Entry(
        "agents.research.ppo_privileged",
        "PrivilegedPPOConfig",
        "PrivilegedPPO",
        "PPO with a critic that reads the privileged state, + auxiliary localisation losses",
    ),
    "drqn-aux": Entry(
        "agents.research.drqn_aux", "DRQNAuxConfig", "DRQNAux", "DRQN + auxiliary localisation and map losses"
    ),
    "pqn-aux": Entry(
        "agents.research.pqn_aux", "PQNAuxConfig", "PQNAux", "PQN-RNN + auxiliary localisation and map losses"
    ),
    "pqn-belief": Entry(
        "agents.research.pqn_belief",
        "PQNBeliefConfig",
        "PQNBelief",
        "PQN-RNN whose Q head reads the design expected at its position belief (a histogram filter, or learned)",
    ),
    "ippo": Entry(
        "agents.learners.ippo",
        "IPPOConfig",
        "IPPO",
        "IPPO: shared-parameter PPO for several robots (snac_jax.multi); --robots N",
    ),
}


def _check_algorithm(algorithm: Any) -> Entry:
    if algorithm not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {algorithm!r}; allowed: {', '.join(ALGORITHMS)}")
    return ALGORITHMS[algorithm]


def config_class(algorithm: str) -> type[TrainConfig]:
    entry = _check_algorithm(algorithm)
    return getattr(importlib.import_module(entry.module), entry.config)


def build_algorithm(config: TrainConfig):
    """The algorithm object (pure functions the driver runs) of a config."""
    entry = _check_algorithm(config.algorithm)
    return getattr(importlib.import_module(entry.module), entry.algorithm)(config)


def tuned_files(algorithm: str) -> list[Path]:
    """The tuned files `algorithm` trains with, in the order they apply: its base learner's
    (`tuned_as`), then its own; only those that exist."""
    base = config_class(algorithm).tuned_as
    names = ([base] if base else []) + [algorithm]
    return [path for name in names if (path := TUNED_DIR / f"{name}.toml").is_file()]


def tuned_source(algorithm: str, task: str, option: str) -> Path | None:
    """The tuned file whose entry for `task` sets `option` for `algorithm` (the last to apply), if any."""
    for path in reversed(tuned_files(algorithm)):
        if option in tomllib.loads(path.read_text()).get(task, {}):
            return path
    return None


@functools.cache
def tuned_table(algorithm: str) -> dict[str, dict[str, Any]]:
    """Task -> tuned values of `algorithm` (without `result`), checked against its config's fields:
    a variant's base learner's values, updated per task by the variant's own file."""
    cls = config_class(algorithm)
    fields = {f.name for f in dataclasses.fields(cls)} - {"task"}
    table: dict[str, dict[str, Any]] = {}
    for path in tuned_files(algorithm):
        for task, entry in tomllib.loads(path.read_text()).items():
            entry = dict(entry)
            if task not in TASKS:
                raise ValueError(f"{path}: unknown task {task!r}; allowed: {', '.join(TASKS)}")
            if "result" not in entry:
                raise ValueError(
                    f'{path}: [{task}] must name the result it was tuned for (`result = "bench/results/..."`)'
                )
            entry.pop("result")
            unknown = sorted(set(entry) - fields)
            if unknown:
                raise ValueError(
                    f"{path}: [{task}] has unknown {algorithm} option(s) {unknown}; allowed: {', '.join(sorted(fields))}"
                )
            table[task] = {**table.get(task, {}), **entry}
    return table


def make_config(algorithm: str, task: str = TrainConfig.task, **overrides: Any) -> TrainConfig:
    """The tuned config of `algorithm` on `task`, updated with `overrides` (None values are
    ignored), validated."""
    cls = config_class(algorithm)
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; allowed: {', '.join(TASKS)}")
    fields = {f.name for f in dataclasses.fields(cls)}
    overrides = {k: v for k, v in overrides.items() if v is not None}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"unknown {algorithm} option(s) {unknown}; allowed: {', '.join(sorted(fields))}")
    config = cls(**{**tuned_table(algorithm).get(task, {}), **overrides, "task": task})
    config.validate()
    return config


def config_from_json(data: dict[str, Any]) -> TrainConfig:
    """Inverse of `TrainConfig.to_json` (a run's `config.json`; a sweep's leaves its swept
    settings to the arms and names them under `swept`, and they take the class defaults here)."""
    data = dict(data)
    data.pop("swept", None)
    cls = config_class(data.pop("algorithm", None))
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - fields)
    if unknown:
        raise ValueError(
            f"config.json has unknown {cls.algorithm} option(s) {unknown}; allowed: {', '.join(sorted(fields))}"
        )
    config = cls(**data)
    config.validate()
    return config
