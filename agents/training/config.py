"""What every training configuration shares: fields declared once, checked from their declaration.

An option is a dataclass field made with `option(default, help, low=..., high=...)`. Its type
annotation, bounds and help text are the single declaration that validation (`TrainConfig.validate`)
and the command line (`agents.training.cli`, one flag per field) both read, so adding a hyperparameter is
one line in the algorithm's config class. Rules that tie several fields together live in the
class's `check()`.

Each algorithm module defines its own config class beside the algorithm (`agents.learners.ppo.PPOConfig`,
...); `agents.training.registry` maps names to them, and `agents/tuned/<algorithm>.toml` holds the tuned
values per task.
"""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from typing import Any, ClassVar

from snac_jax.atomic import atomic_write_text
from snac_jax.config import REWARD_SCHEMES
from snac_jax.tasks import MAX_INT32, TASKS

MAX_UPDATES = MAX_INT32


def option(
    default: Any,
    help: str,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    cli: bool = True,
) -> Any:
    """A config field with its bounds (`low` inclusive unless `low_open`, `high` inclusive) and
    help text; `cli=False` keeps it off the command line."""
    return dataclasses.field(
        default=default, metadata={"help": help, "low": low, "high": high, "low_open": low_open, "cli": cli}
    )


@dataclasses.dataclass(frozen=True)
class FieldSpec:
    """A field's declaration, resolved: what validation and the CLI read."""

    name: str
    kind: type  # bool, int, float or str
    optional: bool  # None is allowed
    default: Any
    help: str
    low: float | None
    high: float | None
    low_open: bool
    cli: bool

    def describe(self) -> str:
        """The allowed values in words, e.g. 'an int >= 1' or 'a number in [0, 1]'."""
        if self.kind is bool:
            return "True or False"
        noun = "an int" if self.kind is int else "a number"
        if self.low is not None and self.high is not None:
            text = f"{noun} in {'(' if self.low_open else '['}{self.low:g}, {self.high:g}]"
        elif self.low is not None:
            text = f"{noun} {'>' if self.low_open else '>='} {self.low:g}"
        elif self.high is not None:
            text = f"{noun} <= {self.high:g}"
        else:
            text = noun
        return text + (" or None" if self.optional else "")

    def check(self, value: Any) -> None:
        """Raise `ValueError` naming the field and its allowed values unless `value` is one."""
        if self.optional and value is None:
            return
        if self.kind is str:
            return
        if self.kind is bool:
            ok = isinstance(value, bool)
        elif self.kind is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if ok and self.kind is not bool:
            if self.low is not None:
                ok = value > self.low if self.low_open else value >= self.low
            if ok and self.high is not None:
                ok = value <= self.high
        if not ok:
            raise ValueError(f"{self.name} must be {self.describe()}, got {value!r}")


def field_specs(cls: type) -> dict[str, FieldSpec]:
    """The declarations of every field of config class `cls`, in declaration order."""
    hints = typing.get_type_hints(cls)
    specs = {}
    for field in dataclasses.fields(cls):
        hint = hints[field.name]
        args = typing.get_args(hint)
        optional = type(None) in args
        kind = next(a for a in args if a is not type(None)) if args else hint
        meta = field.metadata
        specs[field.name] = FieldSpec(
            name=field.name,
            kind=kind,
            optional=optional,
            default=field.default,
            help=meta.get("help", ""),
            low=meta.get("low"),
            high=meta.get("high"),
            low_open=meta.get("low_open", False),
            cli=meta.get("cli", True),
        )
    return specs


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """What the shared driver (`agents.training.driver`) needs from any algorithm."""

    algorithm: ClassVar[str] = "base"
    paper_method: ClassVar[str] = "base"  # the algorithm's row in the paper's results
    # the algorithm whose tuned file (agents/tuned/<name>.toml) this one trains with; a variant that
    # adds training signals to a base learner reads the base's, so a comparison isolates the signals
    tuned_as: ClassVar[str | None] = None
    # options that change only how a trained policy acts, not its parameters, its world or its
    # training alone: what a table arm may switch on when scored (`Variant.evaluation`)
    acting_options: ClassVar[tuple[str, ...]] = ()

    task: str = option("1d-static-sin", "the task to train on", cli=False)
    total_steps: int = option(2_000_000, "env steps per seed", low=1)
    num_envs: int = option(256, "parallel worlds per seed (split over devices)", low=1)
    seeds: int = option(1, "independent runs, vmapped in one process", low=1)
    seed: int = option(0, "base seed; run i uses fold_in(key(seed), i)", low=0, high=2**32 - 1)
    chunks: int = option(20, "the driver logs and checkpoints this many times over the run", low=1)
    max_steps: int = option(0, "episode step limit for training; 0 keeps the task's", low=0, high=2**31 - 1)
    rollout_steps: int = option(64, "steps per world between learning phases", low=1)
    previous_step: bool = option(True, "the network also reads the previous window and its last action")
    switches: str = option(
        "",
        "environment switches for training and evaluation, comma-separated key=value "
        "(gps=true, stride_probs=1/0/0, obstacles=true|false, landmarks=K, reward_scheme=height|binary; "
        "SPEC §9), as in the paper's ablations; empty: the task as defined",
    )
    train_reward: str = option(
        "",
        "the reward table training learns from (height or binary, SPEC §5); empty: the "
        "task's own. Unlike a reward_scheme switch it leaves the task scored as defined: "
        "a learner's choice of training signal, not another task",
    )

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.rollout_steps

    @property
    def num_updates(self) -> int:
        return max(1, self.total_steps // self.steps_per_update)

    def validate(self) -> None:
        """Every field against its declaration, then the class's cross-field rules. A config
        holding traced values (one run of a sweep, `agents.training.sweep`) is not checked again: its
        arms' concrete configs were, and a traced value has no value to check."""
        import jax

        if any(isinstance(getattr(self, f.name), jax.core.Tracer) for f in dataclasses.fields(self)):
            return
        if self.task not in TASKS:
            raise ValueError(f"unknown task {self.task!r}; allowed: {', '.join(TASKS)}")
        for name, spec in field_specs(type(self)).items():
            spec.check(getattr(self, name))
        if self.num_updates > MAX_UPDATES:
            raise ValueError(
                f"total_steps {self.total_steps:,} makes {self.num_updates:,} updates of {self.steps_per_update:,} "
                f"env steps; at most {MAX_UPDATES:,} (updates are counted in int32)"
            )
        if self.switches:
            self.env_config()  # every switch value checked by make, before anything is traced
        if self.train_reward not in ("", *REWARD_SCHEMES):
            raise ValueError(
                f"train_reward must be one of {('', *REWARD_SCHEMES)} (empty: the task's own), "
                f"got {self.train_reward!r}"
            )
        if self.train_reward and "reward_scheme" in self.env_overrides:
            raise ValueError(
                "give the reward as the reward_scheme switch (another task, scored so) or as "
                "train_reward (training alone), not both"
            )
        self.check()

    def check(self) -> None:
        """Rules that relate several fields (each field alone is checked from its declaration)."""

    @property
    def env_overrides(self) -> dict[str, Any]:
        """The `snac_jax.make` overrides the run is scored with: its switches and its step limit,
        when it set them. It trains with them and its `train_reward` (`training_overrides`)."""
        from snac_jax.tasks import parse_switches

        return {**parse_switches(self.switches), **({"max_steps": self.max_steps} if self.max_steps else {})}

    def scored_world(self):
        """`(env, params)` of a world this run's policy is scored in: its switches and step limit,
        built by `make`, which checks every value; a dynamic task is pinned to one test design, so
        no training bank is drawn (`make_env` draws it). With `design_change` a pinned design has
        none to change to (SPEC §15): a bank of two, the smallest it allows, is drawn instead."""
        from snac_jax.tasks import make, without_training_bank

        overrides = self.env_overrides
        return make(self.task, **overrides, **without_training_bank(self.task, overrides))

    def env_config(self):
        """The static `EnvConfig` (observation, action table, rules) the run's switches give: what a
        world must match for this run's policy."""
        return self.scored_world()[0].config

    @property
    def training_overrides(self) -> dict[str, Any]:
        """The `make` overrides the run trains with: the scored ones (`env_overrides`) and the
        reward `train_reward` names, which changes no observation, rule or episode, so a policy
        trained so acts in the scored world unchanged."""
        return {**self.env_overrides, **({"reward_scheme": self.train_reward} if self.train_reward else {})}

    def make_env(self):
        """The training environment `(env, params)` of this config (`training_overrides`)."""
        from snac_jax.tasks import make

        return make(self.task, **self.training_overrides)

    def to_json(self) -> dict[str, Any]:
        return {"algorithm": self.algorithm, **dataclasses.asdict(self)}


def save_config(config: TrainConfig, path) -> None:
    atomic_write_text(path, json.dumps(config.to_json(), indent=2) + "\n")
