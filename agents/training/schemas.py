"""The schemas of the files a run directory and the table keep, checked with `snac_jax.schema`.

Each file has one schema, defined here once, and every place that reads the file reads it through
`load` (or `read_config`'s use of `config_json`), so a damaged or hand-edited file fails with one
line naming the file and the field, whoever reads it:

- `config.json`: the fields of the run's config class (`agents.training.config.option`: type and bounds),
  checked from the same declarations that validate a config made in code;
- `run.json`: the options of `snac train` kept for a resume (`agents.training.cli.RUN_OPTIONS`);
- `cell.json`: what `snac table` keeps beside them (`agents.table.plan.Cell.record`);
- `eval.json`: the protocol's results, one row per training seed (`snac_jax.evaluation.TaskResult`),
  every IoU in [0, 1]; `bench/results/handcrafted.json` has the same rows;
- a table cell's raw copy (`bench/results/table/<preset>/<algorithm>/<task>[.<arm>].json`): the
  three above and the curve, one file, each part checked with its file's schema.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from snac_jax.paper import PAPER_TASKS
from snac_jax.schema import (
    Anything,
    Bool,
    Int,
    ListOf,
    MapOf,
    Mismatch,
    Nullable,
    Number,
    Object,
    Spec,
    Str,
    load_json,
    mismatch,
    subfield,
)
from snac_jax.tasks import MAX_SEED, TASKS


class _Declared(Spec):
    """A config field, checked by its declaration (`agents.training.config.FieldSpec`), in its words."""

    def __init__(self, spec):
        self.spec = spec

    def describe(self) -> str:
        return "a string" if self.spec.kind is str else self.spec.describe()

    def check(self, value: Any, field: str) -> None:
        if self.spec.kind is str and not (isinstance(value, str) or (self.spec.optional and value is None)):
            raise mismatch(field, self.describe(), value)
        try:
            self.spec.check(value)
        except ValueError:
            raise mismatch(field, self.describe(), value) from None


SWEPT = "swept"
"""The key of a sweep's top-level config.json naming the settings its arms set (and it leaves out)."""


class _ConfigJson(Spec):
    """config.json: `algorithm` names the config class, whose declared fields the rest must match
    (a field left out takes the class default, as runs of older versions do; a retired option
    is read, its value refused by `config_from_json` unless off); a sweep's names its swept
    settings under `swept` (`agents.training.sweep.base_config_json`)."""

    def describe(self) -> str:
        return "an object"

    def check(self, value: Any, field: str) -> None:
        from agents.training.config import field_specs
        from agents.training.registry import ALGORITHMS, config_class

        Object({"algorithm": Str(ALGORITHMS)}, {"task": Anything()}).check(
            {k: v for k, v in value.items() if k in ("algorithm", "task")} if isinstance(value, dict) else value, field
        )
        cls = config_class(value["algorithm"])
        specs = field_specs(cls)
        fields = {name: Str(TASKS) if name == "task" else _Declared(spec) for name, spec in specs.items()}
        fields[SWEPT] = ListOf(Str(tuple(specs)))  # a sweep's: the settings its arms set (agents.training.sweep)
        unknown = sorted(set(value) - set(fields) - {"algorithm"})
        if unknown:
            where = f" in {field}" if field else ""
            raise Mismatch(
                f"unknown {value['algorithm']} option(s) {unknown}{where}; allowed: {', '.join(sorted(fields))}"
            )
        Object({"algorithm": Str(ALGORITHMS)}, fields).check(value, field)


CONFIG_JSON = _ConfigJson()

RUN_JSON = Object({}, {"eval_episodes": Nullable(Int(1)), "no_eval": Bool()})

SWEEP_JSON = Object({"names": ListOf(Str()), "arms": ListOf(ListOf(Number()))})
"""A sweep's grid (`agents.training.sweep`): the swept settings' names and one list of values per arm."""

PROTOCOL = Object({"static_episodes": Int(1), "episodes_per_test_design": Int(1)})

CELL_JSON = Object(
    {
        "preset": Str(),
        "algorithm": Str(),
        "column": Str(PAPER_TASKS),
        "task": Str(TASKS),
        # `capped`: records from when the table capped budgets to a wall time (requested > env_steps then)
        "budget": Object({"env_steps": Int(1), "requested": Int(1), "source": Str()}, {"capped": Bool()}),
        "eval_seed": Int(0, MAX_SEED),
        "protocol": PROTOCOL,
    },
    {
        "variant": Str(),
        "paper_variant": Str(),
        "switches": Str(),
        "settings": MapOf(Anything()),
        "evaluation": MapOf(Anything()),
        "adopted_from": Str(),
        "adopted_record": Str(),
    },
)

IOU = Number(0.0, 1.0)

STAT_TOLERANCE = 1e-9
"""How far a reported statistic may stray past a bound it holds by construction: they are float64
sums of float32 IoUs, so the mean of equal IoUs may come out an ulp or so below them; an edited or
damaged number strays by far more."""


def _min_at_most_mean(row: dict, field: str) -> None:
    if row["min"] > row["mean"] + STAT_TOLERANCE:
        raise Mismatch(f"{subfield(field, 'min')} is {row['min']!r}, above its mean {row['mean']!r}")


class _Stratum(Object):
    """One test design's (or 1D shape's) statistics in an eval row's `per_design`: its minimum is
    at most its mean."""

    def __init__(self):
        super().__init__({"mean": IOU, "min": IOU, "std": Number(0.0), "episodes": Int(1)})

    def check(self, value: Any, field: str) -> None:
        super().check(value, field)
        _min_at_most_mean(value, field)


class _EvalRow(Object):
    """One training seed's protocol result (`snac_jax.evaluation.TaskResult`): its fields, and the
    bounds they hold together by construction (`snac_jax.evaluation.summarize`): min <= mean, the
    95% interval holds the mean, a row whose episodes laid no brick scores IoU 0 (the overlap grows
    only by a brick laid), and where it has strata, its mean is theirs, its minimum their least and
    its episodes their sum. A row that breaks one was edited or damaged, and would be reported."""

    def check(self, value: Any, field: str) -> None:
        super().check(value, field)
        _min_at_most_mean(value, field)
        low, high = value["ci95"]
        if not low - STAT_TOLERANCE <= value["mean"] <= high + STAT_TOLERANCE:
            raise Mismatch(f"{subfield(field, 'ci95')} {value['ci95']!r} does not hold its mean {value['mean']!r}")
        if value["mean_bricks_used"] == 0 and value["mean"] > STAT_TOLERANCE:
            raise Mismatch(
                f"{subfield(field, 'mean')} is {value['mean']!r} with mean_bricks_used 0: an episode that "
                "lays no brick scores IoU 0"
            )
        strata = list(value["per_design"].values())
        if not strata:
            return
        pooled = {
            "episodes": sum(s["episodes"] for s in strata),
            "mean": sum(s["mean"] for s in strata) / len(strata),
            "min": min(s["min"] for s in strata),
        }
        for name, what in (("episodes", "sum"), ("mean", "mean"), ("min", "least")):
            if abs(value[name] - pooled[name]) > STAT_TOLERANCE:
                raise Mismatch(
                    f"{subfield(field, name)} is {value[name]!r}, its per_design's {what} is {pooled[name]!r}"
                )


STRATUM = _Stratum()
EVAL_ROW = _EvalRow(
    {
        "task": Str(),
        "mean": IOU,
        "min": IOU,
        "std": Number(0.0),
        "ci95": ListOf(Number(), length=2),
        "episodes": Int(1),
        "mean_length": Number(0.0),
        "mean_bricks_used": Number(0.0),
        "mean_return": Number(),
        "per_design": MapOf(STRATUM),
        "seed": Int(0, MAX_SEED),
        "wall_s": Number(0.0),
    },
    {"overrides": MapOf(Anything())},
)  # the `make` overrides it was scored with, where not the task's own
EVAL_JSON = MapOf(EVAL_ROW, min_items=1)


class _MetricsRecord(Object):
    """One line of a run's metrics.jsonl: an object with its chunk number (the rest is what the
    learner logs; the report reads `env_steps`, `wall_s` and `iou`). An `Object`, so that a list
    of them names the record and field that is wrong."""

    def __init__(self):
        super().__init__({})

    def describe(self) -> str:
        return "a metrics record (an object with an int chunk >= 0)"

    def plural(self) -> str:
        return "metrics records"

    def check(self, value: Any, field: str) -> None:
        if not isinstance(value, dict):
            raise mismatch(field, self.describe(), value)
        Int(0).check(value.get("chunk"), f"{field}.chunk")
        for name in ("env_steps", "wall_s"):
            if name in value:
                Number(0.0).check(value[name], f"{field}.{name}")


RAW_CELL_JSON = Object({"cell": CELL_JSON, "config": CONFIG_JSON, "eval": EVAL_JSON, "curve": ListOf(_MetricsRecord())})
"""A table cell's raw copy under bench/results/table/ (`agents.table.files.read_raw`): its cell.json,
config.json and eval.json, and its metrics.jsonl's records as `curve` (empty where not kept)."""


def load(path: str | Path, schema: Spec) -> Any:
    """The JSON file at `path`, checked against `schema` (`SchemaError`, a `ValueError`, names
    the file and the field)."""
    return load_json(path, schema)
