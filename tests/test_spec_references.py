"""Every `SPEC §n` cited in the code and docs resolves to a section heading of docs/SPEC.md."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SPEC = ROOT / "docs" / "SPEC.md"
SCANNED_DIRS = ("snac_jax", "agents", "bench", "tests", "notebooks")
SCANNED_FILES = ("README.md",)
SUFFIXES = {".py", ".md", ".ipynb"}

# "SPEC §6", "SPEC §2-6" (also with an en dash or spaces around the dash).
REFERENCE = re.compile(r"SPEC §(\d+)(?:\s*[-\u2013]\s*§?(\d+))?")
# "## §6 Observation" (any heading level).
HEADING = re.compile(r"^#{1,6}\s+§(\d+)\b", re.MULTILINE)


def scanned_files() -> list[Path]:
    files = [ROOT / name for name in SCANNED_FILES if (ROOT / name).is_file()]
    for directory in SCANNED_DIRS:
        files += sorted(p for p in (ROOT / directory).rglob("*") if p.suffix in SUFFIXES and p.is_file())
    return files


def references() -> dict[int, list[str]]:
    """Section number -> places ("path:line") that cite it; a range cites every number in it."""
    cited: dict[int, list[str]] = {}
    for path in scanned_files():
        text = path.read_text(encoding="utf-8", errors="replace")
        for match in REFERENCE.finditer(text):
            low = int(match.group(1))
            high = int(match.group(2)) if match.group(2) else low
            line = text.count("\n", 0, match.start()) + 1
            place = f"{path.relative_to(ROOT)}:{line}"
            assert low <= high, f"{place}: reversed range {match.group(0)!r}"
            for number in range(low, high + 1):
                cited.setdefault(number, []).append(place)
    return cited


def spec_sections() -> list[int]:
    return [int(n) for n in HEADING.findall(SPEC.read_text(encoding="utf-8"))]


def test_spec_exists_with_unique_sections():
    assert SPEC.is_file(), f"{SPEC.relative_to(ROOT)} is missing"
    sections = spec_sections()
    assert sections, "docs/SPEC.md has no '## §n' headings"
    duplicates = sorted({n for n in sections if sections.count(n) > 1})
    assert not duplicates, f"docs/SPEC.md repeats section headings {duplicates}"


def test_every_spec_reference_resolves():
    cited = references()
    assert cited, "no SPEC references found: the scan is broken"
    sections = set(spec_sections())
    missing = {n: places for n, places in sorted(cited.items()) if n not in sections}
    assert not missing, "SPEC sections cited but not in docs/SPEC.md: " + "; ".join(
        f"§{n} ({', '.join(places[:3])}{', ...' if len(places) > 3 else ''})" for n, places in missing.items()
    )
