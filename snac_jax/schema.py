"""Every file the project reads back is checked against one schema, here, before any field is used.

A file edited by hand, cut short by a full disk or written by another program must fail with one
line naming the file and the field (`<file>: seeds must be an int >= 1, got '2'`), never with a
`KeyError` deep inside a report, and never be half-read. A schema is a small tree of specs
(`Int`, `Number`, `Bool`, `Str`, `ListOf`, `Object`, `MapOf`, `Nullable`, `Either`, `Anything`), each of
which says in words what it allows; `check` walks a parsed value against it and `load_json` reads,
parses and checks a file. Numbers are always finite: JSON readers accept `NaN` and `Infinity`,
and a score of NaN is no score.

The schema of each file lives beside its other rules and is defined once: the human records'
here (`HUMAN_RECORD`, read by `snac_jax.human.records`), the learners' run files (`config.json`,
`run.json`, `cell.json`, `eval.json`) in `agents.training.schemas`, with this checker.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from snac_jax.designs import NUM_TEST_DESIGNS
from snac_jax.tasks import MAX_INT32, MAX_SEED, TASKS


class SchemaError(ValueError):
    """A file, or one record of it, that does not match its schema; the message is one line
    naming the file and the field."""


class Mismatch(Exception):
    """What a spec raises: the text that follows the file's name in the `SchemaError`."""


def subfield(prefix: str, key: Any) -> str:
    """`prefix.key`, or `prefix['key']` where the key is not a plain word (eval.json's
    `'2d-static-sparse (seed 0)'`), or `prefix[3]` in a list."""
    if isinstance(key, int):
        return f"{prefix}[{key}]"
    if re.fullmatch(r"[\w-]+", str(key)):
        return f"{prefix}.{key}" if prefix else str(key)
    return f"{prefix}[{str(key)!r}]"


def mismatch(field: str, what: str, value: Any) -> Mismatch:
    """`field must be <what>, got <value>` (a long value shortened)."""
    shown = repr(value)
    return Mismatch(f"{field} must be {what}, got {shown if len(shown) <= 60 else shown[:57] + '...'}")


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


class Spec:
    """What one field allows: `describe()` in words, `check(value, field)` raising `Mismatch`."""

    def describe(self) -> str:
        raise NotImplementedError

    def plural(self) -> str:
        """The description of many such values ('ints >= 0'), for lists."""
        return f"each {self.describe()}"

    def check(self, value: Any, field: str) -> None:
        raise NotImplementedError


class Anything(Spec):
    def describe(self) -> str:
        return "any JSON value"

    def check(self, value: Any, field: str) -> None:
        pass


def _range(low: float | None, high: float | None, both: str) -> str:
    """' in <both>', ' >= low', ' <= high' or '', as the bounds given."""
    if low is not None and high is not None:
        return f" in {both}"
    if low is not None:
        return f" >= {low:g}"
    return "" if high is None else f" <= {high:g}"


class Int(Spec):
    def __init__(self, low: int | None = None, high: int | None = None):
        self.low, self.high = low, high

    def describe(self) -> str:
        return "an int" + _range(self.low, self.high, f"{self.low}..{self.high}")

    def plural(self) -> str:
        return "ints" + _range(self.low, self.high, f"{self.low}..{self.high}")

    def check(self, value: Any, field: str) -> None:
        if not (
            _is_int(value) and (self.low is None or value >= self.low) and (self.high is None or value <= self.high)
        ):
            raise mismatch(field, self.describe(), value)


class Number(Spec):
    """A finite number (an int or a float), within the bounds given."""

    def __init__(self, low: float | None = None, high: float | None = None):
        self.low, self.high = low, high

    def _range(self) -> str:
        return _range(
            self.low, self.high, f"[{self.low:g}, {self.high:g}]" if None not in (self.low, self.high) else ""
        )

    def describe(self) -> str:
        return "a finite number" + self._range()

    def plural(self) -> str:
        return "finite numbers" + self._range()

    def check(self, value: Any, field: str) -> None:
        if not (
            _is_number(value) and (self.low is None or value >= self.low) and (self.high is None or value <= self.high)
        ):
            raise mismatch(field, self.describe(), value)


class Bool(Spec):
    def describe(self) -> str:
        return "true or false"

    def check(self, value: Any, field: str) -> None:
        if not isinstance(value, bool):
            raise mismatch(field, self.describe(), value)


class Str(Spec):
    """A string, or one of `choices` (an unknown one is named with the allowed values)."""

    def __init__(self, choices: Iterable[str] | None = None):
        self.choices = None if choices is None else tuple(choices)

    def describe(self) -> str:
        return "a string" if self.choices is None else f"one of {', '.join(self.choices)}"

    def plural(self) -> str:
        return "strings" if self.choices is None else f"each one of {', '.join(self.choices)}"

    def check(self, value: Any, field: str) -> None:
        if self.choices is not None and value not in self.choices:
            raise Mismatch(f"unknown {field} {value!r}; allowed: {', '.join(self.choices)}")
        if not isinstance(value, str):
            raise mismatch(field, self.describe(), value)


class OneOf(Spec):
    """One of a few fixed JSON values (ints, say)."""

    def __init__(self, *values: Any):
        self.values = values

    def describe(self) -> str:
        shown = [json.dumps(v) for v in self.values]
        return ", ".join(shown[:-1]) + f" or {shown[-1]}" if len(shown) > 1 else shown[0]

    def plural(self) -> str:
        return self.describe()

    def check(self, value: Any, field: str) -> None:
        if not any(type(value) is type(v) and value == v for v in self.values):
            raise mismatch(field, self.describe(), value)


class Either(Spec):
    """A value that matches one of `specs` (a number, or a table of numbers)."""

    def __init__(self, *specs: Spec):
        self.specs = specs

    def describe(self) -> str:
        return " or ".join(spec.describe() for spec in self.specs)

    def check(self, value: Any, field: str) -> None:
        errors = []
        for spec in self.specs:
            try:
                return spec.check(value, field)
            except Mismatch as error:
                errors.append(str(error))
        raise Mismatch(errors[-1] if isinstance(value, dict) else str(mismatch(field, self.describe(), value)))


class Nullable(Spec):
    def __init__(self, spec: Spec):
        self.spec = spec

    def describe(self) -> str:
        return f"{self.spec.describe()} or null"

    def check(self, value: Any, field: str) -> None:
        if value is not None:
            try:
                self.spec.check(value, field)
            except Mismatch:
                raise mismatch(field, self.describe(), value) from None


class ListOf(Spec):
    """A list of items of one spec; `length`: exactly that many."""

    def __init__(self, item: Spec, length: int | None = None):
        self.item, self.length = item, length

    def describe(self) -> str:
        return f"a list of {'' if self.length is None else f'{self.length} '}{self.item.plural()}"

    def plural(self) -> str:
        return f"lists of {self.item.plural()}"

    def check(self, value: Any, field: str) -> None:
        if not isinstance(value, list) or (self.length is not None and len(value) != self.length):
            raise mismatch(field, self.describe(), value)
        for index, item in enumerate(value):
            try:
                self.item.check(item, subfield(field, index))
            except Mismatch as inner:
                if isinstance(self.item, (ListOf, Object, MapOf)):
                    raise
                raise Mismatch(f"{field} must be {self.item.plural()}, got {item!r} at position {index}") from inner


class Object(Spec):
    """A JSON object with named fields: `required` must be there, `optional` may be; any other
    name is refused (a misspelt field is not silently ignored)."""

    def __init__(self, required: Mapping[str, Spec], optional: Mapping[str, Spec] | None = None):
        self.required, self.optional = dict(required), dict(optional or {})

    def describe(self) -> str:
        return "an object"

    def plural(self) -> str:
        return "objects"

    def check(self, value: Any, field: str) -> None:
        if not isinstance(value, dict):
            raise Mismatch(
                f"{field} must be an object, got {type(value).__name__}"
                if field
                else f"must hold a JSON object, got {type(value).__name__}"
            )
        allowed = {**self.required, **self.optional}
        unknown = [k for k in value if k not in allowed]
        if unknown:
            where = f" in {field}" if field else ""
            raise Mismatch(f"unknown field(s) {unknown}{where}; allowed: {', '.join(allowed)}")
        for name, spec in allowed.items():
            if name in value:
                spec.check(value[name], subfield(field, name))
            elif name in self.required:
                raise Mismatch(f"{subfield(field, name)} is missing ({spec.describe()})")


class MapOf(Spec):
    """A JSON object whose keys are free (a task, a design) and whose values share one spec."""

    def __init__(self, value: Spec, min_items: int = 0):
        self.value, self.min_items = value, min_items

    def describe(self) -> str:
        return "an object" + (f" of at least {self.min_items} entries" if self.min_items else "")

    def check(self, value: Any, field: str) -> None:
        if not isinstance(value, dict):
            raise Mismatch(
                f"{field} must be an object, got {type(value).__name__}"
                if field
                else f"must hold a JSON object, got {type(value).__name__}"
            )
        if len(value) < self.min_items:
            raise Mismatch(f"{field or 'it'} must have at least {self.min_items} entries, got {len(value)}")
        for key, item in value.items():
            self.value.check(item, subfield(field, key))


def check(data: Any, schema: Spec, where: str | Path) -> Any:
    """`data` when it matches `schema`, else `SchemaError` naming `where` (a file, or a file's
    line; "" where the caller names it) and the field."""
    try:
        schema.check(data, "")
    except Mismatch as error:
        text = str(error)
        if not str(where):
            raise SchemaError(text) from None
        raise SchemaError(f"{where} {text}" if text.startswith("must hold") else f"{where}: {text}") from None
    return data


def loads_json(text: str, schema: Spec, where: str | Path) -> Any:
    """Parse `text` (the content of `where`) and check it."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise SchemaError(f"{where} is not valid JSON ({error}); it is damaged or was edited by hand") from None
    return check(data, schema, where)


def load_json(path: str | Path, schema: Spec) -> Any:
    """Read, parse and check the JSON file at `path`; an unreadable file is the `OSError` itself."""
    path = Path(path)
    try:
        text = path.read_text()
    except UnicodeDecodeError as error:
        raise SchemaError(f"{path} is not valid JSON ({error}); it is damaged or was edited by hand") from None
    return loads_json(text, schema, path)


# --- the files snac_jax reads ----------------------------------------------------------------------

MODES = ("train", "eval")
"""`train`: the player sees per-step and total reward; `eval`: only steps and bricks (paper)."""

HUMAN_RECORD = Object(
    required={
        "task": Str(TASKS),
        "mode": Str(MODES),
        "seed": Int(0, MAX_SEED),
        "test_design": Nullable(Int(0, NUM_TEST_DESIGNS - 1)),
        "design": ListOf(ListOf(Int())),
        "max_steps": Int(1, MAX_INT32),
        "actions": ListOf(Int(0)),
        "strides": ListOf(OneOf(1, 2, 3)),
        "total_reward": Number(),
        "bricks_used": Int(0, MAX_INT32),
        "terminated": Bool(),
        "iou": Number(0.0, 1.0),
        "duration_s": Number(0.0),
        "started_at": Str(),
    },
    optional={"player": Nullable(Str()), "switches": Str(), "version": Int(1)},
)
"""One line of a human record file (`snac_jax.human.records.EpisodeRecord`); the rules that tie
fields together (lengths, the design's shape, which records play a test design, the switch
keys) are the record's `validate`. A record without `switches` was played without any."""
