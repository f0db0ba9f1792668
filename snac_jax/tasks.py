"""The task registry and `make`: task ids, defaults (SPEC §1) and the switches (SPEC §9).

All input checking happens here, in Python, before anything is traced: a bad task id or
override raises `ValueError` naming what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Any

import jax.numpy as jnp
import numpy as np

from snac_jax import design_change, designs, landmark_action, memory
from snac_jax.config import PLAN_SIZE_1D, PLAN_SIZE_2D, REWARD_SCHEMES, EnvConfig
from snac_jax.env import SNACEnv
from snac_jax.state import EnvParams


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    dim: int
    dynamic: bool
    design: str  # the designs.json variant (static) or the density of the triangles / "sine"
    max_steps: int

    @property
    def half_window(self) -> int:
        return 2 if self.dim == 1 else 3


STEP_LIMITS: dict[tuple[int, bool], int] = {
    (1, False): 750,
    (1, True): 750,
    (2, False): 600,
    (2, True): 600,
    (3, False): 1300,
    (3, True): 1000,
}
"""The step limit (truncation) of a task by (dimension, dynamic) (SPEC §1): every other place
reads it from here (`task_spec(task).max_steps`)."""

_SPECS: dict[str, TaskSpec] = {
    **{
        f"1d-static-{s}": TaskSpec(dim=1, dynamic=False, design=f"1d-static-{s}", max_steps=STEP_LIMITS[1, False])
        for s in ("sin", "gauss", "step")
    },
    "1d-dynamic": TaskSpec(dim=1, dynamic=True, design="sine", max_steps=STEP_LIMITS[1, True]),
}
for _dim in (2, 3):
    for _density in ("dense", "sparse"):
        _SPECS[f"{_dim}d-static-{_density}"] = TaskSpec(
            dim=_dim, dynamic=False, design=f"{_dim}d-static-{_density}", max_steps=STEP_LIMITS[_dim, False]
        )
    for _density in ("dense", "sparse"):
        _SPECS[f"{_dim}d-dynamic-{_density}"] = TaskSpec(
            dim=_dim, dynamic=True, design=_density, max_steps=STEP_LIMITS[_dim, True]
        )

TASKS: tuple[str, ...] = tuple(_SPECS)
"""Every task id (SPEC §1)."""

DEFAULT_STRIDE_PROBS = (1 / 3, 1 / 3, 1 / 3)
DEFAULT_DESIGN_BANK_SIZE = 16384
DEFAULT_NUM_LANDMARKS = 8

OVERRIDES = {
    "gps": "bool: append the true plan position to the observation",
    "stride_probs": "three probabilities for strides 1, 2, 3 ((1, 0, 0) is the paper's -Uncertainty)",
    "obstacles": "bool: the 3D action set and obstacle rule (default: on in 3D, off in 2D; 1D has none)",
    "landmarks": f"int K >= 0 landmark cells outside the design (2D/3D; True means {DEFAULT_NUM_LANDMARKS})",
    "reward_scheme": f"one of {REWARD_SCHEMES} (default: 'binary' in 2D, 'height' in 1D/3D)",
    "max_steps": "int in 1..2**31-1, the step limit (truncation)",
    "test_design": "int 0..9: pin a dynamic task to one of its ten test designs",
    "design_bank_size": f"int >= 1, training designs drawn at make time (dynamic tasks; default {DEFAULT_DESIGN_BANK_SIZE})",
    "design_seed": "int in 0..2**32-1, the seed of the design bank (dynamic tasks; default 0)",
    "landmark_action": "int K in 0..400: an extra action places up to K landmarks an episode (2D/3D; 0 = off)",
    "design_change": "(a, b), 1 <= a <= b < max_steps: the design changes at a step drawn from a..b (dynamic tasks)",
}

SWITCHES = ("gps", "stride_probs", "obstacles", "landmarks", "reward_scheme", "landmark_action", "design_change")
"""The overrides a training run may carry as text (`parse_switches`): the paper's ablation switches,
the reward scheme and the two extensions (SPEC §14-15). The step limit and the design bank are not among them: a training config
has an option of its own for the step limit, and the bank is the task's."""


def parse_switches(text: str) -> dict[str, Any]:
    """`"gps=true,stride_probs=1/0/0"` -> `{"gps": True, "stride_probs": (1.0, 0.0, 0.0)}`.

    Why text: a training config holds scalars (its fields become CLI flags and config.json
    entries), so the switches of an ablation travel as one string. A value is `true`/`false`, an
    integer (ASCII digits: `_ASCII_INT`), numbers joined by `/` (a tuple), or a word, in ASCII
    (the text is stored as typed). The keys are checked here (`SWITCHES`), the values by `make`.
    The empty string is no switches."""
    if not isinstance(text, str):
        raise ValueError(f"switches must be a string of comma-separated key=value pairs, got {text!r}")
    switches: dict[str, Any] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, sep, value = (s.strip() for s in item.partition("="))
        if not sep or not value:
            raise ValueError(f"switch {item!r} must be key=value; allowed keys: {', '.join(SWITCHES)}")
        if key not in SWITCHES:
            raise ValueError(f"unknown switch {key!r}; allowed: {', '.join(SWITCHES)}")
        if key in switches:
            raise ValueError(f"switch {key!r} is given twice in {text!r}")
        switches[key] = _switch_value(key, value)
    return switches


_ASCII_INT = re.compile(r"-?[0-9]+")
"""An integer switch value as `format_switches` writes it. Python's `int` reads more ('\u0664' in
Arabic-Indic digits, '1_0', '+4'), which would be stored as typed in a run's config.json."""


def _switch_value(key: str, value: str) -> Any:
    if not value.isascii():
        raise ValueError(
            f"switch {key}={value!r}: ASCII only (digits 0-9); a value is true/false, an integer, "
            "numbers joined by '/', or a word"
        )
    if key == "design_change":  # steps, not probabilities: "100/300" is (100, 300)
        steps = value.split("/")
        if not all(_ASCII_INT.fullmatch(v) for v in steps):
            raise ValueError(f"switch design_change={value!r}: two step numbers a/b expected, e.g. 100/300")
        return tuple(int(v) for v in steps)
    if value.lower() in ("true", "false"):
        return value.lower() == "true"
    if "/" in value:
        try:
            return tuple(float(v) for v in value.split("/"))
        except ValueError:
            raise ValueError(f"switch {key}={value!r}: numbers joined by '/' expected") from None
    return int(value) if _ASCII_INT.fullmatch(value) else value


def format_switches(switches: dict[str, Any]) -> str:
    """The text of `switches` (as `parse_switches` returns them) that parses back to the same
    dict, keys in `SWITCHES` order, so switches that parse equal have one text: `true`/`false`,
    integers without padding, a tuple's numbers joined by `/` (a whole float as an integer), a
    word as is."""
    unknown = [key for key in switches if key not in SWITCHES]
    if unknown:
        raise ValueError(f"unknown switch {unknown[0]!r}; allowed: {', '.join(SWITCHES)}")

    def text(value: Any) -> str:
        if isinstance(value, bool):
            return "true" if value else "false"
        if isinstance(value, tuple):
            return "/".join(str(int(v)) if float(v).is_integer() else repr(float(v)) for v in value)
        return str(value)

    return ",".join(f"{key}={text(switches[key])}" for key in SWITCHES if key in switches)


MAX_INT32 = 2**31 - 1
"""Step counts are int32 on device."""
MAX_SEED = 2**32 - 1
"""`jax.random.key` keeps 32 bits of a seed (without x64), so larger seeds would repeat smaller ones."""


def task_spec(task_id: str) -> TaskSpec:
    if task_id not in _SPECS:
        raise ValueError(f"unknown task id {task_id!r}; allowed task ids: {', '.join(TASKS)}")
    return _SPECS[task_id]


def test_design_names(task_id: str) -> list[str]:
    """The designs.json keys of a dynamic task's ten test designs."""
    spec = task_spec(task_id)
    if not spec.dynamic:
        raise ValueError(
            f"{task_id!r} is a static task and has no test designs; dynamic tasks: "
            f"{', '.join(t for t in TASKS if _SPECS[t].dynamic)}"
        )
    return [f"{task_id}-test{i}" for i in range(designs.NUM_TEST_DESIGNS)]


test_design_names.__test__ = False  # a library function, not a pytest test


def _require_bool(name: str, value: Any) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def _is_int(value: Any) -> bool:
    """A Python or NumPy int, not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _require_int(name: str, value: Any, low: int, high: int | None = None) -> int:
    ok = _is_int(value)
    if not ok or value < low or (high is not None and value > high):
        allowed = f"an int >= {low}" if high is None else f"an int in {low}..{high}"
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
    return int(value)


def _bank_bytes_per_design(dim: int) -> int:
    """An upper bound of the memory `designs.design_bank` needs per design: the host copy, and
    on device the generator's working set (a triangle edge is rasterised as an n x n x n mask)."""
    plan = PLAN_SIZE_1D if dim == 1 else PLAN_SIZE_2D**2
    working = 8 * plan if dim == 1 else PLAN_SIZE_2D**3
    return 2 * plan + working


def _stride_probs(value: Any) -> tuple[float, float, float]:
    try:
        probs = () if isinstance(value, str) else tuple(float(p) for p in value)
    except (TypeError, ValueError):
        probs = ()
    if len(probs) != 3 or any(not math.isfinite(p) or p < 0 for p in probs) or abs(sum(probs) - 1) > 1e-6:
        raise ValueError(
            f"stride_probs must be three non-negative probabilities for strides 1, 2, 3 summing to 1, got {value!r}"
        )
    return probs


def without_training_bank(task_id: str, overrides: dict[str, Any]) -> dict[str, Any]:
    """What to add to `overrides` so that `make` builds the task's world without drawing its
    training bank (a check of the settings, a world the test designs then replace): a dynamic
    task pinned to test design 0, or, under `design_change`, which needs another design to change
    to (SPEC §15), a bank of two, the smallest it allows. Nothing for a static task."""
    if not task_spec(task_id).dynamic:
        return {}
    return {"design_bank_size": 2} if "design_change" in overrides else {"test_design": 0}


def make(task_id: str, **overrides: Any) -> tuple[SNACEnv, EnvParams]:
    """Build a task: `env, params = make("2d-static-dense", gps=True)`.

    Returns a gymnax `Environment` and its default `EnvParams`. See `OVERRIDES` for the
    switches; anything else raises `ValueError`.
    """
    spec = task_spec(task_id)
    unknown = sorted(set(overrides) - set(OVERRIDES))
    if unknown:
        allowed = "; ".join(f"{k}: {v}" for k, v in OVERRIDES.items())
        raise ValueError(f"unknown override(s) {unknown} for make({task_id!r}); allowed overrides: {allowed}")

    gps = _require_bool("gps", overrides.get("gps", False))
    stride_probs = _stride_probs(overrides.get("stride_probs", DEFAULT_STRIDE_PROBS))
    obstacles = _require_bool("obstacles", overrides.get("obstacles", spec.dim == 3))
    if obstacles and spec.dim == 1:
        raise ValueError("obstacles=True needs a 2D or 3D task; 1D has no obstacle rule")
    landmarks = overrides.get("landmarks", 0)
    if isinstance(landmarks, bool):
        landmarks = DEFAULT_NUM_LANDMARKS if landmarks else 0
    landmarks = _require_int("landmarks", landmarks, 0)
    if landmarks and spec.dim == 1:
        raise ValueError("landmarks need a 2D or 3D task; every 1D column belongs to the design")
    reward_scheme = overrides.get("reward_scheme", "binary" if spec.dim == 2 else "height")
    if reward_scheme not in REWARD_SCHEMES:
        raise ValueError(f"reward_scheme must be one of {REWARD_SCHEMES}, got {reward_scheme!r}")
    max_steps = _require_int("max_steps", overrides.get("max_steps", spec.max_steps), 1, MAX_INT32)
    landmark_placements = landmark_action.check(spec.dim, overrides.get("landmark_action", 0))
    bank_size = overrides.get("design_bank_size", DEFAULT_DESIGN_BANK_SIZE)
    change = design_change.check(
        spec.dynamic,
        overrides.get("design_change"),
        max_steps,
        "test_design" in overrides,
        int(bank_size) if _is_int(bank_size) else 2,  # a bad size is refused below, by name
    )

    for name in ("test_design", "design_bank_size", "design_seed"):
        if name in overrides and not spec.dynamic:
            raise ValueError(f"{name} applies to dynamic tasks only; {task_id!r} is static")
    if spec.dynamic and "test_design" in overrides:
        index = _require_int("test_design", overrides["test_design"], 0, designs.NUM_TEST_DESIGNS - 1)
        if "design_bank_size" in overrides or "design_seed" in overrides:
            raise ValueError("test_design pins one design: it cannot be combined with design_bank_size or design_seed")
        design_stack = designs.fixed_design(test_design_names(task_id)[index])[None]
    elif spec.dynamic:
        size = _require_int("design_bank_size", overrides.get("design_bank_size", DEFAULT_DESIGN_BANK_SIZE), 1)
        seed = _require_int("design_seed", overrides.get("design_seed", 0), 0, MAX_SEED)
        density = None if spec.dim == 1 else spec.design
        memory.require(f"a bank of {size:,} designs", size * _bank_bytes_per_design(spec.dim), "lower design_bank_size")
        design_stack = designs.design_bank(spec.dim, density, size, seed)
    else:
        design_stack = designs.fixed_design(spec.design)[None]

    if landmarks:
        free_cells = int(np.min(np.sum(design_stack == 0, axis=(1, 2))))
        if landmarks > free_cells:
            raise ValueError(f"landmarks must be at most {free_cells} (the free cells of the design), got {landmarks}")

    config = EnvConfig(
        task_id=task_id,
        dim=spec.dim,
        dynamic=spec.dynamic,
        half_window=spec.half_window,
        obstacles=obstacles,
        binary_grid=spec.dim == 2,
        reward_scheme=reward_scheme,
        gps=gps,
        num_landmarks=landmarks,
        landmark_action=landmark_placements,
        design_change=change,
    )
    params = make_params(design_stack, spec.dim, stride_probs=stride_probs, max_steps=max_steps)
    return SNACEnv(config, params), params


def make_params(
    design_stack: np.ndarray, dim: int, stride_probs=DEFAULT_STRIDE_PROBS, max_steps: int = MAX_INT32
) -> EnvParams:
    """`EnvParams` whose resets draw from `design_stack` (K, *plan_shape). `make` passes the
    task's step limit; a caller that only wants the design fields (a swapped design stack) may
    leave `max_steps` out."""
    design_stack = np.asarray(design_stack, dtype=np.int16)
    return EnvParams(
        designs=jnp.asarray(design_stack),
        design_max_bricks=jnp.asarray(designs.max_bricks_for(design_stack, dim)),
        design_volume=jnp.asarray(design_stack.reshape(len(design_stack), -1).sum(axis=1), dtype=jnp.int32),
        stride_probs=jnp.asarray(stride_probs, dtype=jnp.float32),
        max_steps_in_episode=jnp.asarray(max_steps, dtype=jnp.int32),
    )
