"""bench/per_design.py: per-test-design rows against the handcrafted policy, checked on a results
tree with numbers set by hand, on its refusals, and on the committed record."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import per_design

RESULTS = Path(__file__).resolve().parent.parent / "bench" / "results"
CELL = RESULTS / "table" / "beyond" / "pqn-belief" / "2d-dynamic-dense.json"
HAND = RESULTS / "handcrafted_report_key.json"
TASK = "2d-dynamic-dense"
D0, D1 = f"{TASK}-test0", f"{TASK}-test1"


def _agreeing(row: dict) -> dict:
    """`row` with its statistics and those of its `per_design` made to agree, as the record's schema
    requires: its episodes (the protocol's) split evenly over the designs kept, its mean theirs, its
    minimum their least, an interval holding the mean."""
    strata = {d: {**s, "episodes": row["episodes"] // len(row["per_design"])} for d, s in row["per_design"].items()}
    mean = sum(s["mean"] for s in strata.values()) / len(strata)
    least = min(s["min"] for s in strata.values())
    return {**row, "per_design": strata, "mean": mean, "min": least, "ci95": [mean, mean]}


def _tree(tmp: Path, seeds: list[tuple[float, float]], hand: tuple[float, float], hand_seed: int | None = None) -> Path:
    """A results directory holding a copy of a committed cell whose three seeds score `seeds`
    (test0, test1), and a handcrafted record scoring `hand`, both over the two designs only."""
    raw = json.loads(CELL.read_text())
    for row, means in zip(raw["eval"].values(), seeds, strict=True):
        row["per_design"] = {d: {**row["per_design"][d], "mean": m, "min": 0.0} for d, m in zip((D0, D1), means)}
    raw["eval"] = {name: _agreeing(row) for name, row in raw["eval"].items()}
    cell = tmp / "results" / "table" / "beyond" / "pqn-belief" / f"{TASK}.json"
    cell.parent.mkdir(parents=True)
    cell.write_text(json.dumps(raw))
    record = json.loads(HAND.read_text())
    row = record[TASK]
    row["per_design"] = {d: {**row["per_design"][d], "mean": m, "min": 0.0} for d, m in zip((D0, D1), hand)}
    row["seed"] = row["seed"] if hand_seed is None else hand_seed
    record[TASK] = _agreeing(row)
    (tmp / "results" / "handcrafted_report_key.json").write_text(json.dumps(record))
    return tmp / "results"


def _files(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def test_rows_by_hand(tmp_path, capsys):
    results = _tree(tmp_path, [(0.6, 0.3), (0.7, 0.5), (0.8, 0.2)], (0.5, 0.4))
    before = _files(tmp_path)
    out = tmp_path / "out"
    assert (
        per_design.main(
            ["--preset", "beyond", "--algorithm", "pqn-belief", "--results", str(results), "--out", str(out)]
        )
        == 0
    )
    assert _files(tmp_path) - before == {"out", "out/per_design.json", "out/per_design.md"}
    task = json.loads((out / "per_design.json").read_text())["tasks"][TASK]
    first, second = task["rows"]
    assert first["design"] == D0 and first["seeds_vs_handcrafted"] == "above"
    assert (first["mean"], first["lowest_seed"], first["highest_seed"]) == pytest.approx((0.7, 0.6, 0.8))
    assert (first["handcrafted"], first["difference"]) == pytest.approx((0.5, 0.2))
    assert second["design"] == D1 and second["seeds_vs_handcrafted"] == "mixed"  # 0.5 above 0.4, 0.3 and 0.2 below
    assert (second["mean"], second["lowest_seed"], second["highest_seed"]) == pytest.approx((1 / 3, 0.2, 0.5))
    assert second["difference"] == pytest.approx(1 / 3 - 0.4)
    assert task["summary"] == {"above": 1, "below": 0, "mixed": 1}
    text = (out / "per_design.md").read_text()
    assert text.startswith("`python bench/per_design.py --preset beyond") and text in capsys.readouterr().out
    assert f"| {D0} | 0.700 | 0.600 | 0.800 | 0.500 | +0.200 | above |" in text


def test_every_seed_below(tmp_path):
    results = _tree(tmp_path, [(0.1, 0.3), (0.2, 0.3), (0.3, 0.3)], (0.4, 0.3))
    per_design.main(
        ["--preset", "beyond", "--algorithm", "pqn-belief", "--results", str(results), "--out", str(tmp_path / "o")]
    )
    rows = json.loads((tmp_path / "o" / "per_design.json").read_text())["tasks"][TASK]["rows"]
    assert [r["seeds_vs_handcrafted"] for r in rows] == ["below", "mixed"]  # a seed equal to it is not above


@pytest.mark.parametrize(
    "args, named",
    [
        (["--preset", "nope", "--algorithm", "pqn-belief"], "presets present: beyond"),
        (["--preset", "beyond", "--algorithm", "nope"], "algorithms present: pqn-belief"),
    ],
)
def test_a_missing_directory_is_one_line(tmp_path, args, named):
    results = _tree(tmp_path, [(0.5, 0.5)] * 3, (0.5, 0.5))
    with pytest.raises(SystemExit) as exit_:
        per_design.main([*args, "--results", str(results), "--out", str(tmp_path / "out")])
    message = str(exit_.value.code)
    assert named in message and "\n" not in message
    assert not (tmp_path / "out").exists()


def test_a_different_key_is_one_line(tmp_path):
    results = _tree(tmp_path, [(0.5, 0.5)] * 3, (0.5, 0.5), hand_seed=0)
    with pytest.raises(SystemExit) as exit_:
        per_design.main(
            [
                "--preset",
                "beyond",
                "--algorithm",
                "pqn-belief",
                "--results",
                str(results),
                "--out",
                str(tmp_path / "out"),
            ]
        )
    message = str(exit_.value.code)
    assert "evaluation key 1000003" in message and "with 0" in message and "\n" not in message
    assert not (tmp_path / "out").exists()


def test_different_designs_are_refused(tmp_path):
    results = _tree(tmp_path, [(0.5, 0.5)] * 3, (0.5, 0.5))
    record = json.loads((results / "handcrafted_report_key.json").read_text())
    record[TASK]["per_design"].pop(D1)
    record[TASK] = _agreeing(record[TASK])
    (results / "handcrafted_report_key.json").write_text(json.dumps(record))
    with pytest.raises(SystemExit, match="only the same designs are comparable"):
        per_design.main(
            [
                "--preset",
                "beyond",
                "--algorithm",
                "pqn-belief",
                "--results",
                str(results),
                "--out",
                str(tmp_path / "out"),
            ]
        )


def test_the_committed_record(tmp_path):
    """pqn-belief's beyond cell against the handcrafted policy scored with the same key."""
    out = tmp_path / "out"
    assert (
        per_design.main(
            [
                "--preset",
                "beyond",
                "--algorithm",
                "pqn-belief",
                "--task",
                TASK,
                "--handcrafted",
                str(HAND),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = json.loads((out / "per_design.json").read_text())["tasks"][TASK]["rows"]
    assert [r["design"] for r in rows] == [f"{TASK}-test{k}" for k in range(10)]
    seeds = list(json.loads(CELL.read_text())["eval"].values())
    for r in rows:
        assert r["mean"] == pytest.approx(sum(s["per_design"][r["design"]]["mean"] for s in seeds) / len(seeds))
    # 200 episodes on each design: the mean over designs is the seeds' eval means averaged
    assert sum(r["mean"] for r in rows) / len(rows) == pytest.approx(sum(s["mean"] for s in seeds) / len(seeds))
    assert sorted(p.name for p in out.iterdir()) == ["per_design.json", "per_design.md"]
