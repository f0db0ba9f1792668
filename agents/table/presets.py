"""The presets of `snac table` (`budgets.toml`): how much each cell of a grid trains, how it is
scored, and an ablation's arms; and the task names a grid accepts (paper columns or environment
tasks). Read once, checked at the boundary, so that a typo in the file fails before any training."""

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
_PLANNED_OPTIONS = {"seeds", "seed", "switches", "total_steps", "task"}  # what an arm's settings cannot change
_BUDGET_KEYS = ("env_steps", "episodes", "source")
_PRESET_KEYS = {
    "description",
    "seeds",
    "budgets",
    "settings",
    "static_episodes",
    "episodes_per_test_design",
    "algorithms",
    "tasks",
    "variants",
    "adopts",
}


@dataclasses.dataclass(frozen=True)
class Variant:
    """An ablation's arm: the environment switches its cells train and are scored with, the
    learner settings it changes (an ingredient of a learner switched off), the learner settings
    its greedy policy acts with only when scored (`evaluation`: the arm trains as the base arm,
    so it takes over the run the base arm adopts, checkpoints and all, and scores those params
    again), its tasks, and its name in the paper's ablation table ("" where the paper has no
    such arm)."""

    name: str
    paper: str
    switches: str
    tasks: tuple[str, ...]
    settings: dict[str, Any] = dataclasses.field(default_factory=dict)
    evaluation: dict[str, Any] = dataclasses.field(default_factory=dict)


def arm_changes(switches: str, settings: dict[str, Any], evaluation: dict[str, Any] | None = None) -> str:
    """An ablation arm's changes as the table prints them: its switches, its settings, then its
    evaluation-only settings."""
    return ", ".join(
        ([switches] if switches else [])
        + [f"{k}={json.dumps(v)}" for k, v in sorted(settings.items())]
        + [f"{k}={json.dumps(v)} at evaluation" for k, v in sorted((evaluation or {}).items())]
    )


@dataclasses.dataclass(frozen=True)
class Preset:
    """One table of budgets.toml: how much each cell trains and how it is scored."""

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
    adopts: str | None = None  # a preset whose finished run with a cell's very settings the cell takes over

    def adopted_base(self) -> Variant | None:
        """The base arm where it is another preset's cells as they are (the preset `adopts` and the
        arm changes nothing): what the report reads from that preset's raw copies (`raw.with_adopted_bases`)."""
        base = next((v for v in self.variants if v.name == BASE_ARM), None)
        return None if base is None or self.adopts is None or base.switches or base.settings else base

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
        unknown = sorted(set(table) - _PRESET_KEYS)
        if unknown:
            raise ValueError(
                f"{path}: [{name}] has unknown key(s) {unknown}; allowed: {', '.join(sorted(_PRESET_KEYS))}"
            )
        table = {
            **table,
            "budgets": {
                algorithm: _same_as(path, tables, name, algorithm, budget)
                for algorithm, budget in table.get("budgets", {}).items()
            },
        }
        for algorithm, budget in table["budgets"].items():
            unknown = sorted(set(budget) - set(_BUDGET_KEYS))
            if unknown or ("env_steps" in budget and "episodes" in budget):
                raise ValueError(
                    f"{path}: [{name}.budgets] {algorithm} must give env_steps or episodes (and a source), or "
                    "same_as" + (f"; unknown key(s) {unknown}" if unknown else "")
                )
            per_task = budget.get("env_steps")
            if isinstance(per_task, dict) and sorted(set(per_task) - set(TASKS)):
                raise ValueError(
                    f"{path}: [{name}.budgets] {algorithm}'s env_steps names unknown task(s) "
                    f"{sorted(set(per_task) - set(TASKS))}; allowed: {', '.join(TASKS)}"
                )
        presets[name] = Preset(
            name=name,
            description=table.get("description", ""),
            seeds=int(table.get("seeds", 1)),
            budgets=table.get("budgets", {}),
            settings=table.get("settings", {}),
            static_episodes=int(table.get("static_episodes", STATIC_EPISODES)),
            episodes_per_test_design=int(table.get("episodes_per_test_design", EPISODES_PER_TEST_DESIGN)),
            algorithms=tuple(table["algorithms"]) if "algorithms" in table else None,
            tasks=tuple(table["tasks"]) if "tasks" in table else None,
            variants=tuple(_variant(path, name, key, value) for key, value in table.get("variants", {}).items()),
            adopts=table.get("adopts"),
        )
        arms = {v.name: v for v in presets[name].variants}
        if arms and BASE_ARM not in arms:
            raise ValueError(
                f"{path}: [{name}.variants] needs an arm named base (every other arm is reported against it)"
            )
        if any(v.evaluation for v in arms.values()) and (
            arms[BASE_ARM].evaluation or arms[BASE_ARM].settings or arms[BASE_ARM].switches or "adopts" not in table
        ):
            raise ValueError(
                f"{path}: [{name}] has an arm with evaluation settings, which scores the base arm's run "
                "again: the preset must adopt another's runs, and its base arm give no settings, switches "
                "or evaluation"
            )
    for name, preset in presets.items():
        plain = sorted(n for n, p in presets.items() if n != name and not p.variants)
        if preset.adopts is not None and preset.adopts not in plain:
            raise ValueError(
                f"{path}: [{name}] adopts {preset.adopts!r}; it can adopt the runs of another preset "
                f"without arms (its cells are named by the task alone): {', '.join(plain) or 'none'}"
            )
    return presets


def _same_as(path, tables: dict, preset: str, algorithm: str, budget: dict) -> dict:
    """`budget` with `same_as = "PRESET.ALGORITHM"` replaced by that entry's env steps or
    episodes and source. Why: a budget another preset reuses (the paper's, for an ablation) is
    stated once, where it comes from."""
    if "same_as" not in budget:
        return budget
    if set(budget) != {"same_as"}:
        raise ValueError(
            f"{path}: [{preset}.budgets] {algorithm} gives same_as and {sorted(set(budget) - {'same_as'})}; "
            "same_as stands alone (or give env_steps or episodes, and a source)"
        )
    reference = budget["same_as"]
    other, _, learner = str(reference).partition(".")
    target = tables.get(other, {}).get("budgets", {}).get(learner) if isinstance(tables.get(other), dict) else None
    if not isinstance(target, dict) or "same_as" in target or not {"env_steps", "episodes"} & set(target):
        raise ValueError(
            f"{path}: [{preset}.budgets] {algorithm}'s same_as must name, as PRESET.ALGORITHM, another "
            f"entry that gives env_steps or episodes itself, got {reference!r}"
        )
    whose = f"the {other} preset's budget" if learner == algorithm else f"{learner}'s budget in the {other} preset"
    return {
        **{k: v for k, v in target.items() if k in ("env_steps", "episodes")},
        "source": f"{whose}, {target['source']}" if "source" in target else whose,
    }


def _variant(path, preset: str, name: str, table: dict) -> Variant:
    where = f"{path}: [{preset}.variants.{name}]"
    unknown = sorted(set(table) - {"paper", "switches", "settings", "evaluation", "tasks"})
    if unknown or "tasks" not in table:
        raise ValueError(
            f"{where} must give tasks, and may give paper, switches, settings and evaluation"
            + (f"; unknown key(s) {unknown}" if unknown else "")
        )
    settings, evaluation = table.get("settings", {}), table.get("evaluation", {})
    for key, options in (("settings", settings), ("evaluation", evaluation)):
        if not isinstance(options, dict):
            raise ValueError(f"{where}: {key} must be a table of learner options, e.g. {{ position_coef = 0.0 }}")
        reserved = sorted(set(options) & _PLANNED_OPTIONS)
        if reserved:
            raise ValueError(
                f"{where}: {key} may not set {reserved}: the plan sets {', '.join(sorted(_PLANNED_OPTIONS))}"
                + (" (give an environment change as switches)" if key == "settings" else "")
            )
    if evaluation and (settings or table.get("switches")):
        raise ValueError(
            f"{where}: an arm with evaluation settings trains as the base arm (it scores the base's run "
            "again), so it may not give settings or switches"
        )
    try:
        parse_switches(table.get("switches", ""))
        tasks = tuple(task for _, task in expand_tasks(table["tasks"]))
    except ValueError as error:
        raise ValueError(f"{where}: {error}") from None
    return Variant(
        name=name,
        paper=table.get("paper", ""),
        switches=table.get("switches", ""),
        tasks=tasks,
        settings=settings,
        evaluation=evaluation,
    )


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
