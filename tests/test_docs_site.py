"""The docs site's link rewriting (docs/hooks/repository_links.py): a relative link that works
when browsing the repository points at the same file on the site, where docs/ is the root, the
README the home page and every other linked file keeps its repository path."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

pytest.importorskip("mkdocs")

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("repository_links", ROOT / "docs" / "hooks" / "repository_links.py")
links = importlib.util.module_from_spec(spec)
spec.loader.exec_module(links)


def test_site_paths_put_docs_at_the_root_and_the_readme_home():
    assert links.site_path("docs/usage.md") == "usage.md"
    assert links.site_path("README.md") == "index.md"
    assert links.site_path("bench/results/ppo.md") == "bench/results/ppo.md"
    assert links.site_path("agents/tuned/ppo.toml") == "agents/tuned/ppo.toml"


def test_links_are_rewritten_from_repository_paths_to_site_paths():
    docs_page = "See [t](../bench/results/table.md#how) and [s](SPEC.md), [w](https://x.org/a.md), [h](#here).\n"
    assert links.rewrite_links(docs_page, "docs/usage.md", set()) == (
        "See [t](bench/results/table.md#how) and [s](SPEC.md), [w](https://x.org/a.md), [h](#here).\n"
    )
    readme = "[spec](docs/SPEC.md#1-tasks) ![gif](docs/a.gif) [ppo](bench/results/ppo.md)\n"
    assert links.rewrite_links(readme, "README.md", set()) == (
        "[spec](SPEC.md#1-tasks) ![gif](a.gif) [ppo](bench/results/ppo.md)\n"
    )
    result_page = '[toml](../../agents/tuned/ppo.toml) [usage](../../docs/usage.md "title") [d](table/x/)\n'
    assert links.rewrite_links(result_page, "bench/results/ppo.md", {"bench/results/table/x"}) == (
        '[toml](../../agents/tuned/ppo.toml) [usage](../../usage.md "title") [d](table/x/index.md)\n'
    )


def test_links_inside_fenced_code_are_left_alone():
    text = "[a](../README.md)\n```\n[b](../README.md)\n```\n[c](../README.md)\n"
    assert links.rewrite_links(text, "docs/usage.md", set()) == (
        "[a](index.md)\n```\n[b](../README.md)\n```\n[c](index.md)\n"
    )
    assert links.link_targets(text) == ["../README.md", "../README.md"]


def test_linked_files_follow_the_pages_links_through_the_repository(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "usage.md").write_text("[r](../bench/results/a.md) [self](SPEC.md)\n")
    results = tmp_path / "bench" / "results"
    (results / "raw").mkdir(parents=True)
    (results / "a.md").write_text("[fig](a.png) [raw](raw/) [gone](missing.json) [up](../../../outside.md)\n")
    (results / "a.png").write_bytes(b"png")
    (results / "raw" / "cell.json").write_text("{}")
    (tmp_path / "README.md").write_text("[usage](docs/usage.md)\n")
    files, folders = links.linked_files(tmp_path, ["README.md", "docs/usage.md"])
    assert files == {"bench/results/a.md", "bench/results/a.png", "bench/results/raw/cell.json"}
    assert folders == {"bench/results/raw"}
