"""The record holds together: every link of a learner page to a file of the record points at a
file that is there, every tuned setting names a page that exists, and every committed cell is the
run its preset trains today."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
PAGES = ("ppo.md", "pqn.md", "dqn.md", "rainbow.md", "sac.md", "beyond.md")


def test_every_learner_page_exists_and_its_links_into_the_record_resolve():
    missing = []
    for name in PAGES:
        page = RESULTS / name
        assert page.is_file(), f"bench/results/{name} is missing (agents/tuned/*.toml name it as their result)"
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" not in target and not (page.parent / target).exists():
                missing.append(f"{name} -> {target}")
    assert not missing, "links to files that are not there:\n" + "\n".join(missing)


def test_the_tuned_settings_name_pages_that_exist():
    import tomllib

    for path in sorted((ROOT / "agents" / "tuned").glob("*.toml")):
        for task, entry in tomllib.loads(path.read_text()).items():
            result = entry.get("result") if isinstance(entry, dict) else None
            if result is not None:
                assert (ROOT / result).is_file(), f"{path.name} [{task}]: result {result} is not a file"


def test_every_committed_cell_is_what_its_preset_trains_now(tmp_path):
    """A cell's raw copy holds the config.json that `snac table --preset P` trains for that cell
    today (the table's own rule for the same run, `plan.settings_differ`), so a changed tuned entry
    cannot silently redefine an ablation whose arms were measured on the old one. The one exception:
    a cell trained under the wall-time cap the table once had (its cell.json's budget requested
    more than it trained) differs in total_steps alone. Arms that only score another arm's run
    again (`evaluation`) train nothing of their own."""
    import json

    from agents.table.plan import make_plan, settings_differ
    from agents.table.presets import load_presets
    from agents.training.registry import ALGORITHMS, config_from_json
    from snac_jax.paper import PAPER_TASKS

    checked, drifted = 0, []
    for name, preset in load_presets().items():
        arms = [v.name for v in preset.variants if not v.evaluation] or None
        cells = make_plan(
            preset, list(preset.algorithms or ALGORITHMS), list(preset.tasks or PAPER_TASKS), None, tmp_path, arms=arms
        )
        for cell in cells:
            record = RESULTS / "table" / name / cell.algorithm / f"{cell.directory.name}.json"
            if not record.is_file():
                continue
            checked += 1
            raw = json.loads(record.read_text())
            differ = settings_differ(cell, config_from_json(raw["config"]))
            if raw["cell"]["budget"]["requested"] > raw["cell"]["budget"]["env_steps"]:  # capped
                differ = [k for k in differ if k != "total_steps"]
            if differ:
                drifted.append(f"{record.relative_to(ROOT)}: {', '.join(differ)}")
    assert checked > 100  # the paper, tuned, beyond and ablation presets' cells
    assert not drifted, "records their preset no longer trains:\n" + "\n".join(drifted)
