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

A run keeps its grid twice, in `sweep.json` and in each arm's `config.json`; reading it back
(`load`, `check_arms`) puts `sweep.json` through the checks a `--sweep` passes and refuses an
arm whose two records disagree, so a hand edit never trains silently with other values.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from agents.training import schemas
from agents.training.checkpoint import CONFIG_FILE, read_config
from agents.training.config import TrainConfig, field_specs, save_config
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


def _describe_setting_refusal(config_class: type[TrainConfig], name: str) -> str | None:
    """Why `name` cannot be swept for `config_class` (None: it can), naming the sweepable ones."""
    fields, allowed = field_specs(config_class), sweepable(config_class)
    if name not in fields or not fields[name].cli:
        return f"{config_class.algorithm} has no setting {name!r}; sweepable: {', '.join(allowed)}"
    if name not in allowed:
        why = "sets shapes or loop counts" if fields[name].kind is int else "changes the program's structure"
        return (
            f"{name} cannot be swept in one program: it {why} (a {fields[name].kind.__name__}); "
            f"sweepable: {', '.join(allowed)}"
        )
    return None


def _check_float32(name: str, value: float) -> None:
    """A swept value reaches the learner as a float32 (`Sweep.run_values`): one that float32
    turns into inf, 0 or a subnormal (where the value is not one) would train with another value
    than the one recorded."""
    with np.errstate(over="ignore"):
        cast = np.float32(value)
    if value != 0 and not np.isfinite(cast):
        raise ValueError(f"{name}={value!r} is inf in float32, the type a swept value trains with; give a smaller one")
    if value != 0 and (cast == 0 or abs(cast) < np.finfo(np.float32).tiny):
        what = "0" if cast == 0 else "a subnormal"
        raise ValueError(
            f"{name}={value!r} is {what} in float32, the type a swept value trains with; give one of magnitude "
            f">= {np.finfo(np.float32).tiny:.3g}"
        )


def check_grid(swept: Sweep, config: TrainConfig) -> None:
    """`ValueError` (one line) unless every arm of `swept` is a config of `config`'s class that
    trains as recorded: sweepable names, each given once; every value within its declared bounds
    and representable in float32; no two arms the same after the cast; every arm's whole config
    valid. `parse_sweep` and `load` both check a grid here, so a `sweep.json` edited by hand
    passes the checks a `--sweep` on the command line does."""
    if len(set(swept.names)) != len(swept.names):
        twice = next(name for name in swept.names if swept.names.count(name) > 1)
        raise ValueError(f"{twice} is given twice; give its values in one --sweep {twice}=V1,V2")
    fields = field_specs(type(config))
    for name in swept.names:
        refusal = _describe_setting_refusal(type(config), name)
        if refusal is not None:
            raise ValueError(refusal)
    for arm in swept.arms:
        for name, value in zip(swept.names, arm):
            fields[name].check(value)
            _check_float32(name, value)
    seen: dict[tuple[float, ...], int] = {}
    for index, arm in enumerate(swept.arms):
        cast = tuple(np.float32(value).item() for value in arm)
        if cast in seen:
            first = seen[cast]
            raise ValueError(
                f"arms {first} ({swept.label(first)}) and {index} ({swept.label(index)}) are the same arm in float32, "
                "the type a swept value trains with: they would train identically; give distinct values"
            )
        seen[cast] = index
    for arm in range(swept.num_arms):
        swept.arm_config(config, arm).validate()


def parse_sweep(specs: list[str], config: TrainConfig) -> Sweep:
    """The grid of `NAME=V1,V2,...` specs for `config`'s class, checked by `check_grid`; a
    one-line `ValueError` naming the problem and the allowed names otherwise."""
    names, values = [], []
    for spec in specs:
        name, sep, text = spec.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or not name or not text.strip():
            raise ValueError(f"--sweep takes NAME=V1,V2,..., got {spec!r}")
        refusal = _describe_setting_refusal(type(config), name)
        if refusal is not None:
            raise ValueError(f"--sweep: {refusal}")
        if name in names:
            raise ValueError(f"--sweep: {name} is given twice; give its values in one --sweep {name}=V1,V2")
        try:
            parsed = [float(v) for v in text.split(",")]
        except ValueError:
            raise ValueError(f"--sweep {name}: values must be numbers separated by commas, got {text!r}") from None
        if len(set(parsed)) != len(parsed):
            raise ValueError(f"--sweep {name}: a value is given twice in {text!r}")
        names.append(name)
        values.append(parsed)
    sweep = Sweep(tuple(names), tuple(itertools.product(*values)))
    try:
        check_grid(sweep, config)
    except ValueError as error:
        raise ValueError(f"--sweep: {error}") from None
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


def load(out_dir: Path, config: TrainConfig | None = None) -> Sweep | None:
    """The sweep of the run in `out_dir` (None for a run of one arm), checked by `check_grid`
    against the run's config (`config`, else read from `out_dir`) and against the settings its
    `config.json` names as swept: a hand-edited grid is refused in one line naming the file."""
    out_dir = Path(out_dir)
    path = out_dir / SWEEP_FILE
    if not path.is_file():
        return None
    swept = Sweep.from_json(schemas.load(path, schemas.SWEEP_JSON), path)
    config = read_config(out_dir) if config is None else config
    try:
        check_grid(swept, config)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    recorded = schemas.load(out_dir / CONFIG_FILE, schemas.CONFIG_JSON).get(schemas.SWEPT)
    if recorded is not None and tuple(recorded) != swept.names:  # runs of older versions record none
        raise ValueError(
            f"{path} sweeps {', '.join(swept.names)} but {out_dir / CONFIG_FILE} says the run sweeps "
            f"{', '.join(recorded)}: the two files must agree (restore the run's own sweep.json)"
        )
    return swept


def base_config_json(config: TrainConfig, sweep: Sweep) -> dict[str, Any]:
    """A sweep's top-level `config.json`: what every arm shares, and under `swept` the names of
    the settings it leaves out: their values are per arm (`sweep.json`, `arms/<i>/config.json`),
    and one value there would read as the value every arm trained with."""
    data = {k: v for k, v in config.to_json().items() if k not in sweep.names}
    return {**data, schemas.SWEPT: list(sweep.names)}


def arm_dir(out_dir: Path, arm: int) -> Path:
    return out_dir / ARMS_DIR / str(arm)


def check_arms(out_dir: Path, config: TrainConfig, sweep: Sweep, restore: Callable[[str], None] | None = None) -> None:
    """`ValueError` (one line naming the file) unless each arm's folder is a real folder inside
    the run and its `config.json` is the config `sweep.json` gives the arm: the two records of an
    arm's settings never disagree silently, and a resume never writes outside the run through a
    link. With `restore` (a resume, which writes), a missing arm folder or `config.json` is
    rewritten from `sweep.json` and reported through `restore(message)`; without, it is left
    alone (nothing reads it)."""
    out_dir = Path(out_dir)
    arms = out_dir / ARMS_DIR
    if arms.is_symlink() or (arms.exists() and not arms.is_dir()):
        raise ValueError(f"{arms} is not the run's own folder (a link or a file): a sweep's arms live inside its run")
    extra = (
        sorted(p.name for p in arms.iterdir() if p.name not in {str(a) for a in range(sweep.num_arms)})
        if (arms.is_dir())
        else []
    )
    if extra:
        raise ValueError(
            f"{arms} holds {', '.join(extra)}, which {out_dir / SWEEP_FILE} has no arm for "
            f"({sweep.num_arms} arms: 0..{sweep.num_arms - 1}): the two must agree"
        )
    for arm in range(sweep.num_arms):
        folder, expected = arm_dir(out_dir, arm), sweep.arm_config(config, arm)
        if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
            raise ValueError(
                f"{folder} is not the run's own folder (a link or a file): a sweep's arms live inside its run"
            )
        if not (folder / CONFIG_FILE).is_file() and not (folder / CONFIG_FILE).is_symlink():
            if restore is not None:
                folder.mkdir(parents=True, exist_ok=True)
                save_config(expected, folder / CONFIG_FILE)
                restore(f"{folder / CONFIG_FILE} was missing; rewritten from {out_dir / SWEEP_FILE} (arm {arm})")
            continue
        if (folder / CONFIG_FILE).is_symlink():
            raise ValueError(f"{folder / CONFIG_FILE} is a link, not the arm's own config.json")
        recorded = read_config(folder).to_json()
        differ = [name for name, value in expected.to_json().items() if recorded.get(name) != value]
        if differ:
            shown = ", ".join(
                f"{name}={recorded.get(name)!r} there, {getattr(expected, name)!r} by sweep.json" for name in differ[:3]
            )
            raise ValueError(
                f"{folder / CONFIG_FILE} disagrees with {out_dir / SWEEP_FILE}'s arm {arm}: {shown}; "
                "the two records of an arm's settings must agree (restore the edited file)"
            )
