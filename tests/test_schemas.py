"""One schema per file the project reads back, one checker: a bad field in any of them is one
line naming the file and the field, and a good file of each kind passes."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from agents.training import schemas
from snac_jax import schema
from snac_jax.schema import Bool, Int, ListOf, MapOf, Nullable, Number, Object, OneOf, SchemaError, Str
from tests.table_cells import write_cell

ROOT = Path(__file__).resolve().parents[1]


def _refused(path: Path, spec, message: str) -> str:
    with pytest.raises(SchemaError) as error:
        schema.load_json(path, spec)
    text = str(error.value)
    assert "\n" not in text and text.startswith(str(path)) and message in text, text
    return text


def _edit(path: Path, edit) -> Path:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    return path


def test_the_checker_names_the_field_and_what_it_allows(tmp_path):
    spec = Object(
        {
            "n": Int(1),
            "x": Number(0.0, 1.0),
            "flag": Bool(),
            "kind": Str(("a", "b")),
            "rows": MapOf(Object({"v": Nullable(Int(0, 9))})),
            "list": ListOf(OneOf(1, 2, 3)),
        },
        {"note": Str()},
    )
    good = {"n": 1, "x": 0.5, "flag": False, "kind": "a", "rows": {"r 1": {"v": None}}, "list": [1, 3]}
    assert schema.check(good, spec, "f.json") is good
    cases = {
        "f.json: n must be an int >= 1, got True": dict(n=True),  # a bool is no int
        "f.json: n must be an int >= 1, got 1.0": dict(n=1.0),
        "f.json: x must be a finite number in [0, 1], got nan": dict(x=float("nan")),
        "f.json: x must be a finite number in [0, 1], got -3": dict(x=-3),
        "f.json: flag must be true or false, got 'false'": dict(flag="false"),
        "f.json: unknown kind 'c'; allowed: a, b": dict(kind="c"),
        "f.json: rows['r 1'].v must be an int in 0..9 or null, got 10": dict(rows={"r 1": {"v": 10}}),
        "f.json: rows.r1 must be an object, got int": dict(rows={"r1": 3}),
        "f.json: list must be 1, 2 or 3, got 4 at position 1": dict(list=[1, 4]),
        "f.json: unknown field(s) ['extra']; allowed: n, x, flag, kind, rows, list, note": dict(extra=1),
    }
    for message, change in cases.items():
        with pytest.raises(SchemaError) as error:
            schema.check({**good, **change}, spec, "f.json")
        assert str(error.value) == message
    with pytest.raises(SchemaError, match=r"^f.json: kind is missing \(one of a, b\)$"):
        schema.check({k: v for k, v in good.items() if k != "kind"}, spec, "f.json")
    with pytest.raises(SchemaError, match=r"^f.json must hold a JSON object, got list$"):
        schema.check([], spec, "f.json")
    (tmp_path / "cut.json").write_text('{"n": 1, "x"')
    _refused(tmp_path / "cut.json", spec, "is not valid JSON")
    (tmp_path / "binary.json").write_bytes(b"\xff\xfe")
    _refused(tmp_path / "binary.json", spec, "is not valid JSON")


def test_config_json_schema_is_the_config_classs_declarations(tmp_path):
    from agents.training.config import save_config
    from agents.training.registry import make_config

    path = tmp_path / "config.json"
    save_config(make_config("ppo", "1d-dynamic", total_steps=512), path)
    assert schemas.load(path, schemas.CONFIG_JSON)["algorithm"] == "ppo"
    for edit, message in [
        (lambda d: d.update(seeds="2"), "config.json: seeds must be an int >= 1, got '2'"),
        (lambda d: d.update(gamma=float("inf")), "config.json: gamma must be a number"),
        (lambda d: d.update(task="4d-static"), "config.json: unknown task '4d-static'; allowed: 1d-static-sin"),
        (lambda d: d.update(switches=5), "config.json: switches must be a string, got 5"),
        (lambda d: d.update(lstm_size=8), "config.json: unknown ppo option(s) ['lstm_size']"),
        (lambda d: d.pop("algorithm"), "config.json: algorithm is missing (one of ppo, dqn"),
    ]:
        save_config(make_config("ppo", "1d-dynamic", total_steps=512), path)
        _refused(_edit(path, edit), schemas.CONFIG_JSON, message)


def test_run_json_schema(tmp_path):
    path = tmp_path / "run.json"
    path.write_text('{"eval_episodes": null, "no_eval": false}')
    assert schemas.load(path, schemas.RUN_JSON) == {"eval_episodes": None, "no_eval": False}
    path.write_text('{"eval_episodes": 0, "no_eval": false}')
    _refused(path, schemas.RUN_JSON, "run.json: eval_episodes must be an int >= 1 or null, got 0")


def test_cell_json_and_eval_json_schemas_read_every_committed_cell(tmp_path):
    committed = sorted((ROOT / "bench" / "results" / "table").glob("*/*/*.json"))
    assert len(committed) > 50
    for path in committed:  # one file per cell: each part against its own file's schema
        record = schemas.load(path, schemas.RAW_CELL_JSON)
        schema.check(record["cell"], schemas.CELL_JSON, path)
        schema.check(record["eval"], schemas.EVAL_JSON, path)
    schemas.load(ROOT / "bench" / "results" / "handcrafted.json", schemas.EVAL_JSON)
    cell = tmp_path / "cell"
    write_cell(cell)
    _refused(
        _edit(cell / "cell.json", lambda d: d["budget"].update(capped="no")),
        schemas.CELL_JSON,
        "cell.json: budget.capped must be true or false, got 'no'",
    )
    _refused(
        _edit(cell / "eval.json", lambda d: d["1d-static-sin (seed 1)"].update(min=-3.0)),
        schemas.EVAL_JSON,
        "eval.json: ['1d-static-sin (seed 1)'].min must be a finite number in [0, 1], got -3.0",
    )
    write_cell(cell)
    _refused(
        _edit(cell / "eval.json", lambda d: d["1d-static-sin (seed 1)"].update(per_design={"t0": {"mean": 2}})),
        schemas.EVAL_JSON,
        "eval.json: ['1d-static-sin (seed 1)'].per_design.t0.mean must be a finite number in [0, 1]",
    )
    (cell / "eval.json").write_text("{}")
    _refused(cell / "eval.json", schemas.EVAL_JSON, "eval.json: it must have at least 1 entries, got 0")


def test_eval_json_refuses_statistics_that_cannot_hold_together(tmp_path):
    """Each bound below holds by construction (`snac_jax.evaluation.summarize`, and an episode
    that lays no brick scores IoU 0), so a row that breaks one was edited or damaged."""
    cell, row = tmp_path / "cell", "1d-static-sin (seed 1)"  # mean 0.7, min 0.1, ci95 [0.65, 0.75], 2 episodes
    strata = {
        "a": {"mean": 0.6, "min": 0.1, "std": 0.0, "episodes": 1},
        "b": {"mean": 0.8, "min": 0.5, "std": 0.0, "episodes": 1},
    }
    write_cell(cell)
    assert schemas.load(_edit(cell / "eval.json", lambda d: d[row].update(per_design=strata)), schemas.EVAL_JSON)
    where = f"eval.json: ['{row}']"
    cases = [
        (dict(min=0.8), f"{where}.min is 0.8, above its mean 0.7"),
        (dict(ci95=[0.72, 0.75]), f"{where}.ci95 [0.72, 0.75] does not hold its mean 0.7"),
        (dict(mean_bricks_used=0.0), f"{where}.mean is 0.7 with mean_bricks_used 0"),
        (dict(per_design={**strata, "b": {**strata["b"], "min": 0.9}}), f"{where}.per_design.b.min is 0.9, above"),
        (dict(per_design={**strata, "b": {**strata["b"], "episodes": 3}}), f"{where}.episodes is 2, its per_design"),
        (dict(per_design={**strata, "b": {**strata["b"], "mean": 0.9}}), f"{where}.mean is 0.7, its per_design"),
        (dict(per_design={**strata, "a": {**strata["a"], "min": 0.2}}), f"{where}.min is 0.1, its per_design"),
    ]
    for change, message in cases:
        write_cell(cell)
        _refused(_edit(cell / "eval.json", lambda d, change=change: d[row].update(change)), schemas.EVAL_JSON, message)
    # within float rounding of the bound: the mean of equal IoUs may come out an ulp below them
    write_cell(cell)
    assert schemas.load(_edit(cell / "eval.json", lambda d: d[row].update(min=0.7 + 1e-12)), schemas.EVAL_JSON)


def test_a_cells_raw_copy_is_checked_part_by_part_naming_the_part_and_the_field(tmp_path):
    from agents.table.files import read_cell, read_raw

    cell = tmp_path / "runs" / "ppo" / "1d-static-sin"
    write_cell(cell)
    copy = tmp_path / "results" / "ppo" / "1d-static-sin.json"
    copy.parent.mkdir(parents=True)
    copy.write_text(read_cell(cell))
    assert read_raw(copy)["eval"] == json.loads((cell / "eval.json").read_text())
    _refused(
        _edit(copy, lambda d: d["cell"]["budget"].update(capped="no")),
        schemas.RAW_CELL_JSON,
        "1d-static-sin.json: cell.budget.capped must be true or false, got 'no'",
    )
    copy.write_text(read_cell(cell))
    _refused(
        _edit(copy, lambda d: d["curve"].append({"chunk": 1, "wall_s": -1.0})),
        schemas.RAW_CELL_JSON,
        "1d-static-sin.json: curve[1].wall_s must be a finite number >= 0",
    )
    copy.write_text(read_cell(cell))
    _refused(
        _edit(copy, lambda d: d["curve"].append({"iou": 0.5})),
        schemas.RAW_CELL_JSON,
        "1d-static-sin.json: curve[1].chunk must be an int >= 0, got None",
    )
    copy.write_text(read_cell(cell))
    _refused(_edit(copy, lambda d: d.pop("eval")), schemas.RAW_CELL_JSON, "1d-static-sin.json: eval is missing")
    # A copy under another cell's name is refused, naming both.
    copy.write_text(read_cell(cell))
    elsewhere = copy.with_name("1d-static-gauss.json")
    copy.rename(elsewhere)
    with pytest.raises(
        ValueError,
        match=r"gauss.json: cell: its algorithm and task \(ppo/1d-static-sin\) are not where it "
        r"stands \(ppo/1d-static-gauss\)",
    ):
        read_raw(elsewhere)


def test_human_record_schema_names_the_line_and_the_field(tmp_path):
    from snac_jax.human import records
    from snac_jax.human.game import GameSession

    session = GameSession("2d-static-sparse", "eval", seed=3, max_steps=3)
    for key in ("space", "right", "space"):
        session.press(key)
    [honest] = session.records
    line = json.loads(honest.to_json())
    assert schema.check(line, schema.HUMAN_RECORD, "h.jsonl:1") is line
    path = tmp_path / "h.jsonl"
    path.write_text(honest.to_json() + "\n" + json.dumps({**line, "iou": 7.5}) + "\n")
    with pytest.raises(
        ValueError, match=r"h.jsonl:2: not a valid human record \(iou must be a finite number in \[0, 1\], got 7.5\)$"
    ):
        records.load_records(path)
    path.write_text(json.dumps({**line, "terminated": "no"}) + "\n")
    with pytest.raises(ValueError, match=r"h.jsonl:1: .*terminated must be true or false, got 'no'"):
        records.load_records(path)
    with pytest.raises(ValueError, match=r"strides must be 1, 2 or 3, got 5 at position 0"):
        records.EpisodeRecord(**{**dataclasses.asdict(honest), "strides": [5, 1, 1]}).validate()
