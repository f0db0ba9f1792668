"""Facts about the code's structure that anyone can check with grep and the import graph: the
library never imports the learners, no module imports itself back through others, modules stay
short, and code comments do not narrate measurements (those live in bench/results/*.md)."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).parents[1]
PACKAGES = ("snac_jax", "agents")
MAX_LINES = 400


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))}


def _imports(path: Path, modules: dict[str, Path]) -> set[str]:
    """Project modules `path` imports anywhere in its body (function-level imports included)."""
    found = set()
    package = _module_name(path) if path.name == "__init__.py" else _module_name(path).rpartition(".")[0]
    tree = ast.parse(path.read_text())
    typing_only = {
        id(inner)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
        for inner in ast.walk(node)
    }  # annotations only: nothing is imported at run time
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(
                    package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else [])
                )
            names = [base] + [f"{base}.{alias.name}" for alias in node.names]
        else:
            continue
        for name in names:
            while name and name not in modules:
                name = name.rpartition(".")[0]
            if name:
                found.add(name)
    return found - {_module_name(path)}


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(path, modules) for name, path in modules.items()}


def test_the_library_never_imports_the_learners():
    offenders = {
        m: sorted(i for i in deps if i.split(".")[0] == "agents")
        for m, deps in _graph().items()
        if m.split(".")[0] == "snac_jax"
    }
    assert not {m: d for m, d in offenders.items() if d}


def test_no_import_circles():
    graph = _graph()
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(node):  # Tarjan's strongly connected components
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for dep in graph[node]:
            if dep not in index:
                visit(dep)
                low[node] = min(low[node], low[dep])
            elif dep in on_stack:
                low[node] = min(low[node], index[dep])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    # A package's __init__ that re-exports its submodules is not a circle of logic.
    cycles = [c for c in cycles if not all(m == c[0] or m.startswith(c[0] + ".") for m in c)]
    assert not cycles


def test_no_module_is_over_the_line_limit():
    long = {
        str(p.relative_to(ROOT)): n
        for package in (*PACKAGES, "bench")
        for p in (ROOT / package).rglob("*.py")
        if (n := len(p.read_text().splitlines())) > MAX_LINES
    }
    assert not long


# Phrases of a lab notebook: numbered log entries, pilots, machines, measured scores, speeds and
# wall times, a curve's progress. Data files and code state a setting and its reason; the
# measurements behind it live on the learner's page under bench/results/.
_COUNT = (
    r"(?:[\d.,]+(?:\s?[-–]\s?[\d.,]+)?|an?|one|two|three|four|five|six|seven|eight|nine|ten|\w+teen|\w+ty|several|many)"
)
NARRATION = re.compile(
    r"\bsessions? \d|\b(?:issue|log entry|entry) #?\d|\bpilots?\b|"
    r"\b(older|slower|faster|busy) (cpu|machine|vm)\b|\bgreedy (protocol )?iou\b|"
    r"\d[\d.,]*\s?[kM]? env-steps/s|\bmeasured (at|on|in)\b|\b0\.\d{3}\b|"
    rf"\btook (?:about |some |roughly |over |under |nearly |almost )?{_COUNT} (?:seconds?|minutes?|hours?|days?|s|min|h)\b|"
    rf"\b{_COUNT} times (?:slower|faster)\b|\bstill (?:rising|climbing|improving)\b|\bwas level with\b",
    re.IGNORECASE,
)
# Prose of the learners and the docs (the results pages under bench/results/ are where measurements go).
NARRATION_DOCS = ("agents", "docs")


def _toml_prose(text: str) -> list[tuple[int, str]]:
    """(line, text) of each comment and string value of a TOML file: its numbers are settings,
    its prose is what the check reads."""
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        found += [(number, m.group(0)) for m in re.finditer(r'"(?:[^"\\]|\\.)*"|\'[^\']*\'', line)]
        code = re.sub(r'"(?:[^"\\]|\\.)*"|\'[^\']*\'', "", line)
        if "#" in code:
            found.append((number, code[code.index("#") :]))
    return found


def test_the_narration_check_reads_its_phrases():
    for narrated in (
        "Session 21's pilot",
        "took 10 minutes for three seeds",
        "took 56-57 minutes",
        "ran about ten times slower",
        "several times slower",
        "was still rising at 20M",
        "64 was level with 128",
        "issue 21's ablation",
        "(beyond.md, sessions 11-12)",
    ):
        assert NARRATION.search(narrated), narrated
    for plain in ("the 30-minute table cell", "three times the step size", "the issue tracker", "a pilot_light"):
        assert not NARRATION.search(plain), plain
    assert _toml_prose('x = 0.001  # lr, chosen on 1d-static-sin\ns = "took 5 minutes"') == [
        (1, "# lr, chosen on 1d-static-sin"),
        (2, '"took 5 minutes"'),
    ]


def test_data_files_and_docs_do_not_narrate_measurements():
    found = []
    for path in sorted(
        p for folder in NARRATION_DOCS for p in (ROOT / folder).rglob("*") if p.suffix in (".toml", ".md")
    ):
        text = path.read_text()
        lines = _toml_prose(text) if path.suffix == ".toml" else list(enumerate(text.splitlines(), 1))
        found += [f"{path.relative_to(ROOT)}:{n}: {line.strip()[:120]}" for n, line in lines if NARRATION.search(line)]
    assert not found, "\n".join(found)


def test_code_comments_do_not_narrate_measurements():
    found = []
    for package in (*PACKAGES, "bench"):
        for path in (ROOT / package).rglob("*.py"):
            tokens = tokenize.generate_tokens(io.StringIO(path.read_text()).readline)
            for token in tokens:
                if token.type == tokenize.COMMENT and NARRATION.search(token.string):
                    found.append(f"{path.relative_to(ROOT)}:{token.start[0]}: {token.string.strip()}")
    assert not found, "\n".join(found)


def test_docstrings_do_not_narrate_measurements():
    found = []
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                    doc = ast.get_docstring(node) or ""
                    if match := NARRATION.search(doc):
                        found.append(f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 1)}: ...{match.group(0)}...")
    assert not found, "\n".join(found)


LEARNER_MODULES = {
    "agents.learners.ppo",
    "agents.learners.pqn",
    "agents.learners.dqn",
    "agents.learners.drqn",
    "agents.learners.drqn_her",
    "agents.learners.rainbow",
    "agents.learners.sac",
    "agents.common.offpolicy",
    "agents.research.ppo_privileged",
    "agents.research.drqn_aux",
    "agents.research.pqn_aux",
    "agents.research.pqn_belief",
}
# Names through which a variant (ppo-privileged, pqn-aux, drqn-aux, pqn-belief) would reach into its
# base learner: hook methods that do nothing in the base, and arguments the base passes and ignores.
VARIANT_HOOKS = (
    "_privileged",
    "_auxiliary_losses",
    "auxiliary_losses",
    "_auxiliary_targets",
    "_step",
    "privileged",
    "auxiliary_heads",
    "sown",
)


def test_ppo_and_pqn_fork_alone():
    """agents/learners/ppo.py and agents/learners/pqn.py import no other learner (only the library modules:
    networks, targets, inputs, config) and carry no hook for a variant: the variants build on
    them in their own files."""
    graph = _graph()
    for name in ("agents.learners.ppo", "agents.learners.pqn"):
        assert not graph[name] & (LEARNER_MODULES - {name}), name
    for path in ("agents/learners/ppo.py", "agents/learners/pqn.py", "agents/learners/dqn.py"):
        text = (ROOT / path).read_text()
        found = {hook: len(re.findall(rf"\b{hook}\b", text)) for hook in VARIANT_HOOKS}
        assert not {hook: n for hook, n in found.items() if n}, path
