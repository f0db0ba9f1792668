"""The presets of `snac table` (`budgets.toml`): what each cell of a grid trains and how it is
scored. A cell is (algorithm, task, env-step budget, arm overrides, seeds); an ablation preset's
arms (`variants`) are overrides of its own base arm. Read once and checked against one schema, so
that a typo in the file fails before any training."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

from snac_jax.evaluation import EPISODES_PER_TEST_DESIGN, STATIC_EPISODES
from snac_jax.paper import PAPER_GROUPS, PAPER_TASKS
from snac_jax.schema import Anything, Either, Int, ListOf, MapOf, Object, Str, check
from snac_jax.tasks import TASKS, parse_switches

BASE_ARM = "base"  # the arm every other arm of an ablation preset is measured against
BUDGETS_FILE = Path(__file__).parent / "budgets.toml"
_PLANNED = {"seeds", "seed", "switches", "total_steps", "task"}  # what an arm's settings cannot change

_BUDGET = Object(
    {},
    {"env_steps": Either(Int(1), Object({}, {task: Int(1) for task in TASKS})), "episodes": Int(1), "source": Str()},
)
_ARM = Object(
    {},
    {
        "paper": Str(),
        "switches": Str(),
        "settings": MapOf(Anything()),
        "evaluation": MapOf(Anything()),
        "tasks": ListOf(Str()),
    },
)
PRESETS_SCHEMA = MapOf(
    Object(
        {},
        {
            "description": Str(),
            "seeds": Int(1),
            "algorithms": ListOf(Str()),
            "tasks": ListOf(Str()),
            "budgets": MapOf(_BUDGET),
            "settings": MapOf(Anything()),
            "static_episodes": Int(1),
            "episodes_per_test_design": Int(1),
            "variants": MapOf(_ARM),
        },
    )
)
"""budgets.toml: one table per preset (`Preset`), a budget per algorithm, an arm per variant."""


@dataclasses.dataclass(frozen=True)
class Variant:
    """An ablation's arm: the switches and learner settings it changes, the learner settings its
    greedy policy acts with only when scored (`evaluation`: it trains nothing, and scores the base
    arm's run again), its tasks, and its name in the paper's ablation table ("" if none)."""

    name: str
    paper: str
    switches: str
    tasks: tuple[str, ...]
    settings: dict[str, Any] = dataclasses.field(default_factory=dict)
    evaluation: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Preset:
    name: str
    description: str
    seeds: int
    budgets: dict[str, dict[str, Any]]
    settings: dict[str, Any]
    protocol: dict[str, int]  # the episode counts each cell is scored over (`snac_jax.evaluation`)
    algorithms: tuple[str, ...] | None = None  # the grid's defaults (None: every algorithm, every column)
    tasks: tuple[str, ...] | None = None
    variants: tuple[Variant, ...] = ()  # an ablation's arms; empty: one cell per (algorithm, task)

    def overrides(self, algorithm: str) -> dict[str, Any]:
        """The preset's settings for `algorithm`: the shared ones, then the algorithm's own."""
        shared = {k: v for k, v in self.settings.items() if not isinstance(v, dict)}
        return {**shared, **self.settings.get(algorithm, {})}


def load_presets(path: str | Path = BUDGETS_FILE) -> dict[str, Preset]:
    presets = {}
    for name, table in check(tomllib.loads(Path(path).read_text()), PRESETS_SCHEMA, path).items():
        for algorithm, budget in table.get("budgets", {}).items():
            if "env_steps" in budget and "episodes" in budget:
                raise ValueError(f"{path}: {name}.budgets.{algorithm} gives env_steps and episodes; one or the other")
        where = f"{path}: [{name}.variants"
        arms = {k: _variant(f"{where}.{k}]", k, v, table.get("tasks")) for k, v in table.get("variants", {}).items()}
        if arms and BASE_ARM not in arms:
            raise ValueError(f"{where}] needs an arm named base (every other arm is reported against it)")
        if arms.get(BASE_ARM) and arms[BASE_ARM].evaluation:
            raise ValueError(f"{where}.base]: the base arm trains the run the other arms are measured against")
        protocol = {
            "static_episodes": table.get("static_episodes", STATIC_EPISODES),
            "episodes_per_test_design": table.get("episodes_per_test_design", EPISODES_PER_TEST_DESIGN),
        }
        presets[name] = Preset(
            name=name,
            description=table.get("description", ""),
            seeds=table.get("seeds", 1),
            budgets=table.get("budgets", {}),
            settings=table.get("settings", {}),
            protocol=protocol,
            algorithms=tuple(table["algorithms"]) if "algorithms" in table else None,
            tasks=tuple(table["tasks"]) if "tasks" in table else None,
            variants=tuple(arms.values()),
        )
    return presets


def _variant(where: str, name: str, table: dict, tasks) -> Variant:
    """An arm; its `tasks` default to its preset's."""
    table = {"tasks": tasks, **table} if tasks is not None else table
    if "tasks" not in table:
        raise ValueError(f"{where} must give tasks (or its preset)")
    settings, evaluation = table.get("settings", {}), table.get("evaluation", {})
    for key, options in (("settings", settings), ("evaluation", evaluation)):
        if set(options) & _PLANNED:
            raise ValueError(
                f"{where}: {key} may not set {sorted(set(options) & _PLANNED)}: the plan sets {', '.join(sorted(_PLANNED))}"
            )
    if evaluation and (settings or table.get("switches")):
        raise ValueError(f"{where}: an arm with evaluation settings scores the base arm's run: no settings or switches")
    try:
        parse_switches(table.get("switches", ""))
        tasks = tuple(expand_tasks(table["tasks"]))
    except ValueError as error:
        raise ValueError(f"{where}: {error}") from None
    return Variant(name, table.get("paper", ""), table.get("switches", ""), tasks, settings, evaluation)


def expand_tasks(names) -> list[str]:
    """The environment tasks of paper columns (`1d-static`: its three shapes) or environment task
    ids, in order, without repeats."""
    tasks = []
    for name in names:
        if name not in PAPER_GROUPS and name not in TASKS:
            raise ValueError(
                f"unknown task {name!r}; allowed: {', '.join(PAPER_TASKS)} or an environment task ({', '.join(TASKS)})"
            )
        tasks += PAPER_GROUPS.get(name, (name,))
    return list(dict.fromkeys(tasks))
