"""The docs site shows the repository's Markdown as GitHub does: every relative link that works
when browsing the repository works on the site.

`docs/` is the site's root; the README is its home page; every other file of the repository that a
page links to (the results pages under `bench/results/`, their figures and raw JSON files, a tuned
settings file) is added to the site at its repository path, and a link to a folder becomes a
generated page listing the folder's files. Each link is rewritten from its repository path to that
file's place on the site, so `mkdocs build --strict` checks the same links a reader follows on
GitHub, and a page under `bench/results/` stays the one home of its numbers.

mkdocs loads this file through `hooks:` in mkdocs.yml; it is not part of the package.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File, Files

DOCS = "docs"
HOME = "README.md"
# The pages outside docs/ that the site shows, besides the README: the results.
RESULT_PAGES = "bench/results/*.md"
# A Markdown link or image target: `](target)` or `](target "title")`.
# The linked folders of this build, filled by on_files for on_page_markdown.
_FOLDERS: set[str] = set()
LINK = re.compile(r"(\]\()([^)\s]+)((?:\s+\"[^\"]*\")?\))")


def site_path(repository_path: str) -> str:
    """Where a repository file sits on the site: docs/ is the root, the README its home page,
    anything else keeps its repository path."""
    if repository_path == HOME:
        return "index.md"
    prefix = DOCS + "/"
    return repository_path[len(prefix) :] if repository_path.startswith(prefix) else repository_path


def folder_page(repository_path: str) -> str:
    """The generated page that lists a linked folder's files."""
    return site_path(repository_path.rstrip("/")) + "/index.md"


def is_relative(target: str) -> bool:
    return not (target.startswith(("#", "/", "mailto:")) or "://" in target)


def link_targets(markdown: str) -> list[str]:
    """The relative link targets of a page, outside fenced code, without their anchors."""
    targets = []
    for part in _outside_fences(markdown):
        targets += [m.group(2).split("#")[0] for m in LINK.finditer(part) if is_relative(m.group(2))]
    return [t for t in targets if t]


def rewrite_links(markdown: str, page_repository_path: str, folders: set[str]) -> str:
    """The page with each relative link pointing where its target sits on the site."""
    page_site_dir = posixpath.dirname(site_path(page_repository_path))
    page_dir = posixpath.dirname(page_repository_path)

    def rewrite(match: re.Match) -> str:
        target = match.group(2)
        if not is_relative(target):
            return match.group(0)
        path, _, anchor = target.partition("#")
        if not path:
            return match.group(0)
        resolved = posixpath.normpath(posixpath.join(page_dir, path))
        destination = folder_page(resolved) if resolved in folders else site_path(resolved)
        new = posixpath.relpath(destination, page_site_dir or ".") + (f"#{anchor}" if anchor else "")
        return match.group(1) + new + match.group(3)

    parts = _split_fences(markdown)
    return "".join(LINK.sub(rewrite, text) if not fenced else text for text, fenced in parts)


def _split_fences(markdown: str) -> list[tuple[str, bool]]:
    """The page cut into runs of lines: (text, inside a ``` or ~~~ fence)."""
    parts: list[tuple[str, bool]] = []
    inside = False
    for line in markdown.splitlines(keepends=True):
        opens_or_closes = line.lstrip().startswith(("```", "~~~"))
        fenced = inside or opens_or_closes
        if parts and parts[-1][1] == fenced:
            parts[-1] = (parts[-1][0] + line, fenced)
        else:
            parts.append((line, fenced))
        if opens_or_closes:
            inside = not inside
    return parts


def _outside_fences(markdown: str) -> list[str]:
    return [text for text, fenced in _split_fences(markdown) if not fenced]


def linked_files(root: Path, pages: list[str]) -> tuple[set[str], set[str]]:
    """Every repository file and folder outside docs/ that the pages link to, following the links
    of the Markdown files found on the way: (files, folders), as repository paths."""
    files, folders, queue, seen = set(), set(), list(pages), set()
    while queue:
        page = queue.pop()
        if page in seen:
            continue
        seen.add(page)
        for target in link_targets((root / page).read_text()):
            resolved = posixpath.normpath(posixpath.join(posixpath.dirname(page), target))
            if resolved.startswith("..") or resolved.startswith(DOCS + "/"):
                continue  # outside the repository, or a docs page mkdocs finds itself
            if (root / resolved).is_dir():
                folders.add(resolved)
                files.update(str(p.relative_to(root)) for p in sorted((root / resolved).iterdir()) if p.is_file())
            elif (root / resolved).is_file():
                files.add(resolved)
                if resolved.endswith(".md"):
                    queue.append(resolved)
    return files, folders


def _root(config) -> Path:
    return Path(config.config_file_path).resolve().parent


def _repository_path(file: File) -> str:
    return getattr(file, "repository_path", DOCS + "/" + file.src_uri)


def on_files(files: Files, config) -> Files:
    root = _root(config)
    results = sorted(str(p.relative_to(root)) for p in root.glob(RESULT_PAGES))
    docs_pages = [DOCS + "/" + f.src_uri for f in files if f.src_uri.endswith(".md")]
    linked, folders = linked_files(root, [HOME, *results, *docs_pages])
    for path in sorted({HOME, *results, *linked}):
        file = File.generated(config, site_path(path), abs_src_path=str(root / path))
        file.repository_path = path
        files.append(file)
    for folder in sorted(folders):
        names = sorted(p.name for p in (root / folder).iterdir() if p.is_file())
        listing = "\n".join(f"- [{name}]({name})" for name in names)
        file = File.generated(config, folder_page(folder), content=f"# `{folder}/`\n\n{listing}\n")
        file.repository_path = folder + "/index.md"
        files.append(file)
    _FOLDERS.clear()
    _FOLDERS.update(folders)
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    return rewrite_links(markdown, _repository_path(page.file), _FOLDERS)
