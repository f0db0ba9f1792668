"""Sweeps in one program: every arm of a hyperparameter grid, times every seed, trained by one
compiled function (PureJaxRL's `vmap` over seeds and settings).

`snac train ALGO --sweep NAME=V1,V2 [--sweep NAME2=...]` makes the grid of the values (first
name slowest) and runs `arms x seeds` independent trainings as one batch: the driver's seed
axis becomes the run axis, arm-major, so run `a * seeds + s` is arm `a` with seed `s` and starts
from the same key as seed `s` of a separate run with arm `a`'s settings. A swept value reaches
the learner as a traced float (one per run) instead of a Python constant, so the learner
compiles once for the whole grid; on a GPU a sweep of 8 arms costs about what one arm costs.

Only a float setting can be swept: an int sets shapes or loop counts (worlds, widths, epochs),
a bool or a string the program's structure, and either would need a program per arm. A float
that a learner reads outside the traced computation (in Python arithmetic that sizes something
or picks a branch) is refused too: `check_traceable` traces one chunk before anything runs.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path
from typing import Any

import jax
import numpy as np

from agents.training.config import TrainConfig, field_specs
from snac_jax.atomic import atomic_write_text

SWEEP_FILE = "sweep.json"
ARMS_DIR = "arms"


@dataclasses.dataclass(frozen=True)
class Sweep:
    """The swept settings' names and the grid of their values, one tuple per arm."""

    names: tuple[str, ...]
    arms: tuple[tuple[float, ...], ...]

    @property
    def num_arms(self) -> int:
        return len(self.arms)

    def arm_settings(self, arm: int) -> dict[str, float]:
        return dict(zip(self.names, self.arms[arm]))

    def arm_config(self, config: TrainConfig, arm: int) -> TrainConfig:
        """The whole config of one arm: what a separate run of it would train with."""
        return dataclasses.replace(config, **self.arm_settings(arm))

    def run_values(self, seeds: int) -> dict[str, np.ndarray]:
        """Each swept setting per run (arms x seeds, arm-major), as float32 arrays."""
        grid = np.asarray(self.arms, np.float32).reshape(self.num_arms, len(self.names))
        return {name: np.repeat(grid[:, i], seeds) for i, name in enumerate(self.names)}

    def label(self, arm: int) -> str:
        return ", ".join(f"{name}={value:g}" for name, value in self.arm_settings(arm).items())

    def to_json(self) -> dict[str, Any]:
        return {"names": list(self.names), "arms": [list(arm) for arm in self.arms]}

    @classmethod
    def from_json(cls, data: Any, path: Path) -> Sweep:
        try:
            names, arms = tuple(data["names"]), tuple(tuple(float(v) for v in arm) for arm in data["arms"])
            if not names or not arms or any(len(arm) != len(names) for arm in arms):
                raise ValueError
        except (TypeError, KeyError, ValueError):
            raise ValueError(f'{path}: not a sweep (expected {{"names": [...], "arms": [[...], ...]}})') from None
        return cls(names, arms)


def sweepable(config_class: type[TrainConfig]) -> list[str]:
    """The settings of `config_class` a sweep may vary: its float options."""
    return [name for name, spec in field_specs(config_class).items() if spec.kind is float and spec.cli]


def parse_sweep(specs: list[str], config: TrainConfig) -> Sweep:
    """The grid of `NAME=V1,V2,...` specs for `config`'s class, every arm's config validated;
    a one-line `ValueError` naming the problem and the allowed names otherwise."""
    fields = field_specs(type(config))
    allowed = sweepable(type(config))
    names, values = [], []
    for spec in specs:
        name, sep, text = spec.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or not name or not text.strip():
            raise ValueError(f"--sweep takes NAME=V1,V2,..., got {spec!r}")
        if name not in fields or not fields[name].cli:
            raise ValueError(f"--sweep: {config.algorithm} has no setting {name!r}; sweepable: {', '.join(allowed)}")
        if name not in allowed:
            why = "sets shapes or loop counts" if fields[name].kind is int else "changes the program's structure"
            raise ValueError(
                f"--sweep: {name} cannot be swept in one program: it {why} (a {fields[name].kind.__name__}); "
                f"sweepable: {', '.join(allowed)}"
            )
        if name in names:
            raise ValueError(f"--sweep: {name} is given twice; give its values in one --sweep {name}=V1,V2")
        try:
            parsed = [float(v) for v in text.split(",")]
        except ValueError:
            raise ValueError(f"--sweep {name}: values must be numbers separated by commas, got {text!r}") from None
        if len(set(parsed)) != len(parsed):
            raise ValueError(f"--sweep {name}: a value is given twice in {text!r}")
        for value in parsed:
            fields[name].check(value)
        names.append(name)
        values.append(parsed)
    sweep = Sweep(tuple(names), tuple(itertools.product(*values)))
    for arm in range(sweep.num_arms):
        sweep.arm_config(config, arm).validate()
    return sweep


def traced_config(config: TrainConfig, values: dict[str, jax.Array]) -> TrainConfig:
    """`config` with the swept settings replaced by one run's traced values (inside the vmap over
    runs). Not validated: `parse_sweep` checked every arm's concrete config."""
    return dataclasses.replace(config, **values)


def learner_for(config: TrainConfig, values: dict[str, jax.Array]):
    """The learner of one run of a sweep, built inside the traced function with its traced values.

    A learner's constructor does concrete work (it makes the environment, samples the design
    bank, reads the designs' heights); under `ensure_compile_time_eval` that work runs eagerly
    as it would outside, and only what the swept values reach is traced."""
    from agents.training.registry import build_algorithm

    with jax.ensure_compile_time_eval():
        return build_algorithm(traced_config(config, values))


def check_traceable(config: TrainConfig, swept: Sweep) -> None:
    """Trace one run's initialisation and one update with the swept settings as tracers (no
    compilation, nothing runs): a setting the learner reads in Python (to size an array, count a
    loop or pick a branch) fails here, before any training, with a one-line `ValueError`."""

    def one_run(values, key):
        learner = learner_for(config, values)
        return learner.train_chunk(learner.init(key), learner.env_params, 1)

    values = {name: jax.ShapeDtypeStruct((), np.float32) for name in swept.names}
    try:
        jax.eval_shape(one_run, values, jax.random.key(0))
    except TypeError as error:  # JAX's concretization errors (a tracer used as a Python value) are TypeErrors
        raise ValueError(
            f"--sweep: {config.algorithm} reads {', '.join(swept.names)} outside the traced computation, "
            f"so it cannot be swept in one program ({type(error).__name__}); run one training per value "
            "instead"
        ) from None


def save(sweep: Sweep, out_dir: Path) -> None:
    atomic_write_text(out_dir / SWEEP_FILE, json.dumps(sweep.to_json(), indent=2) + "\n")


def load(out_dir: Path) -> Sweep | None:
    """The sweep of the run in `out_dir`, or None for a run of one arm."""
    from agents.training import schemas

    path = out_dir / SWEEP_FILE
    if not path.is_file():
        return None
    return Sweep.from_json(schemas.load(path, schemas.SWEEP_JSON), path)


def arm_dir(out_dir: Path, arm: int) -> Path:
    return out_dir / ARMS_DIR / str(arm)
