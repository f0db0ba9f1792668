"""The record stays readable: `bench/results/` is the current results, not a lab notebook (a
bounded number of files; pilots and superseded runs live in git history), the README stays a
front page, and the README and docs/ cite no numbered log entry (a reader cannot follow one:
the pages name a commit instead). Every link of a learner page to a file of the record points at
a file that is there, and every committed cell is the run its preset trains today."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
MAX_RESULT_FILES = 200
MAX_README_LINES = 300
LOG_CITATION = re.compile(r"\bsession \d+|\bissue \d+|\blog entry \d+|\bsessions \d+", re.IGNORECASE)
PAGES = ("ppo.md", "pqn.md", "dqn.md", "rainbow.md", "sac.md", "beyond.md")


def test_the_results_folder_holds_at_most_200_files():
    files = [p for p in RESULTS.rglob("*") if p.is_file()]
    assert len(files) <= MAX_RESULT_FILES, (
        f"bench/results holds {len(files)} files, more than {MAX_RESULT_FILES}: delete pilots and superseded runs "
        "(git keeps them; a page may name the commit)"
    )


def test_the_readme_is_at_most_300_lines():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines; move detail to docs/ or a page"


def test_readme_and_docs_cite_no_numbered_log_entry():
    found = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            found += [f"{path.relative_to(ROOT)}:{number}: {m.group(0)!r}" for m in LOG_CITATION.finditer(line)]
    assert not found, "numbered log entries cited (name a page or a commit instead):\n" + "\n".join(found)


def test_the_log_citation_pattern_catches_what_it_is_for():
    for text in ("Session 29", "(issue 19)", "log entry 12", "rainbow.md, sessions 24-26"):
        assert LOG_CITATION.search(text), text
    for text in ("the session's CPU", "an issue with the seeds", "29 sessions"):
        assert not LOG_CITATION.search(text), text


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
    today (the table's own rule for the same run, `plan._settings_differ`), so a changed tuned entry
    cannot silently redefine an ablation whose arms were measured on the old one; a smaller budget
    is the rule's one exception (a run trained under the wall-time cap the table once had, kept as
    it is). Arms that only score another arm's run again (`evaluation`) train nothing of their own."""
    import json

    from agents.table.plan import _settings_differ, make_plan
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
            stored = config_from_json(json.loads(record.read_text())["config"])
            differ = _settings_differ(cell, stored)
            if differ:
                drifted.append(f"{record.relative_to(ROOT)}: {', '.join(differ)}")
    assert checked > 100  # the paper, tuned, beyond and ablation presets' cells
    assert not drifted, "records their preset no longer trains:\n" + "\n".join(drifted)
