"""bench/multi_ippo.py: IPPO's rows of multi.md from the record, checked on cells with numbers set by hand."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import multi_ippo

RECORD = Path(__file__).resolve().parent.parent / "bench" / "results" / "table" / "multi" / "ippo"


def _cell(tmp: Path, name: str, robots: int, ious: list[float], lengths: list[float]) -> None:
    """A copy of a committed cell with its robots and its seeds' IoUs and lengths set by hand (each
    row's other statistics made to agree with its IoU, as the record's schema requires)."""
    raw = json.loads(sorted(RECORD.glob("*.json"))[0].read_text())
    raw["config"]["robots"] = robots
    rows = list(raw["eval"].values())[: len(ious)]
    raw["eval"] = {
        f"x (seed {i})": {
            **r,
            "mean": iou,
            "mean_length": length,
            "min": min(r["min"], iou),
            "ci95": [iou, iou],
            "per_design": {},
        }
        for i, (r, iou, length) in enumerate(zip(rows, ious, lengths))
    }
    (tmp / name).write_text(json.dumps(raw))


def test_rows_by_hand(tmp_path):
    record = tmp_path / "record"
    record.mkdir()
    _cell(record, "a.base.json", 1, [0.2, 0.4, 0.6], [400.0, 300.0, 200.0])
    _cell(record, "a.robots-2.json", 2, [0.5, 0.5, 0.5], [150.0, 150.0, 150.0])
    assert multi_ippo.main(["--record", str(record), "--out", str(tmp_path / "out")]) == 0
    rows = json.loads((tmp_path / "out" / "multi_ippo.json").read_text())["rows"]
    one, two = rows
    assert (one["robots"], two["robots"]) == (1, 2)
    assert one["mean_iou"] == pytest.approx(0.4) and one["mean_length"] == pytest.approx(300.0)
    assert one["ci95"][0] <= 0.4 <= one["ci95"][1] and one["ci95"][0] >= 0.2 and one["ci95"][1] <= 0.6
    assert two["ci95"] == pytest.approx([0.5, 0.5])
    assert "| 0.50 |" in (tmp_path / "out" / "multi_ippo.md").read_text()  # 150 steps against 300


def test_an_empty_record_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        multi_ippo.main(["--record", str(tmp_path), "--out", str(tmp_path / "out")])
    assert exit_.value.code == 2 and "no cells there" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
