"""The presets of `snac table` (`budgets.toml`): what each cell of a grid trains and how it is
scored. A cell is (algorithm, task, env-step budget, arm overrides, seeds); an ablation preset's
arms (`variants`) are overrides of one base arm, whose cell may be another preset's (`adopts`).
Read once and checked, so that a typo in the file fails before any training."""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path
from typing import Any

from snac_jax.evaluation import EPISODES_PER_TEST_DESIGN, STATIC_EPISODES
from snac_jax.paper import PAPER_GROUPS, PAPER_TASKS, paper_column
from snac_jax.tasks import TASKS, parse_switches

BASE_ARM = "base"  # the arm every other arm of an ablation preset is measured against
BUDGETS_FILE = Path(__file__).parent / "budgets.toml"
_PLANNED = {"seeds", "seed", "switches", "total_steps", "task"}  # what an arm's settings cannot change
_PRESET_KEYS = (
    "adopts algorithms budgets description episodes_per_test_design seeds settings static_episodes tasks variants"
)
_ARM_KEYS = {"paper", "switches", "settings", "evaluation", "tasks"}


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


def arm_changes(switches: str, settings: dict[str, Any], evaluation: dict[str, Any] | None = None) -> str:
    """An arm's changes as the table prints them: switches, settings, then evaluation-only settings."""
    return ", ".join(
        ([switches] if switches else [])
        + [f"{k}={json.dumps(v)}" for k, v in sorted(settings.items())]
        + [f"{k}={json.dumps(v)} at evaluation" for k, v in sorted((evaluation or {}).items())]
    )


@dataclasses.dataclass(frozen=True)
class Preset:
    name: str
    description: str
    seeds: int
    budgets: dict[str, dict[str, Any]]
    settings: dict[str, Any]
    static_episodes: int = STATIC_EPISODES
    episodes_per_test_design: int = EPISODES_PER_TEST_DESIGN
    algorithms: tuple[str, ...] | None = None  # the grid's defaults (None: every algorithm, every column)
    tasks: tuple[str, ...] | None = None
    variants: tuple[Variant, ...] = ()  # an ablation's arms; empty: one cell per (algorithm, task)
    adopts: str | None = None  # the preset whose cell is the base arm where it trained the base arm's config

    def overrides(self, algorithm: str) -> dict[str, Any]:
        """The preset's settings for `algorithm`: the shared ones, then the algorithm's own."""
        shared = {k: v for k, v in self.settings.items() if not isinstance(v, dict)}
        return {**shared, **self.settings.get(algorithm, {})}

    @property
    def protocol(self) -> dict[str, int]:
        return {"static_episodes": self.static_episodes, "episodes_per_test_design": self.episodes_per_test_design}


def load_presets(path: str | Path = BUDGETS_FILE) -> dict[str, Preset]:
    tables = tomllib.loads(Path(path).read_text())
    presets = {}
    for name, table in tables.items():
        unknown = sorted(set(table) - set(_PRESET_KEYS.split()))
        if unknown:
            raise ValueError(
                f"{path}: [{name}] has unknown key(s) {unknown}; allowed: {', '.join(_PRESET_KEYS.split())}"
            )
        where, tasks = f"{path}: [{name}.variants", table.get("tasks")
        variants = tuple(_variant(f"{where}.{k}]", k, v, tasks) for k, v in table.get("variants", {}).items())
        presets[name] = preset = Preset(
            name=name,
            description=table.get("description", ""),
            seeds=int(table.get("seeds", 1)),
            budgets={a: _budget(path, tables, name, a, b) for a, b in table.get("budgets", {}).items()},
            settings=table.get("settings", {}),
            static_episodes=int(table.get("static_episodes", STATIC_EPISODES)),
            episodes_per_test_design=int(table.get("episodes_per_test_design", EPISODES_PER_TEST_DESIGN)),
            algorithms=tuple(table["algorithms"]) if "algorithms" in table else None,
            tasks=tuple(table["tasks"]) if "tasks" in table else None,
            variants=variants,
            adopts=table.get("adopts"),
        )
        arms = {v.name: v for v in variants}
        if arms and BASE_ARM not in arms:
            raise ValueError(
                f"{path}: [{name}.variants] needs an arm named base (every other arm is reported against it)"
            )
        if arms and (arms[BASE_ARM].evaluation or arms[BASE_ARM].settings or arms[BASE_ARM].switches) and preset.adopts:
            raise ValueError(f"{path}: [{name}] adopts another preset's cells: its base arm may change nothing")
    for name, preset in presets.items():
        plain = sorted(n for n, p in presets.items() if n != name and not p.variants)
        if preset.adopts is not None and preset.adopts not in plain:
            raise ValueError(
                f"{path}: [{name}] adopts {preset.adopts!r}; it can adopt the runs of another preset "
                f"without arms (its cells are named by the task alone): {', '.join(plain) or 'none'}"
            )
    return presets


def _budget(path, tables: dict, preset: str, algorithm: str, budget: dict) -> dict:
    """A budget entry checked: `env_steps` (one number, or one per environment task) or `episodes`,
    and a `source`; or `same_as = "PRESET.ALGORITHM"`, that entry's (a budget stated once)."""
    where = f"{path}: [{preset}.budgets] {algorithm}"
    if "same_as" in budget:
        if set(budget) != {"same_as"}:
            raise ValueError(f"{where} gives same_as and {sorted(set(budget) - {'same_as'})}; same_as stands alone")
        other, _, learner = str(budget["same_as"]).partition(".")
        target = tables.get(other, {}).get("budgets", {}).get(learner)
        if not isinstance(target, dict) or "same_as" in target or not {"env_steps", "episodes"} & set(target):
            raise ValueError(
                f"{where}'s same_as must name, as PRESET.ALGORITHM, another entry with env_steps or episodes"
            )
        whose = f"the {other} preset's budget" if learner == algorithm else f"{learner}'s budget in the {other} preset"
        steps = {k: v for k, v in target.items() if k in ("env_steps", "episodes")}
        return {**steps, "source": f"{whose}, {target['source']}" if "source" in target else whose}
    unknown = sorted(set(budget) - {"env_steps", "episodes", "source"})
    if unknown or ("env_steps" in budget and "episodes" in budget):
        raise ValueError(
            f"{where} must give env_steps or episodes (and a source), or same_as"
            + (f"; unknown key(s) {unknown}" if unknown else "")
        )
    per_task = budget.get("env_steps")
    if isinstance(per_task, dict) and set(per_task) - set(TASKS):
        raise ValueError(f"{where}'s env_steps names unknown task(s) {sorted(set(per_task) - set(TASKS))}")
    return budget


def _variant(where: str, name: str, table: dict, tasks) -> Variant:
    """An arm; its `tasks` default to its preset's."""
    table = {"tasks": tasks, **table} if tasks is not None else table
    unknown = sorted(set(table) - _ARM_KEYS)
    if unknown or "tasks" not in table:
        raise ValueError(
            f"{where} must give tasks (or its preset), and may give paper, switches, settings and evaluation"
            + (f"; unknown key(s) {unknown}" if unknown else "")
        )
    settings, evaluation = table.get("settings", {}), table.get("evaluation", {})
    for key, options in (("settings", settings), ("evaluation", evaluation)):
        if sorted(set(options) & _PLANNED):
            raise ValueError(
                f"{where}: {key} may not set {sorted(set(options) & _PLANNED)}: the plan sets {', '.join(sorted(_PLANNED))}"
            )
    if evaluation and (settings or table.get("switches")):
        raise ValueError(f"{where}: an arm with evaluation settings scores the base arm's run: no settings or switches")
    try:
        parse_switches(table.get("switches", ""))
        tasks = tuple(task for _, task in expand_tasks(table["tasks"]))
    except ValueError as error:
        raise ValueError(f"{where}: {error}") from None
    return Variant(name, table.get("paper", ""), table.get("switches", ""), tasks, settings, evaluation)


def expand_tasks(names) -> list[tuple[str, str]]:
    """(paper column, environment task) pairs of paper columns (`1d-static`: its three shapes)
    or environment task ids, in order, without repeats."""
    pairs = []
    for name in names:
        if name in PAPER_GROUPS:
            pairs += [(name, task) for task in PAPER_GROUPS[name]]
        elif name in TASKS:
            pairs.append((paper_column(name), name))
        else:
            raise ValueError(
                f"unknown task {name!r}; allowed: {', '.join(PAPER_TASKS)} or an environment task ({', '.join(TASKS)})"
            )
    return list(dict.fromkeys(pairs))
