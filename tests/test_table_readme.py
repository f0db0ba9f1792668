"""The README's learner table: generated from table.json, replaced between its markers only."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from agents.table.readme import BEGIN, END, learner_table, replace_block
from agents.table.report import build
from tests.table_cells import cell_files as _files

ROOT = Path(__file__).resolve().parents[1]


def test_rows_by_hand():
    raw = {
        "ppo": {
            "2d-static-dense": _files("ppo", "2d-static-dense", [0.7, 0.8, 0.9], 1_000_000),
            "2d-static-sparse": _files("ppo", "2d-static-sparse", [0.1, 0.2, 0.3], 500_000, below=True),
        }
    }
    hand = {"2d-static-dense": {"mean": 0.949, "seed": 0}}
    text = learner_table({"paper": build(raw, handcrafted=hand, preset="paper", reps=200)})
    rows = text.splitlines()
    assert rows[0].startswith("| learner (preset) | env steps per seed | 1d-static | 1d-dynamic |")
    assert rows[2].startswith("| human (paper) | | 0.830 | 0.881 | 0.803 | 0.606 |")
    assert rows[3].startswith("| handcrafted, ours (paper) | | — | — | 0.949 (0.953) | — |")
    # 2d-static-dense: seeds .7 .8 .9, mean .8, every bootstrap mean between .7 and .9, all above the
    # paper's 0.682: bold. 2d-static-sparse: mean .2 with the paper's .308 above its interval: plain.
    ppo = rows[4]
    assert ppo.startswith("| ppo (paper preset) | 1M, 500k* | — (0.776) | — (0.791) | **0.800 [")
    assert "| 0.200 [" in ppo and "] (0.308) |" in ppo and ppo.count("**") == 2
    raw = {"ppo-privileged": {"2d-static-sparse": _files("ppo-privileged", "2d-static-sparse", [0.4, 0.5], 1000)}}
    text = learner_table({"paper": build(raw, handcrafted={}, preset="paper", reps=200)})
    assert "| ppo-privileged (paper preset; brackets: the paper's ppo) | 1k | — (0.776) |" in text


def test_replace_block_keeps_the_rest_and_refuses_a_readme_without_markers():
    text = f"# title\n\nbefore\n{BEGIN}\nold table\n{END}\nafter\n"
    assert replace_block(text, "new table") == f"# title\n\nbefore\n{BEGIN}\nnew table\n{END}\nafter\n"
    with pytest.raises(ValueError, match="the README has no generated learner table"):
        replace_block("# no markers\n", "x")
    with pytest.raises(ValueError, match="the README has no generated learner table"):
        replace_block(f"{END}\n{BEGIN}\n", "x")


def test_the_committed_readme_table_is_the_one_table_json_gives():
    tables = json.loads((ROOT / "bench" / "results" / "table.json").read_text())
    readme = (ROOT / "README.md").read_text()
    assert replace_block(readme, learner_table(tables)) == readme, (
        "README.md's learner table is stale: run `snac table --report --readme README.md`"
    )


@pytest.mark.slow
def test_cli_writes_the_readme_only_with_report(tmp_path, capsys):
    from snac_jax.cli import main

    results = tmp_path / "results"
    shutil.copytree(ROOT / "bench" / "results" / "table", results / "table")
    shutil.copyfile(ROOT / "bench" / "results" / "handcrafted.json", results / "handcrafted.json")
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{BEGIN}\nstale\n{END}\nrest\n")
    (tmp_path / "runs").mkdir()  # a --runs-dir given must exist
    args = [
        "table",
        "--preset",
        "paper",
        "--runs-dir",
        str(tmp_path / "runs"),
        "--results-dir",
        str(results),
        "--readme",
        str(readme),
    ]
    assert main(args) == 2 and "--readme goes with --report" in capsys.readouterr().err
    assert main(args + ["--report", "--arms", "base"]) == 2 and "leave --arms out" in capsys.readouterr().err
    (tmp_path / "plain.md").write_text("no markers\n")
    assert main(args[:-1] + [str(tmp_path / "plain.md"), "--report"]) == 2
    assert "no generated learner table" in capsys.readouterr().err and not (results / "table.md").exists()
    assert main(args + ["--report"]) == 0
    text = readme.read_text()
    assert text.startswith(f"intro\n{BEGIN}\n| learner (preset) |") and text.endswith(f"\n{END}\nrest\n")
    assert "stale" not in text and "| ppo (paper preset) |" in text
